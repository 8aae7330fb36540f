"""Client of the LED controller over pyserial (protocol: PROTOCOL.md).

Every command is one request line and one reply line with the same sequence number. A
reply that does not come within ``timeout_s``, fails its checksum, or is a ``NAK`` makes
the client resend the same request (same sequence number, so the firmware replays its
reply instead of running the command twice), up to ``retries`` times; then it raises
``ControllerTimeout`` or ``CorruptReply``. An ``ERR`` reply raises ``CommandRejected`` at
once. A port that cannot be opened or disappears raises ``DeviceGone``. No call blocks
longer than about ``(retries + 1) * timeout_s``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import serial

try:  # pyserial's POSIX backend lets termios.error (not an OSError) escape from a vanished tty
    import termios

    _TERMIOS_ERRORS: tuple[type[BaseException], ...] = (termios.error,)
except ImportError:  # Windows
    _TERMIOS_ERRORS = ()
from hardware.led import protocol as p
from hardware.led.errors import (CommandRejected, ControllerError, ControllerTimeout, CorruptReply,
                                 DeviceGone, ProgramMismatch)

# What pyserial raises when the port is gone (ValueError/TypeError: a closed fd under it).
_PORT_ERRORS = (serial.SerialException, OSError, ValueError, TypeError, *_TERMIOS_ERRORS)


@dataclass(frozen=True)
class ControllerInfo:
    """What ``VERSION`` reports."""

    firmware: str
    version: str
    protocol: int
    bars: int


@dataclass(frozen=True)
class ControllerStatus:
    """What ``STATUS`` reports."""

    state: str          # IDLE | LOADING | ARMED | RUNNING
    steps: int          # program length (0 without a program)
    repeat: int         # program repetitions (0 = forever)
    crc32: str | None   # checksum of the armed program
    pulses: int         # pulses acted on since START
    ignored_pulses: int  # pulses received while not running
    log_entries: int
    lit: p.Light


class LedController:
    """A connection to one LED controller.

    Args:
        port: a device path (``/dev/ttyUSB0``, an emulator's ``/dev/pts/N``) or a pyserial
            URL (``loop://``, ``rfc2217://host:port``).
        timeout_s: how long to wait for each reply before resending.
        retries: resends after a timeout, a corrupt reply or a NAK.
        baudrate: line speed (ignored by ptys).
    """

    def __init__(self, port: str, timeout_s: float = 0.5, retries: int = 2, baudrate: int = 115200) -> None:
        if timeout_s <= 0 or retries < 0:
            raise ValueError(f"timeout_s must be > 0 and retries >= 0, got {timeout_s}, {retries}")
        self.port, self.timeout_s, self.retries = port, timeout_s, retries
        self._seq = 0
        try:
            self._serial = serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s,
                                                 write_timeout=timeout_s)
        except _PORT_ERRORS as err:
            raise DeviceGone(f"LED controller port {port}: cannot open ({err}); check the cable "
                             f"and the port name") from err
        try:
            self._serial.reset_input_buffer()
        except _PORT_ERRORS as err:
            raise DeviceGone(f"LED controller port {port}: cannot use ({err}); check the cable") from err

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> None:
        """Close the port (safe to call twice, and after the device vanished)."""
        try:
            self._serial.close()
        except _PORT_ERRORS:
            pass

    def __enter__(self) -> "LedController":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transport -------------------------------------------------------------------------
    def _next_seq(self) -> int:
        self._seq = self._seq % p.MAX_SEQ + 1
        return self._seq

    def command(self, word: str, *args: object) -> tuple[str, ...]:
        """Send one command and return the ACK's arguments (retrying as the class says)."""
        seq = self._next_seq()
        request = p.encode_frame(seq, word, args)
        what = f"LED controller port {self.port}: {word} {' '.join(map(str, args))}".rstrip()
        failure: ControllerError = ControllerTimeout(f"{what}: no reply within {self.timeout_s} s")
        for attempt in range(self.retries + 1):
            self._write(request, what)
            try:
                reply = self._read_reply(seq, what)
            except (ControllerTimeout, CorruptReply) as err:
                failure = err
                continue
            if reply.word == "ACK":
                return reply.args
            if reply.word == "ERR":
                code = reply.args[0] if reply.args else "E??"
                detail = " ".join(reply.args[1:]).replace("_", " ")
                meaning = p.ERR_MESSAGES.get(code, "unknown error")
                raise CommandRejected(f"{what}: refused, {code} {meaning}"
                                      f"{': ' + detail if detail else ''}", code, detail)
            failure = CorruptReply(f"{what}: the controller could not read the request (NAK "
                                   f"{' '.join(reply.args)}); the line is noisy")
        raise type(failure)(f"{failure} (after {self.retries + 1} attempts)")

    def _write(self, request: bytes, what: str) -> None:
        try:
            # Drop stale bytes (a late reply to an earlier attempt) so they cannot be mistaken.
            self._serial.reset_input_buffer()
            # No flush(): on POSIX it is tcdrain(), which can block without limit on a stuck
            # port; write() with write_timeout already hands every byte to the driver.
            self._serial.write(request)
        except serial.SerialTimeoutException as err:
            raise ControllerTimeout(f"{what}: write timed out after {self.timeout_s} s") from err
        except _PORT_ERRORS as err:
            raise DeviceGone(f"{what}: device gone ({err}); check the cable") from err

    def _read_reply(self, seq: int, what: str) -> p.Frame:
        deadline = time.monotonic() + self.timeout_s
        corrupt: str | None = None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if corrupt is not None:
                    raise CorruptReply(f"{what}: corrupted reply {corrupt}")
                raise ControllerTimeout(f"{what}: no reply within {self.timeout_s} s")
            try:
                self._serial.timeout = remaining
                line = self._serial.read_until(b"\n", p.MAX_LINE_BYTES + 1)
            except _PORT_ERRORS as err:
                raise DeviceGone(f"{what}: device gone ({err}); check the cable") from err
            if not line.endswith(b"\n"):
                if len(line) > p.MAX_LINE_BYTES:
                    corrupt = repr(line[:40] + b"...")
                    continue
                # A partial line at the deadline: the loop reports timeout (or corruption).
                if line:
                    corrupt = repr(line)
                continue
            try:
                frame = p.decode_frame(line)
            except p.FrameError as err:
                # Do not wait out the timeout: the firmware replays the reply on a resend.
                raise CorruptReply(f"{what}: corrupted reply ({err})") from err
            if frame.word == "NAK" and frame.seq in (seq, 0):
                return frame
            if frame.seq != seq:
                continue  # a late reply to an earlier request
            if frame.word not in ("ACK", "ERR"):
                raise CorruptReply(f"{what}: unexpected reply word {frame.word!r}")
            return frame

    # -- commands --------------------------------------------------------------------------
    def ping(self) -> float:
        """Round trip of a ``PING``, in seconds."""
        start = time.perf_counter()
        args = self.command("PING")
        if args != ("PONG",):
            raise CorruptReply(f"LED controller port {self.port}: PING answered {args!r}")
        return time.perf_counter() - start

    def version(self) -> ControllerInfo:
        """Firmware name, version, protocol version and bar count."""
        values = self._key_values(self.command("VERSION"), "VERSION")
        try:
            return ControllerInfo(values["fw"], values["version"], int(values["proto"]), int(values["bars"]))
        except (KeyError, ValueError) as err:
            raise CorruptReply(f"LED controller port {self.port}: bad VERSION reply {values}") from err

    def status(self) -> ControllerStatus:
        """State, program, pulse counters and what is lit."""
        v = self._key_values(self.command("STATUS"), "STATUS")
        try:
            return ControllerStatus(v["state"], int(v["steps"]), int(v["repeat"]),
                                    None if v["crc"] == "-" else v["crc"], int(v["pulses"]),
                                    int(v["ignored"]), int(v["log"]), p.parse_light(v["lit"]))
        except (KeyError, ValueError) as err:
            raise CorruptReply(f"LED controller port {self.port}: bad STATUS reply {v}") from err

    def reset(self) -> None:
        """Reset the firmware: no program, intensities 1, log cleared."""
        self.command("RESET")

    def upload(self, steps: Sequence[p.Light], repeat: int) -> str:
        """Upload a program in chunks and check the controller's checksum of it.

        Args:
            steps: one cycle of lights (``"F"`` or bar ids).
            repeat: how many times the cycle runs (0 = until STOP).

        Returns:
            The program's CRC-32 (pass it to ``arm``).
        """
        steps = list(steps)
        expected = p.program_crc32(steps, repeat)  # validates the lights too
        self.command("PROG", "BEGIN", len(steps), repeat)
        for offset in range(0, len(steps), p.PROGRAM_CHUNK_STEPS):
            chunk = steps[offset:offset + p.PROGRAM_CHUNK_STEPS]
            self.command("PROG", "DATA", offset, *(p.light_token(s) for s in chunk))
        info = self._key_values(self.command("PROG", "INFO"), "PROG INFO")
        if info.get("crc") != expected:
            raise ProgramMismatch(f"LED controller port {self.port}: uploaded program checksum "
                                  f"{info.get('crc')} != {expected} ({info.get('loaded')} of "
                                  f"{len(steps)} steps loaded); upload again")
        return expected

    def read_program(self) -> tuple[list[p.Light], int]:
        """The program stored on the controller: (steps, repeat)."""
        info = self._key_values(self.command("PROG", "INFO"), "PROG INFO")
        n, repeat = int(info["steps"]), int(info["repeat"])
        steps: list[p.Light] = []
        for offset in range(0, n, p.PROGRAM_CHUNK_STEPS):
            args = self.command("PROG", "READ", offset, min(p.PROGRAM_CHUNK_STEPS, n - offset))
            if not args or int(args[0]) != offset:
                raise CorruptReply(f"LED controller port {self.port}: PROG READ {offset} answered {args!r}")
            for token in args[1:]:
                if token == "?":
                    raise ProgramMismatch(f"LED controller port {self.port}: program step "
                                          f"{len(steps)} was never loaded; upload again")
                steps.append(p.parse_light(token))
        return steps, repeat

    def verify_program(self, steps: Sequence[p.Light], repeat: int) -> str:
        """Read the stored program back and compare it with ``steps``; returns its CRC-32."""
        stored, stored_repeat = self.read_program()
        if stored != list(steps) or stored_repeat != repeat:
            first = next((i for i, (a, b) in enumerate(zip(stored, steps)) if a != b), min(len(stored), len(steps)))
            raise ProgramMismatch(f"LED controller port {self.port}: stored program differs from "
                                  f"the sequence at step {first} (repeat {stored_repeat} vs {repeat}); upload again")
        return p.program_crc32(stored, stored_repeat)

    def set_intensity(self, bar: int | str, value: float) -> None:
        """Set one bar's (or ``"ALL"`` bars') intensity, 0..1."""
        self.command("INT", "SET", bar, f"{value:.4f}")

    def set_intensities(self, values: Sequence[float]) -> None:
        """Set every bar's intensity (one value per bar id)."""
        for bar, value in enumerate(values):
            self.set_intensity(bar, float(value))

    def intensities(self, n_bars: int) -> list[float]:
        """Read back the intensities of bars ``0 .. n_bars-1``."""
        values: list[float] = []
        for offset in range(0, n_bars, p.INTENSITY_CHUNK):
            args = self.command("INT", "GET", offset, min(p.INTENSITY_CHUNK, n_bars - offset))
            values.extend(float(a) for a in args[1:])
        return values

    def arm(self, crc32: str) -> None:
        """Arm the stored program; the controller checks its checksum against ``crc32``."""
        self.command("ARM", crc32)

    def start(self) -> None:
        """Start on the trigger: every following pulse lights the next program step."""
        self.command("START")

    def stop(self) -> int:
        """Stop reacting to pulses (the program stays armed); returns the pulses acted on."""
        args = self._key_values(self.command("STOP")[1:], "STOP")
        return int(args.get("pulses", "0"))

    def trigger(self, count: int = 1) -> None:
        """Software trigger: ``count`` pulses, as if from the camera trigger line."""
        self.command("TRIG", count)

    def read_log(self) -> list[p.LogEntry]:
        """Every entry of the controller's pulse log."""
        entries: list[p.LogEntry] = []
        total = None
        while total is None or len(entries) < total:
            args = self.command("LOG", "READ", len(entries), p.LOG_CHUNK_ENTRIES)
            try:
                total = int(self._key_values(args[:1], "LOG READ")["total"])
                if int(args[1]) != len(entries):
                    raise ValueError(f"offset {args[1]} != {len(entries)}")
                chunk = [p.LogEntry.parse(tok) for tok in args[2:]]
            except (IndexError, KeyError, ValueError) as err:
                raise CorruptReply(f"LED controller port {self.port}: bad LOG READ reply ({err})") from err
            if not chunk and len(entries) < total:
                raise CorruptReply(f"LED controller port {self.port}: log ended at {len(entries)} of {total}")
            entries.extend(chunk)
        return entries

    def clear_log(self) -> None:
        """Empty the controller's pulse log."""
        self.command("LOG", "CLEAR")

    def _key_values(self, args: Sequence[str], what: str) -> dict[str, str]:
        try:
            return p.parse_key_values(args)
        except ValueError as err:
            raise CorruptReply(f"LED controller port {self.port}: bad {what} reply {args!r}") from err
