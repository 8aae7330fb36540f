"""Layered params (defaults <- rig <- preset <- subject <- --set) and the error messages."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import pytest
from pydantic import Field

from pipeline.config import (canonical_params, load_pipeline_config, load_subject_config, parse_set,
                             validate_params)
from pipeline.errors import ConfigError
from pipeline.stage import Stage, StageContext, StageParams
from pipeline.yamlio import load_yaml_text


class Inner(StageParams):
    steps: int = Field(10, ge=1, description="Steps.")
    kind: Literal["lm", "adam"] = Field("lm", description="Solver.")


class Rig(StageParams):
    bars: int = Field(0, description="Bars.")


class TrackParams(StageParams):
    fps: float = Field(24.0, description="Frame rate.")
    solver: Inner = Field(default_factory=Inner, description="Solver settings.")
    rig: Rig = Field(default_factory=Rig, description="The rig.")


def _run(ctx: StageContext) -> None:
    return None


TRACK = Stage(name="track", inputs=(), params=TrackParams, run=_run)


def _project(tmp_path: Path, preset: str, subject: str, rig: str | None = "bars: 32\n") -> Path:
    (tmp_path / "configs/presets").mkdir(parents=True)
    (tmp_path / "configs/subjects").mkdir(parents=True)
    (tmp_path / "configs/pipeline.yaml").write_text("stages:\n  track: x.track\n")
    (tmp_path / "configs/presets/tiny.yaml").write_text(preset)
    (tmp_path / "configs/subjects/alice.yaml").write_text(subject)
    if rig is not None:
        (tmp_path / "configs/rig.yaml").write_text(rig)
    return tmp_path


def test_layers_apply_in_order(tmp_path: Path) -> None:
    root = _project(tmp_path, "track:\n  fps: 30\n  solver: {steps: 5}\n",
                    "preset: tiny\ntrack:\n  solver:\n    kind: adam\n")
    cfg = load_subject_config(root, "alice", ["track"], sets=["track.solver.steps=7"])
    params = validate_params(TRACK, cfg)
    assert params.fps == 30.0 and params.solver.steps == 7 and params.solver.kind == "adam"
    assert params.rig.bars == 32
    assert canonical_params(params) == {"fps": 30.0, "rig": {"bars": 32}, "solver": {"kind": "adam", "steps": 7}}


def test_a_subject_names_its_own_rig_file(tmp_path: Path) -> None:
    root = _project(tmp_path, "", "preset: tiny\nrig: rigs/studio_b.yaml\n")
    (root / "rigs").mkdir()
    (root / "rigs/studio_b.yaml").write_text("bars: 20\n")
    cfg = load_subject_config(root, "alice", ["track"])
    assert validate_params(TRACK, cfg).rig.bars == 20  # replaces configs/rig.yaml, which stays as it is
    (root / "rigs/studio_b.yaml").write_text("bars: many\n")
    with pytest.raises(ConfigError, match=r"rigs/studio_b.yaml: track.rig.bars = 'many'"):
        validate_params(TRACK, load_subject_config(root, "alice", ["track"]))
    (root / "configs/subjects/alice.yaml").write_text("preset: tiny\nrig: rigs/nowhere.yaml\n")
    with pytest.raises(ConfigError, match=r"configs/subjects/alice.yaml: rig rigs/nowhere.yaml: no such file"):
        load_subject_config(root, "alice", ["track"])


def test_errors_name_file_key_and_allowed(tmp_path: Path) -> None:
    root = _project(tmp_path, "track:\n  solver: {kind: sgd}\n", "preset: tiny\ntrack:\n  fps: fast\n")
    cfg = load_subject_config(root, "alice", ["track"])
    with pytest.raises(ConfigError) as err:
        validate_params(TRACK, cfg)
    text = str(err.value)
    assert "configs/presets/tiny.yaml: track.solver.kind = 'sgd'" in text and "'lm' or 'adam'" in text
    assert "configs/subjects/alice.yaml: track.fps = 'fast'" in text
    cfg = load_subject_config(root, "alice", ["track"], sets=["track.solver.steps=0", "track.solver.kind=lm",
                                                               "track.fps=1"])
    with pytest.raises(ConfigError, match=r"--set track.solver.steps=0: track.solver.steps = 0: .*ge 1"):
        validate_params(TRACK, cfg)


def test_bad_entries(tmp_path: Path) -> None:
    root = _project(tmp_path, "tracking: {}\n", "preset: tiny\n")
    with pytest.raises(ConfigError, match="configs/presets/tiny.yaml: section 'tracking' is not a stage"):
        load_subject_config(root, "alice", ["track"])
    with pytest.raises(ConfigError, match="unknown stage 'trak'"):
        parse_set("trak.fps=3", ["track"])
    assert parse_set("track.solver.steps=3", ["track"]) == ("track", ["solver", "steps"], 3)
    assert parse_set("track.name=a:b", ["track"])[2] == "a:b"
    with pytest.raises(ConfigError, match="subject name"):
        load_subject_config(root, "../etc", ["track"])
    with pytest.raises(ConfigError, match="no such subject file"):
        load_subject_config(root, "zoe", ["track"])


def test_yaml_is_safe_and_strict(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="duplicate key 'a'"):
        load_yaml_text("a: 1\na: 2\n", "f.yaml")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml_text("!!python/object/apply:os.system ['echo hi']", "f.yaml")
    root = _project(tmp_path, "", "preset: tiny\n")
    (root / "configs/pipeline.yaml").write_text("stages:\n  a: m.a\ncommands:\n  hw: nocolon\n")
    with pytest.raises(ConfigError, match="commands.hw: expected 'module:function'"):
        load_pipeline_config(root)
