"""Framing of the LED controller's line protocol (see PROTOCOL.md).

A frame is one ASCII line ``<seq> <WORD> [<arg> ...] *<CC>\\n`` where ``CC`` is the CRC-8
(polynomial 0x07, initial value 0, no reflection; "CRC-8/SMBUS") of every byte before the
space that precedes ``*``, in two upper-case hex digits. Requests and replies share the
framing; a reply repeats its request's ``seq`` and its word is ``ACK``, ``NAK`` or ``ERR``.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Iterable, Sequence, Union

PROTOCOL_VERSION = 1
MAX_LINE_BYTES = 255          # including the newline; the firmware's receive buffer
MAX_SEQ = 9999                # sequence numbers run 1..MAX_SEQ and wrap
PROGRAM_CHUNK_STEPS = 16      # steps per PROG DATA line
LOG_CHUNK_ENTRIES = 8         # entries per LOG READ reply
INTENSITY_CHUNK = 8           # values per INT GET reply

Light = Union[str, int, None]  # "F" every bar on, a bar id, or None (nothing lit)
FULL_ON = "F"
NO_LIGHT = "-"

# ERR codes (the firmware understood the frame but refuses the command).
ERR_UNKNOWN_COMMAND = "E01"
ERR_BAD_ARGUMENT = "E02"
ERR_BAD_STATE = "E03"
ERR_PROGRAM_CHECKSUM = "E04"
ERR_PROGRAM_INCOMPLETE = "E05"
ERR_OUT_OF_RANGE = "E06"
ERR_MESSAGES = {
    ERR_UNKNOWN_COMMAND: "unknown command",
    ERR_BAD_ARGUMENT: "bad argument",
    ERR_BAD_STATE: "not allowed in the current state",
    ERR_PROGRAM_CHECKSUM: "program checksum mismatch",
    ERR_PROGRAM_INCOMPLETE: "program incomplete",
    ERR_OUT_OF_RANGE: "value out of range",
}


class FrameError(ValueError):
    """A line that is not a valid frame (bad checksum, bad shape, too long)."""


@dataclass(frozen=True)
class Frame:
    """One decoded line: sequence number, word (command or reply kind) and arguments."""

    seq: int
    word: str
    args: tuple[str, ...]


def crc8(data: bytes) -> int:
    """CRC-8/SMBUS: polynomial 0x07, initial value 0, no reflection, no final xor."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def encode_frame(seq: int, word: str, args: Iterable[object] = ()) -> bytes:
    """The wire bytes of one frame, newline included."""
    body = " ".join([str(seq), word, *(str(a) for a in args)])
    line = f"{body} *{crc8(body.encode('ascii')):02X}\n".encode("ascii")
    if len(line) > MAX_LINE_BYTES:
        raise FrameError(f"frame of {len(line)} bytes exceeds the {MAX_LINE_BYTES}-byte line limit")
    return line


def decode_frame(line: bytes) -> Frame:
    """Parse and check one line (with or without its newline); raises ``FrameError``."""
    if len(line) > MAX_LINE_BYTES:
        raise FrameError(f"line of {len(line)} bytes exceeds {MAX_LINE_BYTES}")
    try:
        text = line.decode("ascii").rstrip("\r\n")
    except UnicodeDecodeError as err:
        raise FrameError(f"non-ASCII byte in line: {line!r}") from err
    body, sep, checksum = text.rpartition(" *")
    if not sep or len(checksum) != 2:
        raise FrameError(f"no ' *CC' checksum at the end of {text!r}")
    try:
        expected = int(checksum, 16)
    except ValueError as err:
        raise FrameError(f"checksum {checksum!r} is not hex in {text!r}") from err
    if crc8(body.encode("ascii")) != expected:
        raise FrameError(f"checksum mismatch in {text!r}")
    parts = body.split(" ")
    if len(parts) < 2 or not parts[0].isdigit() or not parts[1]:
        raise FrameError(f"expected '<seq> <WORD> ...' in {text!r}")
    return Frame(int(parts[0]), parts[1], tuple(p for p in parts[2:] if p))


def light_token(light: Light) -> str:
    """Wire token of a light: ``F``, a decimal bar id, or ``-`` for nothing lit."""
    if light is None:
        return NO_LIGHT
    if light == FULL_ON:
        return FULL_ON
    if isinstance(light, (int,)) and not isinstance(light, bool) and light >= 0:
        return str(light)
    raise ValueError(f"not a light: {light!r} (expected 'F', a bar id >= 0 or None)")


def parse_light(token: str) -> Light:
    """Inverse of ``light_token``."""
    if token == FULL_ON:
        return FULL_ON
    if token == NO_LIGHT:
        return None
    if token.isdigit():
        return int(token)
    raise ValueError(f"not a light token: {token!r}")


def program_text(steps: Sequence[Light], repeat: int) -> bytes:
    """Canonical bytes of a program, whose CRC-32 the firmware checks on ARM: ``"<repeat>:"``
    followed by the step tokens separated by single spaces."""
    return (f"{repeat}:" + " ".join(light_token(s) for s in steps)).encode("ascii")


def program_crc32(steps: Sequence[Light], repeat: int) -> str:
    """CRC-32 (zlib / IEEE 802.3) of ``program_text``, 8 lower-case hex digits."""
    return f"{zlib.crc32(program_text(steps, repeat)) & 0xFFFFFFFF:08x}"


@dataclass(frozen=True)
class LogEntry:
    """One trigger pulse the firmware acted on.

    Attributes:
        pulse: index of the pulse since ``START`` (0-based; missed pulses are not counted).
        cycle: repetition of the program the pulse fell in.
        step: step of the program (0-based, within the cycle).
        light: ``"F"``, a bar id, or None once the program has run out.
        time_us: the trigger time in microseconds (the trigger's own time stamp when the
            pulse carried one, else the firmware clock since power-up).
    """

    pulse: int
    cycle: int
    step: int
    light: Light
    time_us: int

    def token(self) -> str:
        """Wire form ``pulse,cycle,step,light,time_us``."""
        return f"{self.pulse},{self.cycle},{self.step},{light_token(self.light)},{self.time_us}"

    @staticmethod
    def parse(token: str) -> "LogEntry":
        """Inverse of ``token``; raises ``ValueError`` on a malformed entry."""
        parts = token.split(",")
        if len(parts) != 5:
            raise ValueError(f"log entry {token!r} does not have 5 fields")
        return LogEntry(int(parts[0]), int(parts[1]), int(parts[2]), parse_light(parts[3]), int(parts[4]))

    def to_json(self) -> dict:
        """JSON-ready dict (``controller_log.json``)."""
        return {"pulse": self.pulse, "cycle": self.cycle, "step": self.step,
                "light": self.light, "time_us": self.time_us}


def parse_key_values(args: Sequence[str]) -> dict[str, str]:
    """``("state=ARMED", "steps=48")`` -> ``{"state": "ARMED", "steps": "48"}``."""
    out = {}
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep:
            raise ValueError(f"expected key=value, got {arg!r}")
        out[key] = value
    return out
