"""``pipeline render`` warns about a requested light beyond the evaluate stage's measured limit."""

from __future__ import annotations

import json
import logging
import shutil

from stages.evaluate.limits import LightLimits, write_limits
from stages.relight.cli import main
from tests.stages.relight.test_stage import inputs  # noqa: F401  (fixture)


def test_render_warns_beyond_the_measured_limit(tmp_path, inputs, caplog):  # noqa: F811
    ws = tmp_path / "ws" / "alice"
    (ws / "refs").mkdir(parents=True)
    for stage, folder in inputs.items():
        shutil.copytree(folder, ws / "objects" / f"digest_{stage}")
    (ws / "objects" / "digest_evaluate").mkdir()
    write_limits(ws / "objects" / "digest_evaluate" / "limits.json",
                 LightLimits(20.0, False, 25.0, (0.0, 0.0, 0.0), ((0.0, 0.0, 1.0), (0.5, 0.0, 0.866))))
    for stage in (*inputs, "evaluate"):
        (ws / "refs" / f"{stage}.json").write_text(json.dumps(
            {"stage": stage, "action": "a", "outputs": {"out": f"digest_{stage}"}, "updated": ""}))
    args = ["-S", "alice", "--workspaces", str(tmp_path / "ws"), "--frames", "1", "--width", "12", "--height", "16",
            "--out", str(tmp_path / "out")]
    with caplog.at_level(logging.WARNING):
        assert main([*args, "--point-light", "0,0.1,1.0"]) == 0
    assert not [r for r in caplog.records if "nearest training light" in r.getMessage()]
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert main([*args, "--point-light", "0,0,-1.0"]) == 0
    warned = [r.getMessage() for r in caplog.records if "nearest training light" in r.getMessage()]
    assert len(warned) == 1 and "point light 0" in warned[0] and "20 degrees" in warned[0]
    # A warning, not a refusal: the frame is still rendered.
    assert len(list((tmp_path / "out" / "point_lights" / "frames").glob("*.exr"))) == 1
