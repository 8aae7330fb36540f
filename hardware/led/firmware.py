"""The LED controller's firmware as a pure state machine (no I/O), used by the emulator.

``handle(line)`` takes one received line and returns the reply bytes; ``pulse()`` is the
camera trigger input. Both are thread-safe: the serial link and the trigger line are
served from different threads, as interrupts are on the real board.

States: ``IDLE`` (no valid program), ``LOADING`` (after ``PROG BEGIN``), ``ARMED``
(program verified by ``ARM``), ``RUNNING`` (after ``START``: each trigger pulse lights the
next step and is logged). ``STOP`` returns to ``ARMED``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from hardware.led import protocol as p

FIRMWARE_NAME = "OLATCTL-EMU"
FIRMWARE_VERSION = "1.0.0"
MAX_PROGRAM_STEPS = 4096
MAX_LOG_ENTRIES = 1_000_000
MAX_SOFT_TRIGGERS = 1000


class _Refused(Exception):
    def __init__(self, code: str, detail: str = "") -> None:
        super().__init__(code)
        self.code, self.detail = code, detail


@dataclass
class _Program:
    steps: list[p.Light | None]
    repeat: int

    def complete(self) -> bool:
        return all(step is not None for step in self.steps)


class LedFirmware:
    """Behaviour of the controller board behind the serial port.

    Args:
        n_bars: number of LED bars wired to the board (ids ``0 .. n_bars-1``).
    """

    def __init__(self, n_bars: int = 32) -> None:
        self.n_bars = n_bars
        self._lock = threading.Lock()
        self._boot_ns = time.monotonic_ns()
        self._last_seq: int | None = None
        self._last_request: bytes | None = None
        self._last_reply: bytes | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        self.state = "IDLE"
        self.program: _Program | None = None
        self.armed_crc: str | None = None
        self.intensities = [1.0] * self.n_bars
        self.log: list[p.LogEntry] = []
        self.pulses = 0            # pulses acted on since START
        self.ignored_pulses = 0    # pulses received while not RUNNING
        self.lit: p.Light = None   # what the bars show right now

    # -- trigger input ---------------------------------------------------------------------
    def pulse(self, time_s: float | None = None) -> p.Light:
        """A rising edge on the trigger input; returns what is lit for this exposure.

        Args:
            time_s: the trigger's own time stamp (e.g. the virtual camera's frame time);
                logged in microseconds. None uses the firmware clock.
        """
        with self._lock:
            return self._pulse_locked(time_s)

    def _pulse_locked(self, time_s: float | None) -> p.Light:
        if self.state != "RUNNING" or self.program is None:
            self.ignored_pulses += 1
            return None
        n = len(self.program.steps)
        cycle, step = divmod(self.pulses, n)
        ran_out = self.program.repeat > 0 and cycle >= self.program.repeat
        light = None if ran_out else self.program.steps[step]
        time_us = round(time_s * 1e6) if time_s is not None else (time.monotonic_ns() - self._boot_ns) // 1000
        if len(self.log) < MAX_LOG_ENTRIES:
            self.log.append(p.LogEntry(self.pulses, cycle, step, light, int(time_us)))
        self.pulses += 1
        self.lit = light
        return light

    # -- serial input ----------------------------------------------------------------------
    def handle(self, line: bytes) -> bytes:
        """Reply to one received line (newline included or not)."""
        try:
            frame = p.decode_frame(line)
        except p.FrameError:
            seq = line.split(b" ", 1)[0]
            # A damaged line gets a NAK; its seq is echoed when it still reads as one.
            echo = int(seq) if seq.isdigit() and len(seq) <= 4 else 0
            return p.encode_frame(echo, "NAK", ["CRC"])
        with self._lock:
            # A retried request (same seq, same bytes) gets the same reply without running
            # twice, so retries of non-idempotent commands (TRIG, LOG CLEAR) are safe.
            if frame.seq == self._last_seq and line.rstrip(b"\r\n") == self._last_request:
                return self._last_reply
            try:
                args = self._dispatch(frame.word, list(frame.args))
                reply = p.encode_frame(frame.seq, "ACK", args)
            except _Refused as refused:
                words = [refused.code] + ([refused.detail.replace(" ", "_")] if refused.detail else [])
                reply = p.encode_frame(frame.seq, "ERR", words)
            self._last_seq, self._last_request, self._last_reply = frame.seq, line.rstrip(b"\r\n"), reply
            return reply

    def _dispatch(self, word: str, args: list[str]) -> list[str]:
        handler = getattr(self, f"_cmd_{word.lower()}", None) if word.isalpha() and word.isupper() else None
        if handler is None:
            raise _Refused(p.ERR_UNKNOWN_COMMAND, word)
        return handler(args)

    def _cmd_ping(self, args: list[str]) -> list[str]:
        return ["PONG"]

    def _cmd_version(self, args: list[str]) -> list[str]:
        return [f"fw={FIRMWARE_NAME}", f"version={FIRMWARE_VERSION}", f"proto={p.PROTOCOL_VERSION}",
                f"bars={self.n_bars}", f"maxline={p.MAX_LINE_BYTES}", f"maxsteps={MAX_PROGRAM_STEPS}"]

    def _cmd_reset(self, args: list[str]) -> list[str]:
        self._reset_state()
        return ["RESET"]

    def _cmd_status(self, args: list[str]) -> list[str]:
        prog = self.program
        return [f"state={self.state}", f"steps={len(prog.steps) if prog else 0}",
                f"repeat={prog.repeat if prog else 0}", f"crc={self.armed_crc or '-'}",
                f"pulses={self.pulses}", f"ignored={self.ignored_pulses}", f"log={len(self.log)}",
                f"lit={p.light_token(self.lit)}"]

    def _cmd_prog(self, args: list[str]) -> list[str]:
        if not args:
            raise _Refused(p.ERR_BAD_ARGUMENT, "PROG needs BEGIN|DATA|READ|INFO")
        sub, rest = args[0], args[1:]
        if sub == "BEGIN":
            self._require_not_running()
            n, repeat = self._ints(rest, 2)
            if not 1 <= n <= MAX_PROGRAM_STEPS or repeat < 0:
                raise _Refused(p.ERR_OUT_OF_RANGE, f"steps 1..{MAX_PROGRAM_STEPS}, repeat>=0")
            self.program, self.armed_crc, self.state = _Program([None] * n, repeat), None, "LOADING"
            return ["BEGIN", str(n), str(repeat)]
        if sub == "DATA":
            if self.state != "LOADING" or self.program is None:
                raise _Refused(p.ERR_BAD_STATE, "PROG DATA needs PROG BEGIN first")
            if not rest:
                raise _Refused(p.ERR_BAD_ARGUMENT, "PROG DATA <offset> <steps...>")
            (offset,) = self._ints(rest[:1], 1)
            lights = [self._light(tok) for tok in rest[1:]]
            if offset < 0 or offset + len(lights) > len(self.program.steps) or not lights:
                raise _Refused(p.ERR_OUT_OF_RANGE, f"steps {offset}..{offset + len(lights)} outside program")
            self.program.steps[offset:offset + len(lights)] = lights
            return ["DATA", str(offset), str(len(lights))]
        if sub == "READ":
            offset, count = self._ints(rest, 2)
            prog = self._require_program()
            if offset < 0 or count < 1 or count > p.PROGRAM_CHUNK_STEPS or offset >= len(prog.steps):
                raise _Refused(p.ERR_OUT_OF_RANGE, "PROG READ offset/count")
            chunk = prog.steps[offset:offset + count]
            return [str(offset)] + ["?" if s is None else p.light_token(s) for s in chunk]
        if sub == "INFO":
            prog = self._require_program()
            crc = p.program_crc32(prog.steps, prog.repeat) if prog.complete() else "-"
            loaded = sum(s is not None for s in prog.steps)
            return [f"steps={len(prog.steps)}", f"repeat={prog.repeat}", f"loaded={loaded}", f"crc={crc}"]
        raise _Refused(p.ERR_BAD_ARGUMENT, f"PROG {sub}")

    def _cmd_int(self, args: list[str]) -> list[str]:
        if not args:
            raise _Refused(p.ERR_BAD_ARGUMENT, "INT needs SET|GET")
        if args[0] == "SET" and len(args) == 3:
            self._require_not_running()
            value = self._float(args[2])
            if not 0.0 <= value <= 1.0:
                raise _Refused(p.ERR_OUT_OF_RANGE, "intensity 0..1")
            bars = range(self.n_bars) if args[1] == "ALL" else [self._bar(args[1])]
            for bar in bars:
                self.intensities[bar] = round(value, 4)
            return ["SET", args[1], f"{round(value, 4):.4f}"]
        if args[0] == "GET" and len(args) == 3:
            offset, count = self._ints(args[1:], 2)
            if offset < 0 or offset >= self.n_bars or not 1 <= count <= p.INTENSITY_CHUNK:
                raise _Refused(p.ERR_OUT_OF_RANGE, "INT GET offset/count")
            return [str(offset)] + [f"{v:.4f}" for v in self.intensities[offset:offset + count]]
        raise _Refused(p.ERR_BAD_ARGUMENT, "INT SET <bar|ALL> <0..1> | INT GET <offset> <count>")

    def _cmd_arm(self, args: list[str]) -> list[str]:
        self._require_not_running()
        prog = self._require_program()
        if len(args) != 1:
            raise _Refused(p.ERR_BAD_ARGUMENT, "ARM <crc32>")
        if not prog.complete():
            raise _Refused(p.ERR_PROGRAM_INCOMPLETE, f"{sum(s is None for s in prog.steps)} steps missing")
        crc = p.program_crc32(prog.steps, prog.repeat)
        if args[0].lower() != crc:
            raise _Refused(p.ERR_PROGRAM_CHECKSUM, f"loaded={crc}")
        self.state, self.armed_crc = "ARMED", crc
        return ["ARMED", crc]

    def _cmd_start(self, args: list[str]) -> list[str]:
        if self.state != "ARMED":
            raise _Refused(p.ERR_BAD_STATE, f"START needs ARMED, state is {self.state}")
        self.state, self.pulses, self.lit = "RUNNING", 0, None
        return ["RUNNING"]

    def _cmd_stop(self, args: list[str]) -> list[str]:
        if self.state == "RUNNING":
            self.state = "ARMED"
        self.lit = None
        return ["STOPPED", f"pulses={self.pulses}"]

    def _cmd_trig(self, args: list[str]) -> list[str]:
        (count,) = self._ints(args, 1) if args else (1,)
        if not 1 <= count <= MAX_SOFT_TRIGGERS:
            raise _Refused(p.ERR_OUT_OF_RANGE, f"TRIG 1..{MAX_SOFT_TRIGGERS}")
        if self.state != "RUNNING":
            raise _Refused(p.ERR_BAD_STATE, f"TRIG needs RUNNING, state is {self.state}")
        for _ in range(count):
            self._pulse_locked(None)
        return ["TRIG", str(count), f"pulses={self.pulses}"]

    def _cmd_log(self, args: list[str]) -> list[str]:
        if args[:1] == ["CLEAR"]:
            self._require_not_running()
            self.log = []
            return ["CLEARED"]
        if args[:1] == ["READ"] and len(args) == 3:
            offset, count = self._ints(args[1:], 2)
            if offset < 0 or not 1 <= count <= p.LOG_CHUNK_ENTRIES:
                raise _Refused(p.ERR_OUT_OF_RANGE, f"LOG READ offset>=0, count 1..{p.LOG_CHUNK_ENTRIES}")
            entries = self.log[offset:offset + count]
            return [f"total={len(self.log)}", str(offset)] + [e.token() for e in entries]
        raise _Refused(p.ERR_BAD_ARGUMENT, "LOG READ <offset> <count> | LOG CLEAR")

    # -- helpers ---------------------------------------------------------------------------
    def _require_program(self) -> _Program:
        if self.program is None:
            raise _Refused(p.ERR_BAD_STATE, "no program loaded")
        return self.program

    def _require_not_running(self) -> None:
        if self.state == "RUNNING":
            raise _Refused(p.ERR_BAD_STATE, "STOP first")

    def _ints(self, args: list[str], n: int) -> list[int]:
        if len(args) != n or not all(a.lstrip("-").isdigit() for a in args):
            raise _Refused(p.ERR_BAD_ARGUMENT, f"expected {n} integers")
        return [int(a) for a in args]

    def _float(self, token: str) -> float:
        try:
            return float(token)
        except ValueError as err:
            raise _Refused(p.ERR_BAD_ARGUMENT, f"not a number: {token}") from err

    def _bar(self, token: str) -> int:
        if not token.isdigit() or int(token) >= self.n_bars:
            raise _Refused(p.ERR_OUT_OF_RANGE, f"bar 0..{self.n_bars - 1}")
        return int(token)

    def _light(self, token: str) -> p.Light:
        if token == p.FULL_ON:
            return p.FULL_ON
        return self._bar(token)
