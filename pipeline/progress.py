"""Progress display: a live line on a terminal, plain log lines otherwise (CI, files).

On a TTY the line (stage, done/total, rate, ETA, extra fields such as loss) is redrawn in
place with a carriage return at most ten times a second. Elsewhere a log line is written
every ~10% of the work or every 10 s, whichever comes first.
"""

from __future__ import annotations

import logging
import sys
import time
from typing import Any, Callable, TextIO



def _format_duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes:02d}:{secs:02d}"


def _format_rate(rate: float, unit: str) -> str:
    if rate <= 0:
        return f"- {unit}/s"
    if rate < 1:
        return f"{1 / rate:.3g} s/{unit.rstrip('s') or unit}"
    if rate < 100:
        return f"{rate:.3g} {unit}/s"
    return f"{rate:,.0f} {unit}/s"


def _format_field(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def stream_is_tty(stream: TextIO | None) -> bool:
    """Whether ``stream`` is an interactive terminal."""
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, ValueError):
        return False


_ACTIVE: list["ProgressLine"] = []  # live lines on the terminal, so log records can step around them


class ConsoleHandler(logging.StreamHandler):
    """A console log handler that clears a live progress line before a record and redraws it
    after, so log lines and the progress display never run into each other."""

    def emit(self, record: logging.LogRecord) -> None:
        live = [line for line in _ACTIVE if line.stream is self.stream]
        for line in live:
            line._erase()
        super().emit(record)
        for line in live:
            line._draw()


class ProgressLine:
    """One loop's progress (implements ``pipeline.stage.Progress``).

    Use as ``with ctx.progress(total, "frames") as p: p.advance(loss=0.1)``.
    """

    def __init__(self, total: int, unit: str = "items", *, label: str = "", log: logging.Logger | None = None,
                 stream: TextIO | None = None, tty: bool | None = None, min_interval_s: float = 0.1,
                 log_interval_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.total = max(0, int(total))
        self.unit = unit
        self.label = label
        self.log = log or logging.getLogger("pipeline.progress")
        self.stream = stream if stream is not None else sys.stderr
        self.tty = (stream_is_tty(self.stream) and stream_is_tty(sys.stdout)) if tty is None else tty
        self.min_interval_s = min_interval_s
        self.log_interval_s = log_interval_s
        self.clock = clock
        self.done = 0
        self.fields: dict[str, Any] = {}
        self.start = clock()
        self._last_draw = float("-inf")
        self._last_log = self.start
        self._last_logged_tenth = 0
        self._closed = False
        self._width = 0

    def rate(self) -> float:
        """Items per second since the start."""
        elapsed = self.clock() - self.start
        return self.done / elapsed if elapsed > 0 else 0.0

    def eta_s(self) -> float | None:
        """Seconds left at the current rate (None before any item is done)."""
        rate = self.rate()
        if rate <= 0 or not self.total:
            return None
        return max(0.0, (self.total - self.done) / rate)

    def describe(self) -> str:
        """The text of the progress line."""
        head = f"[{self.label}] " if self.label else ""
        pct = f" {100.0 * self.done / self.total:5.1f}%" if self.total else ""
        text = f"{head}{self.done}/{self.total} {self.unit}{pct} {_format_rate(self.rate(), self.unit)}"
        eta = self.eta_s()
        if eta is not None and self.done < self.total:
            text += f" ETA {_format_duration(eta)}"
        elif self.done >= self.total:
            text += f" in {_format_duration(self.clock() - self.start)}"
        if self.fields:
            text += " " + " ".join(f"{k}={_format_field(v)}" for k, v in self.fields.items())
        return text

    def advance(self, n: int = 1, **fields: Any) -> None:
        """Mark ``n`` more items done; ``fields`` (loss=..., psnr=...) are shown beside the rate."""
        self.done += n
        self.fields.update(fields)
        now = self.clock()
        if self.tty:
            if now - self._last_draw >= self.min_interval_s or self.done >= self.total:
                self._draw()
                self._last_draw = now
            return
        tenth = (10 * self.done // self.total) if self.total else 0
        if tenth > self._last_logged_tenth or now - self._last_log >= self.log_interval_s:
            if self.done < self.total:
                self.log.info("%s", self.describe())
            self._last_logged_tenth = tenth
            self._last_log = now

    def _draw(self) -> None:
        text = self.describe()
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)
        if self not in _ACTIVE:
            _ACTIVE.append(self)

    def _erase(self) -> None:
        if self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()

    def close(self) -> None:
        """Finish: end the live line, and log one summary line."""
        if self._closed:
            return
        self._closed = True
        if self in _ACTIVE:
            _ACTIVE.remove(self)
        if self.tty:
            self._erase()
        self.log.info("%s", self.describe())

    def __enter__(self) -> "ProgressLine":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SilentProgress:
    """Progress that shows nothing (``pipeline.stage.Progress``): DDP ranks that do not report, benchmarks."""

    def advance(self, n: int = 1, **fields: Any) -> None:
        """Nothing to show."""

    def close(self) -> None:
        """Nothing to close."""

    def __enter__(self) -> "SilentProgress":
        return self

    def __exit__(self, *exc: object) -> None:
        return None


def progress_factory(label: str, log: logging.Logger, **kwargs: Any) -> Callable[[int, str], ProgressLine]:
    """A ``StageContext.progress_factory`` making lines labelled with the stage name."""

    def make(total: int, unit: str = "items") -> ProgressLine:
        """A progress line for ``total`` items of ``unit``."""
        return ProgressLine(total, unit, label=label, log=log, **kwargs)

    return make
