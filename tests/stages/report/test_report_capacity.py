"""The report's capacity section, drawn from bench-results/capacity.json when it exists."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.testing import run_stage_for_test
from stages.report.capacity import capacity_section
from stages.report.stage import STAGE, STAGE_EVALS


def _sweep() -> dict:
    points = []
    for texels, n, m, psnr, its in ((32, 16, 2, 20.0, 12.0), (64, 16, 4, 22.5, 9.0), (128, 32, 4, 23.0, 3.0),
                                    (256, 32, 8, 23.1, 1.5)):
        points.append({"texels_per_side": texels, "prims_per_side": n, "voxels_per_side": m, "primitives": n * n,
                       "parameters": 1000 * texels, "heldout_psnr": psnr, "iterations_per_second": its,
                       "peak_memory_mb": 500.0 + texels, "pruned_primitives": 3, "texel_px": 95.0 / texels,
                       "rule_choice": texels == 64})
    return {"source": "test", "iterations_per_size": 10, "rule_inputs": {"image_width_px": 64, "image_height_px": 85,
                                                                          "footprint_px": 52.0, "frames": 45},
            "rule_texels_per_side": 64, "rule_primitives": 256, "rule_voxels_per_side": 4, "rule_width": 56,
            "knee_texels_per_side": 64, "default_at_knee": True, "verdict": "the rule's default sits at the knee",
            "points": points, "note": "test data"}


def test_capacity_section_shows_chart_table_and_verdict(tmp_path: Path) -> None:
    bench = tmp_path / "bench"
    bench.mkdir()
    charts = tmp_path / "charts"
    charts.mkdir()
    assert capacity_section(bench, charts) is None  # no sweep yet: no section
    (bench / "capacity.json").write_text(json.dumps(_sweep()))
    section = capacity_section(bench, charts)
    html = "".join(section.parts)
    assert (charts / "capacity.png").stat().st_size > 1000
    assert 'id="capacity-table"' in html and "data:image/png;base64," in html
    assert "sits at the knee" in html and html.count("<tr>") == 5  # header + 4 sizes
    (bench / "capacity.json").write_text("{not json")
    assert capacity_section(bench, charts) is None


def test_report_page_has_the_capacity_section(tmp_path: Path) -> None:
    inputs = {}
    for stage, evaluator in STAGE_EVALS:
        for name in (stage, evaluator):
            if name:
                folder = tmp_path / "inputs" / name
                folder.mkdir(parents=True)
                (folder / "metrics.json").write_text("{}")
                inputs[name] = folder
    bench = tmp_path / "bench-results"
    bench.mkdir()
    (bench / "capacity.json").write_text(json.dumps(_sweep()))
    (bench / "capacity.png").write_bytes((Path(__file__).parent / "test_report_capacity.py").read_bytes()[:0])
    out = run_stage_for_test(STAGE, tmp_path / "work", inputs=inputs, params={"bench_results": str(bench)})
    page = (out / "report.html").read_text()
    assert 'id="capacity"' in page and 'id="capacity-table"' in page
    assert "bench: capacity" not in page  # the bench's own PNG is not shown twice
    assert (out / "charts" / "capacity.png").is_file()
