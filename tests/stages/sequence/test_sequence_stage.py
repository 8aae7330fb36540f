"""The sequence stage end to end: files, metrics and the controller program."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hardware.led.protocol import program_crc32
from pipeline.errors import ConfigError
from pipeline.testing import run_stage_for_test
from scene.rig import default_rig
from stages.sequence.stage import STAGE, SequenceParams


def test_stage_writes_sequence_and_metrics(tmp_path: Path) -> None:
    out = run_stage_for_test(STAGE, tmp_path, params={"cycles": 3})
    sequence = json.loads((out / "sequence.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())
    n_bars = len(default_rig().bars)
    assert sorted(sequence["olat_order"]) == list(range(n_bars))
    pattern = sequence["pattern"]
    assert len(pattern) == n_bars + n_bars // 2
    assert pattern[0::3] == ["F"] * (n_bars // 2)
    assert [light for light in pattern if light != "F"] == sequence["olat_order"]
    assert sequence["fps"] == 24.0 and sequence["cycles"] == 3
    assert len(sequence["schedule"]) == 3 * len(pattern) == sequence["frames"]
    assert sequence["schedule"][len(pattern) + 1]["light"] == pattern[1]
    assert sequence["program_crc32"] == program_crc32(pattern, 3)
    for key in ("olat_angle_mean_deg", "olat_angle_min_deg", "naive_olat_angle_mean_deg",
                "random_olat_angle_mean_deg"):
        assert isinstance(metrics[key], float)
    assert metrics["olat_angle_mean_deg"] > metrics["random_olat_angle_mean_deg"] > metrics["naive_olat_angle_mean_deg"]
    assert metrics["olat_angle_min_deg"] <= metrics["olat_angle_min_upper_bound_deg"] + 1e-9
    assert (out / "order.png").stat().st_size > 1000


def test_stage_is_deterministic(tmp_path: Path) -> None:
    a = run_stage_for_test(STAGE, tmp_path / "a", params={"cycles": 1})
    b = run_stage_for_test(STAGE, tmp_path / "b", params={"cycles": 1})
    assert (a / "sequence.json").read_text() == (b / "sequence.json").read_text()


def test_too_few_bars_is_a_config_error(tmp_path: Path) -> None:
    rig = default_rig()
    small = rig.model_copy(update={"bars": rig.bars[:2]})
    with pytest.raises(ConfigError, match="bars"):
        run_stage_for_test(STAGE, tmp_path, params={"rig": small})


def test_params_reject_unknown_keys() -> None:
    with pytest.raises(Exception):
        SequenceParams(cycle=3)
