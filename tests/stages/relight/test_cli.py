"""``pipeline render``: usage errors and missing inputs give one clear line and an exit code."""

from __future__ import annotations

from stages.relight.cli import main
from tests.stages.relight.test_stage import inputs  # noqa: F401  (fixture)


def test_bad_point_light_is_a_usage_error(capsys, tmp_path):
    assert main(["-S", "nobody", "--point-light", "1,2", "--workspaces", str(tmp_path)]) == 2
    assert "x,y,z" in capsys.readouterr().err


def test_missing_training_says_what_to_run(capsys, tmp_path):
    assert main(["-S", "nobody", "--orbit", "3", "--workspaces", str(tmp_path), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "pipeline run -S nobody --only train" in err


def test_missing_expressions_file(capsys, tmp_path):
    assert main(["-S", "nobody", "--expressions", str(tmp_path / "nope.csv"), "--workspaces", str(tmp_path)]) == 1
    assert "nope.csv" in capsys.readouterr().err


def test_render_from_a_workspace_writes_frames(tmp_path, inputs, capsys):  # noqa: F811
    """Refs of train/track/capture point at objects; ``render`` writes one folder per sequence."""
    import json
    import shutil

    ws = tmp_path / "ws" / "alice"
    (ws / "refs").mkdir(parents=True)
    for stage, folder in inputs.items():
        shutil.copytree(folder, ws / "objects" / f"digest_{stage}")
        (ws / "refs" / f"{stage}.json").write_text(json.dumps(
            {"stage": stage, "action": "a", "outputs": {"out": f"digest_{stage}"}, "updated": ""}))
    out = tmp_path / "out"
    code = main(["-S", "alice", "--workspaces", str(tmp_path / "ws"), "--point-light", "0.3,0.2,1.0",
                 "--dolly-zoom", "--camera", "0.2,0.1,0.4", "--frames", "2", "--width", "16", "--height", "20", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert len(list((out / "point_lights" / "frames").glob("*.exr"))) == 1
    assert len(list((out / "dolly_zoom" / "previews").glob("*.png"))) == 2
    assert (out / "dolly_zoom" / "dolly_zoom.mp4").exists()
    assert len(list((out / "views" / "frames").glob("*.exr"))) == 1
