"""Typed errors of the LED controller client. Each message names the port and the command."""

from __future__ import annotations


class ControllerError(Exception):
    """Base of every LED controller error."""


class ControllerTimeout(ControllerError):
    """The controller did not answer within the timeout, after every retry."""


class CorruptReply(ControllerError):
    """Replies kept failing their checksum or shape (or the controller kept NAKing), after every retry."""


class DeviceGone(ControllerError):
    """The serial port cannot be opened, or it vanished (unplugged) while in use."""


class CommandRejected(ControllerError):
    """The controller understood the command and refused it (an ``ERR`` reply).

    Attributes:
        code: the firmware's error code (``E01`` .. ``E06``, see PROTOCOL.md).
        detail: the firmware's detail word(s).
    """

    def __init__(self, message: str, code: str, detail: str) -> None:
        super().__init__(message)
        self.code, self.detail = code, detail


class ProgramMismatch(ControllerError):
    """The program read back from the controller differs from the one uploaded."""
