"""The report's light-interpolation section, drawn from bench-results/light_oracle_<subject>.json."""

from __future__ import annotations

import json
from pathlib import Path

from stages.report.light_oracle import ORACLE_COLUMNS, capture_fingerprint, light_oracle_section


def _oracle(held: list[int]) -> dict:
    row = {key: 30.0 + i for i, (key, _) in enumerate(ORACLE_COLUMNS)}
    return {"held_out_bars": held, "images_per_split": 12,
            "psnr_db_per_split": {"novel_light": row, "novel_both": {k: v - 1.0 for k, v in row.items()}}}


def test_the_section_sets_the_oracle_beside_the_models_on_the_same_held_out_bars(tmp_path: Path) -> None:
    train = {"ours_novel_light_psnr": 27.25, "travatar_novel_light_psnr": 26.5, "ours_novel_both_psnr": 28.0,
             "travatar_novel_both_psnr": 27.0, "ours_novel_light_psnr_bar9": 27.0, "ours_novel_light_psnr_bar13": 27.5}
    assert light_oracle_section(tmp_path, "alice", train) is None  # no bench run yet: no section
    (tmp_path / "light_oracle_alice.json").write_text(json.dumps(_oracle([13, 9])))
    html = "".join(light_oracle_section(tmp_path, "alice", train).parts)
    assert 'id="light-oracle-table"' in html and html.count("<tr>") == 3  # header + 2 splits
    assert "30.00" in html and "34.00" in html and "29.00" in html  # perfect render, all-bars fit; "both" one lower
    assert "27.25" in html and "26.50" in html and "TRAvatar*</th>" in html
    assert light_oracle_section(tmp_path, "bob", train) is None  # another subject's run is not shown


def test_an_oracle_of_other_held_out_bars_leaves_the_models_out_and_says_why(tmp_path: Path) -> None:
    train = {"ours_novel_light_psnr": 27.25, "ours_novel_light_psnr_bar9": 27.0, "ours_novel_light_psnr_bar13": 27.5}
    (tmp_path / "light_oracle_alice.json").write_text(json.dumps(_oracle([9, 17])))
    html = "".join(light_oracle_section(tmp_path, "alice", train).parts)
    assert "27.25" not in html and "not the oracle" in html and "9, 13" in html
    (tmp_path / "light_oracle_alice.json").write_text("{not json")
    assert light_oracle_section(tmp_path, "alice", train) is None


def test_an_oracle_of_another_capture_leaves_the_models_out(tmp_path: Path) -> None:
    capture = tmp_path / "capture"
    (capture / "frames" / "cam00").mkdir(parents=True)
    (capture / "manifest.json").write_text(json.dumps({"frames": [{"index": 0, "light": "F", "status": "ok"},
                                                                  {"index": 1, "light": 7, "status": "ok"}]}))
    (capture / "frames" / "cam00" / "000000.exr").write_bytes(b"full-on frame")
    (capture / "frames" / "cam00" / "000001.exr").write_bytes(b"first OLAT frame")
    ours = capture_fingerprint(capture)
    (capture / "frames" / "cam00" / "000000.exr").write_bytes(b"full-on frame, other noise")
    assert capture_fingerprint(capture) == ours  # full-on frames render the same whatever the OLAT settings
    (capture / "frames" / "cam00" / "000001.exr").write_bytes(b"the same OLAT frame, other light samples")
    other = capture_fingerprint(capture)
    assert ours and other and ours != other and capture_fingerprint(tmp_path / "none") is None
    train = {"ours_novel_light_psnr": 27.25, "ours_novel_light_psnr_bar9": 27.0, "ours_novel_light_psnr_bar13": 27.5}
    (tmp_path / "light_oracle_alice.json").write_text(json.dumps({**_oracle([9, 13]), "capture_fingerprint": ours}))
    assert "27.25" in "".join(light_oracle_section(tmp_path, "alice", train, ours).parts)
    html = "".join(light_oracle_section(tmp_path, "alice", train, other).parts)
    assert "27.25" not in html and "another capture" in html
