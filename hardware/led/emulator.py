"""An emulated LED controller serving the firmware's protocol on a pseudo-terminal.

``LedEmulator().start()`` opens a pty pair (``os.openpty``) and answers on the master side
from a background thread; ``emulator.port`` is the slave's path (``/dev/pts/N``), which the
unchanged client opens as it would ``/dev/ttyUSB0``. The camera trigger line is
``emulator.pulse(time_s)``, called by the (virtual) camera at every exposure.

Faults can be injected to test the client: corrupt replies, silence, missed trigger
pulses, and unplugging (closing the pty master, so the client's next read or write fails).
"""

from __future__ import annotations

import errno
import os
import random
import select
import threading
import tty
from dataclasses import dataclass, field

from hardware.led import protocol as p
from hardware.led.firmware import LedFirmware


@dataclass(frozen=True)
class Faults:
    """Faults the emulator injects (all off by default).

    Attributes:
        corrupt_replies: 0-based indices of replies (counted over the emulator's life) sent
            with one byte flipped, so their checksum fails.
        corrupt_rate: probability of corrupting any other reply (seeded by ``seed``).
        silent_after: after this many received request lines, stop answering (still reading).
        unplug_after: after this many received request lines, close the port (the
            request that reaches the count gets no reply).
        drop_pulses: 0-based trigger pulse indices (counted over every pulse on the trigger
            input) that the firmware misses: nothing is lit, nothing is logged.
        seed: seeds ``corrupt_rate``.
    """

    corrupt_replies: frozenset[int] = field(default_factory=frozenset)
    corrupt_rate: float = 0.0
    silent_after: int | None = None
    unplug_after: int | None = None
    drop_pulses: frozenset[int] = field(default_factory=frozenset)
    seed: int = 0


class LedEmulator:
    """The firmware behind a pty, in a daemon thread. Use as a context manager.

    Args:
        n_bars: LED bars on the emulated board.
        faults: faults to inject.
    """

    def __init__(self, n_bars: int = 32, faults: Faults | None = None) -> None:
        self.firmware = LedFirmware(n_bars)
        self.faults = faults or Faults()
        self._rng = random.Random(self.faults.seed)
        self._master_fd: int | None = None
        self._slave_fd: int | None = None
        self._port: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._silent = False
        self._requests = 0
        self._replies = 0
        self._trigger_count = 0
        self._trigger_lock = threading.Lock()
        self.trigger_lights: list[p.Light] = []  # what was lit at every trigger pulse (truth)

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> "LedEmulator":
        """Open the pty and start answering; returns self."""
        master, slave = os.openpty()
        # Raw mode: no echo, no line editing, no CR/LF translation; the client sets the same.
        tty.setraw(slave)
        self._master_fd, self._slave_fd = master, slave
        self._port = os.ttyname(slave)
        self._thread = threading.Thread(target=self._serve, name=f"led-emulator {self._port}", daemon=True)
        self._thread.start()
        return self

    @property
    def port(self) -> str:
        """Path of the pty slave, to pass to ``LedController``."""
        if self._port is None:
            raise RuntimeError("emulator not started; call start() first")
        return self._port

    def close(self) -> None:
        """Stop the thread and close both ends of the pty."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_master()
        if self._slave_fd is not None:
            try:
                os.close(self._slave_fd)
            except OSError:
                pass
            self._slave_fd = None

    def __enter__(self) -> "LedEmulator":
        return self if self._thread is not None else self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault controls --------------------------------------------------------------------
    def unplug(self) -> None:
        """Pull the cable: close the pty master, so the client's reads and writes fail."""
        self._stop.set()
        self._close_master()

    def set_silent(self, silent: bool) -> None:
        """Stop (or resume) answering requests, as a hung firmware would."""
        self._silent = silent

    # -- trigger input ---------------------------------------------------------------------
    def pulse(self, time_s: float | None = None) -> p.Light:
        """One camera trigger pulse; returns what the bars show for this exposure.

        A pulse listed in ``faults.drop_pulses`` is missed by the firmware: nothing is lit
        and the controller's log has no entry for it.
        """
        with self._trigger_lock:
            index = self._trigger_count
            self._trigger_count += 1
        light = None if index in self.faults.drop_pulses else self.firmware.pulse(time_s)
        self.trigger_lights.append(light)
        return light

    # -- serving ---------------------------------------------------------------------------
    def _close_master(self) -> None:
        if self._master_fd is not None:
            fd, self._master_fd = self._master_fd, None
            try:
                os.close(fd)
            except OSError:
                pass

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            fd = self._master_fd
            if fd is None:
                return
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                if not ready:
                    continue
                chunk = os.read(fd, 4096)
            except OSError as err:
                if err.errno in (errno.EBADF,):
                    return
                # EIO: no process holds the slave open right now; keep waiting like a board would.
                self._stop.wait(0.05)
                continue
            buffer += chunk
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                self._on_line(line)
            if len(buffer) > p.MAX_LINE_BYTES:
                buffer = b""  # an over-long line: the firmware drops it and NAKs
                self._send(p.encode_frame(0, "NAK", ["LONG"]))

    def _on_line(self, line: bytes) -> None:
        line = line.rstrip(b"\r")
        if not line:
            return
        self._requests += 1
        faults = self.faults
        if faults.unplug_after is not None and self._requests >= faults.unplug_after:
            self.unplug()
            return
        if self._silent or (faults.silent_after is not None and self._requests > faults.silent_after):
            return
        self._send(self.firmware.handle(line))

    def _send(self, reply: bytes) -> None:
        index = self._replies
        self._replies += 1
        if index in self.faults.corrupt_replies or (self.faults.corrupt_rate > 0
                                                    and self._rng.random() < self.faults.corrupt_rate):
            middle = len(reply) // 2
            reply = reply[:middle] + bytes([reply[middle] ^ 0x01]) + reply[middle + 1:]
        fd = self._master_fd
        if fd is None:
            return
        try:
            view = memoryview(reply)
            while view:
                written = os.write(fd, view)
                view = view[written:]
        except OSError:
            pass
