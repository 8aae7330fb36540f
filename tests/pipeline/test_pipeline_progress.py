"""Progress lines, the executor and the unit-test helper for stages."""

from __future__ import annotations

import io
import logging
from pathlib import Path

import pytest
from pydantic import Field

from pipeline.executors import LocalExecutor, make_executor
from pipeline.errors import ConfigError
from pipeline.hashing import hash_bytes
from pipeline.progress import ProgressLine
from pipeline.stage import Stage, StageContext, StageParams
from pipeline.testing import run_stage_for_test


class _Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_plain_lines_every_tenth_or_ten_seconds(caplog: pytest.LogCaptureFixture) -> None:
    clock = _Clock()
    log = logging.getLogger("test.progress")
    with caplog.at_level(logging.INFO, logger="test.progress"):
        with ProgressLine(100, "frames", label="track", log=log, tty=False, clock=clock) as bar:
            for _ in range(100):
                clock.now += 0.01
                bar.advance(loss=0.5)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 10  # 9 at 10%..90% + the summary
    assert lines[0].startswith("[track] 10/100 frames") and "loss=0.5" in lines[0] and "ETA" in lines[0]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="test.progress"):
        bar = ProgressLine(10_000, "it", log=log, tty=False, clock=clock)
        for _ in range(3):
            clock.now += 11.0
            bar.advance()
    assert len(caplog.records) == 3  # slow loop: one line per 10 s


def test_tty_redraws_in_place_throttled() -> None:
    clock = _Clock()
    stream = io.StringIO()
    bar = ProgressLine(1000, "it", tty=True, stream=stream, clock=clock, log=logging.getLogger("t"))
    for _ in range(1000):
        clock.now += 0.001
        bar.advance()
    bar.close()
    text = stream.getvalue()
    assert "\n" not in text and 5 <= text.count("\r") <= 15 and "1000/1000 it" in text


def test_local_executor_keeps_order() -> None:
    items = [bytes([i]) for i in range(20)]
    with LocalExecutor(workers=2) as pool:
        assert pool.map(hash_bytes, items) == [hash_bytes(i) for i in items]
    with LocalExecutor(workers=1) as serial:
        assert serial.map(hash_bytes, items[:3]) == [hash_bytes(i) for i in items[:3]]
    with pytest.raises(ConfigError, match="unknown"):
        make_executor("nope", 1)


class _P(StageParams):
    n: int = Field(3, description="How many.")


def _run(ctx: StageContext) -> None:
    with ctx.progress(ctx.params.n, "things") as bar:
        for _ in range(ctx.params.n):
            bar.advance()
    (ctx.out / "n.txt").write_text(str(ctx.params.n))
    ctx.metrics["n"] = ctx.params.n


def test_run_stage_for_test(tmp_path: Path) -> None:
    out = run_stage_for_test(Stage(name="count", inputs=(), params=_P, run=_run), tmp_path, params={"n": 4})
    assert (out / "n.txt").read_text() == "4"
    assert (out / "metrics.json").read_text().strip().startswith("{")


def test_console_handler_steps_around_a_live_line() -> None:
    from pipeline.progress import ConsoleHandler

    stream = io.StringIO()
    log = logging.getLogger("test.console")
    log.propagate = False
    handler = ConsoleHandler(stream)
    log.addHandler(handler)
    try:
        bar = ProgressLine(10, "it", tty=True, stream=stream, clock=_Clock(), log=logging.getLogger("quiet"))
        bar.advance()
        log.warning("hello")
        bar.close()
    finally:
        log.removeHandler(handler)
    text = stream.getvalue()
    # the live line is erased before the record, and drawn again after it
    before, after = text.split("hello\n")
    assert before.endswith("\r") and "1/10 it" in after
