"""The report's capacity section: the sweep of ``benchmarks/bench_capacity.py`` (``bench-results/capacity.json``).

Shows the curve that justifies the capacity rule (held-out PSNR and cost against N*M, the
rule's choice and the knee marked), the table of the sweep and whether the rule's default
sits at the knee.
"""

from __future__ import annotations

import json
from pathlib import Path

from stages.report.charts import capacity_chart
from stages.report.html import Section, Table

#: The bench's own PNG; the section draws the chart from the JSON instead.
BENCH_PNG = "capacity.png"


def _fmt(value, digits: int = 2) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else ""
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def capacity_section(bench_folder: Path, charts: Path) -> Section | None:
    """The section, or None when the bench has not written ``capacity.json`` (or it is unreadable)."""
    path = Path(bench_folder) / "capacity.json"
    if not path.is_file():
        return None
    try:
        sweep = json.loads(path.read_text(encoding="utf-8"))
        points = list(sweep["points"])
        for p in points:
            p["knee"] = p["texels_per_side"] == sweep.get("knee_texels_per_side")
    except (ValueError, KeyError, TypeError):
        return None
    section = Section("Capacity a scene needs", "capacity")
    inputs = sweep.get("rule_inputs", {})
    section.paragraph(
        f"The capacity rule (avatar.capacity) chose N*M = {sweep.get('rule_texels_per_side')} texels per UV side "
        f"({sweep.get('rule_primitives')} primitives of {sweep.get('rule_voxels_per_side')}^3 voxels, decoder "
        f"width {sweep.get('rule_width')}) from {inputs.get('image_width_px')}x{inputs.get('image_height_px')} px "
        f"training images, a head {_fmt(inputs.get('footprint_px'), 1)} px wide and {inputs.get('frames')} training "
        f"frames. Sweep: {sweep.get('source')}, {sweep.get('iterations_per_size')} iterations per size. "
        f"{sweep.get('verdict', '')}.")
    chart = charts / "capacity.png"
    capacity_chart(points, chart, f"knee at N*M = {sweep.get('knee_texels_per_side')}, "
                                  f"rule's choice N*M = {sweep.get('rule_texels_per_side')}")
    section.figure(chart, "capacity against held-out PSNR and cost (red: the rule's choice, green: the knee)")
    table = Table(["N*M", "N", "M", "primitives", "parameters", "held-out PSNR (dB)", "it/s", "peak MB",
                   "pruned", "texel px", "rule", "knee"], table_id="capacity-table")
    for p in sorted(points, key=lambda q: q["texels_per_side"]):
        table.add([_fmt(p.get("texels_per_side")), _fmt(p.get("prims_per_side")), _fmt(p.get("voxels_per_side")),
                   _fmt(p.get("primitives")), _fmt(p.get("parameters")), _fmt(p.get("heldout_psnr")),
                   _fmt(p.get("iterations_per_second")), _fmt(p.get("peak_memory_mb"), 0),
                   _fmt(p.get("pruned_primitives")), _fmt(p.get("texel_px")), _fmt(bool(p.get("rule_choice"))),
                   _fmt(bool(p.get("knee")))])
    section.table(table)
    if sweep.get("note"):
        section.paragraph(str(sweep["note"]), "note")
    return section
