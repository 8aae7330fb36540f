"""Stage ``report``: one self-contained HTML page a supervisor opens in a browser.

It reads only what the other stages wrote (their ``metrics.json``, PNGs, optional
``tradeoffs/*.json`` speed-against-accuracy series and relight's ``paths.json``) and never the ground truth itself:
accuracy figures come from the evaluation stages' metrics.

Output::

    report.html        self-contained (images inlined), opens offline
    charts/*.png       the charts, also inlined in the page
    summary.json       every stage's merged metrics and every target's verdict

A ``tradeoffs/<name>.json`` file in any stage's output adds a chart:
``{"title", "x_label", "y_label", "points": [{"x", "y", "label"?, "series"?, "chosen"?}]}``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from pydantic import Field

from pipeline.stage import Stage, StageContext, StageParams
from pipeline.workspace import RUNNER_METRICS_FILE
from stages.capture.output import CaptureOutput
from stages.report.capacity import BENCH_PNG as CAPACITY_PNG, capacity_section
from stages.report.light_oracle import capture_fingerprint, light_oracle_section
from stages.report.output import ReportOutput
from stages.report.seeds import seeds_section
from stages.report.unseen import unseen_subjects_section
from stages.report.charts import stage_timings_chart, target_ratio_chart, tradeoff_chart
from stages.report.html import Section, Table, render_document
from stages.report.targets import TARGETS

# Product stages in pipeline order, each with its evaluation stage (if any).
STAGE_EVALS: tuple[tuple[str, str | None], ...] = (
    ("sequence", None), ("capture", "capture_eval"), ("calibrate", "calibrate_eval"), ("lightcal", "lightcal_eval"),
    ("track", "track_eval"), ("stabilize", "stabilize_eval"), ("matte", "matte_eval"),
    ("train", None), ("relight", "relight_eval"), ("evaluate", None),
)
SPLITS = (("novel_light", "novel light"), ("novel_perf", "novel performance"), ("novel_both", "both"))
# Validation: what settings are chosen on; shown apart, never as the result.
VAL_SPLITS = (("val_light", "validation light"), ("val_perf", "validation performance"))
MEASURES = (("psnr", "PSNR (dB)"), ("mae", "MAE"), ("ssim", "SSIM"), ("lpips", "LPIPS"))


class ReportParams(StageParams):
    """Params of the report stage."""

    title: str = Field("Relightable neural head: capture-to-relight report",
                       description="Heading of the page.")
    max_images_per_stage: int = Field(8, ge=0, description="At most this many PNGs shown per stage output.")
    bench_results: str | None = Field(
        "bench-results", description="Folder of `make bench` results (JSON figures, PNG charts and sweeps) "
        "to include, relative to the working directory; its content counts toward staleness. None: leave out.")


def bench_results_folder(params: ReportParams) -> list[Path]:
    """The benchmark folder as an external input, when it exists."""
    if params.bench_results and Path(params.bench_results).is_dir():
        return [Path(params.bench_results).resolve()]
    return []


def _read_metrics(folder: Path) -> dict[str, float]:
    path = folder / RUNNER_METRICS_FILE
    if not path.is_file():
        return {}
    values = json.loads(path.read_text(encoding="utf-8"))
    return {k: v for k, v in values.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def _fmt(value: float | None) -> str:
    if value is None:
        return "not measured"
    if isinstance(value, float) and (math.isnan(value) or math.isinf(value)):
        return str(value)
    if value == 0 or 1e-3 <= abs(value) < 1e5:
        return f"{value:.4g}"
    return f"{value:.3e}"


def merged_metrics(ctx: StageContext) -> dict[str, dict[str, float]]:
    """Each product stage's metrics merged with its evaluation's (eval keys win on clashes)."""
    merged = {}
    for stage, evaluator in STAGE_EVALS:
        metrics = _read_metrics(ctx.input(stage))
        if evaluator:
            metrics.update(_read_metrics(ctx.input(evaluator)))
        merged[stage] = metrics
    return merged


def _targets_section(merged: dict[str, dict[str, float]], charts: Path) -> tuple[Section, list[dict]]:
    section = Section("Accuracy against targets", "targets")
    table = Table(["stage", "target", "metric", "measured", "bound", "verdict"], table_id="targets-table")
    verdicts, ratio_rows = [], []
    for target in TARGETS:
        value, bound, passed = target.check(merged.get(target.stage, {}))
        verdict = {None: "not measured", True: "pass", False: "FAIL"}[passed]
        bound_text = f"{target.op} {_fmt(bound)}" + (f" ({target.bound})" if isinstance(target.bound, str) else "")
        css = {None: "na", True: "pass", False: "fail"}[passed]
        table.add([target.stage, target.what, target.key, _fmt(value), bound_text, verdict], ["", "", "", "", "", css])
        verdicts.append({"stage": target.stage, "key": target.key, "value": value, "bound": bound, "passed": passed})
        if passed is not None and value and bound and value > 0 and bound > 0:
            ratio = value / bound if target.op == "<=" else bound / value
            ratio_rows.append((f"{target.stage}: {target.key}", ratio, passed))
    section.table(table)
    if ratio_rows:
        chart = charts / "targets.png"
        target_ratio_chart(ratio_rows, chart)
        section.figure(chart, "measured / target for every target with a figure")
    return section, verdicts


def _splits_table(train: dict[str, float], header: list[str], splits, table_id: str) -> Table:
    """One row per split: each model's measures."""
    table = Table(header, table_id=table_id)
    for split, split_label in splits:
        cells = [split_label]
        for model in ("ours", "travatar"):
            cells += [_fmt(train.get(f"{model}_{split}_{key}")) for key, _ in MEASURES]
        table.add(cells)
    return table


def _paper_table_section(train: dict[str, float]) -> Section:
    section = Section("Ours vs TRAvatar* (held-out data, linear RGB)", "paper-table")
    header = ["split"] + [f"{m} {label}" for m in ("ours", "TRAvatar*") for _, label in MEASURES]
    section.table(_splits_table(train, header, SPLITS, "paper-table"))
    section.paragraph("The test splits of one training run (one draw of the seed): measured once, at the end. "
                      "Predictions for novel lights are scaled to the ground truth's exposure (least squares), "
                      "as in the paper. Higher PSNR/SSIM and lower MAE/LPIPS are better.", "note")
    if any(f"ours_{split}_psnr" in train for split, _ in VAL_SPLITS):
        val = _splits_table(train, header, VAL_SPLITS, "validation-table")
        section.paragraph("Validation splits (their own held-out bars and frames, disjoint from the test's): every "
                          "automatic choice and every preset setting is made on these, never on the test splits.")
        section.table(val)
    by_bar = {name: _held_out_bar_psnrs(train, model) for model, name in (("ours", "ours"), ("travatar", "TRAvatar*"))}
    if any(by_bar.values()):
        # The novel-light mean depends on which bars were held out (brighter images, larger errors).
        parts = "; ".join(f"{name} " + ", ".join(f"bar {b} {v:.2f}" for b, v in rows)
                          for name, rows in by_bar.items() if rows)
        section.paragraph(f"Novel light per held-out bar (PSNR dB): {parts}.", "note")
    return section


def _held_out_bar_psnrs(train: dict[str, float], model: str) -> list[tuple[int, float]]:
    """(bar, PSNR) of ``model`` under each held-out bar (the train stage's ``{model}_novel_light_psnr_bar{id}``)."""
    prefix = f"{model}_novel_light_psnr_bar"
    return sorted((int(k[len(prefix):]), float(v)) for k, v in train.items()
                  if k.startswith(prefix) and k[len(prefix):].isdigit())


def _stage_section(ctx: StageContext, stage: str, evaluator: str | None, metrics: dict[str, float],
                   limit: int) -> Section:
    section = Section(f"Stage: {stage}", f"stage-{stage}")
    table = Table(["metric", "value"], table_id=f"metrics-{stage}")
    for key in sorted(metrics):
        table.add([key, _fmt(metrics[key])])
    if metrics:
        section.table(table)
    else:
        section.paragraph("This stage reported no metrics.", "note")
    paths = _render_paths_table(ctx.input(stage), stage)
    if paths is not None:
        section.paragraph("How each sequence was rendered: 'bake' from the light-transfer bake of its view and "
                          "expression (a weighted sum of basis images), 'voxel_sum' through the network every frame.")
        section.table(paths)
    folders = [ctx.input(stage)] + ([ctx.input(evaluator)] if evaluator else [])
    names = [stage] + ([evaluator] if evaluator else [])
    pngs = [(name, p) for name, folder in zip(names, folders) for p in sorted(folder.glob("*.png"))][:limit]
    for name, png in pngs:
        # In words: the stage that drew it and the picture's name (its folder is a content digest).
        section.figure(png, f"{name}: {png.stem.replace('_', ' ')}")
    return section


def _pictures_section(ctx: StageContext) -> Section | None:
    """The paper's comparison figures: every held-out split of train, and the relit head against the studio's truth."""
    from stages.relight.output import RelightEvalOutput
    from stages.train.output import TrainOutput

    figures = TrainOutput(ctx.input("train")).comparisons()
    figures += RelightEvalOutput(ctx.input("relight_eval")).figures()
    if not figures:
        return None
    section = Section("Pictures: held-out images and relighting against the ground truth", "pictures")
    section.paragraph("Each row: the ground truth, each model's render, and each model's per-pixel error as a heat "
                      "map (mean absolute error over RGB as a fraction of the ground truth's white; the colour bar "
                      "gives the scale, shared within a figure).")
    for png, caption in figures:
        section.figure(png, caption, wide=True)
    return section


def _render_paths_table(folder: Path, stage: str) -> Table | None:
    """The stage's ``paths.json`` (relight: sequence -> path, frames, reason) as a table; None if absent or unreadable."""
    try:
        paths = json.loads((folder / "paths.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(paths, dict):
        return None
    table = Table(["sequence", "path", "frames", "why"], table_id=f"paths-{stage}")
    for name, entry in paths.items():
        if isinstance(entry, dict):
            table.add([name, str(entry.get("path", "?")), str(entry.get("frames", "")), str(entry.get("reason", ""))])
    return table


def _tradeoff_charts(ctx: StageContext, charts: Path) -> list[tuple[Path, str]]:
    made = []
    for stage, evaluator in STAGE_EVALS:
        for folder in [ctx.input(stage)] + ([ctx.input(evaluator)] if evaluator else []):
            for spec_path in sorted((folder / "tradeoffs").glob("*.json")):
                try:
                    spec = json.loads(spec_path.read_text(encoding="utf-8"))
                    chart = charts / f"tradeoff_{stage}_{spec_path.stem}.png"
                    tradeoff_chart(spec["title"], spec["x_label"], spec["y_label"], spec["points"], chart)
                except (ValueError, KeyError, TypeError) as err:
                    ctx.log.warning("%s: not a valid trade-off series (%s); skipped", spec_path, err)
                    continue
                made.append((chart, spec["title"]))
    return made


def _bench_section(folder: Path, skip: tuple[str, ...] = ()) -> Section:
    """The figures and charts `make bench` wrote (speed/accuracy sweeps, stability sweeps)."""
    section = Section("Benchmarks and sweeps (make bench)", "bench")
    section.paragraph(f"From {folder}; each benchmark's scalar figures, then its charts. Benchmarks run on "
                      "whatever machine ran `make bench`; see each file's notes.", "note")
    for path in sorted(folder.glob("*.json")):
        try:
            figures = json.loads(path.read_text(encoding="utf-8"))
        except ValueError:
            section.paragraph(f"{path.name}: not valid JSON, skipped", "note")
            continue
        if not isinstance(figures, dict):
            continue
        scalars = {k: v for k, v in figures.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        if scalars:
            table = Table([path.stem, "value"], table_id=f"bench-{path.stem}")
            for key, value in scalars.items():
                table.add([key, _fmt(value)])
            section.table(table)
    for png in sorted(folder.glob("*.png")):
        if png.name not in skip:  # charts a section of their own already shows
            section.figure(png, f"bench: {png.stem.replace('_', ' ')}")
    return section


def run(ctx: StageContext) -> None:
    """Collect every stage's metrics and pictures into report.html."""
    params: ReportParams = ctx.params
    out = ReportOutput(ctx.out)
    charts = out.charts_dir
    charts.mkdir()
    merged = merged_metrics(ctx)

    sections: list[Section] = []
    glance = Section("The capture at a glance", "capture")
    capture = merged["capture"]
    glance_table = Table(["cameras", "frames", "full-on", "OLAT", "dropped", "seconds"], table_id="capture-table")
    glance_table.add([_fmt(capture.get(k)) for k in
                      ("cameras", "frames", "full_on_frames", "olat_frames", "dropped_frames", "seconds")])
    glance.table(glance_table)
    for name, path in CaptureOutput(ctx.input("capture")).previews():
        if path.is_file():
            glance.figure(path, name.removesuffix(".png").replace("_", " "))
    sections.append(glance)

    targets_section, verdicts = _targets_section(merged, charts)
    sections.append(targets_section)
    sections.append(_paper_table_section(merged["train"]))
    pictures = _pictures_section(ctx)
    if pictures is not None:
        sections.append(pictures)
    bench = bench_results_folder(params)
    spread = seeds_section(bench[0], ctx.subject) if bench else None
    if spread is not None:
        sections.append(spread)
    unseen = unseen_subjects_section(bench[0]) if bench else None
    if unseen is not None:
        sections.append(unseen)
    oracle = (light_oracle_section(bench[0], ctx.subject, merged["train"], capture_fingerprint(ctx.input("capture")))
              if bench else None)
    if oracle is not None:
        sections.append(oracle)

    tradeoffs = _tradeoff_charts(ctx, charts)
    if tradeoffs:
        speed = Section("Speed against accuracy", "tradeoffs")
        for chart, title in tradeoffs:
            speed.figure(chart, title)
        sections.append(speed)

    if bench:
        capacity = capacity_section(bench[0], charts)
        if capacity is not None:
            sections.append(capacity)
        sections.append(_bench_section(bench[0], skip=(CAPACITY_PNG,) if capacity is not None else ()))

    seconds = {}
    for stage, evaluator in STAGE_EVALS:
        for name in (stage, evaluator):
            if name:
                own = _read_metrics(ctx.input(name))
                value = own.get("stage_seconds", own.get("seconds"))
                if value is not None:
                    seconds[name] = float(value)
    timing = Section("Timings", "timings")
    if seconds:
        chart = charts / "timings.png"
        stage_timings_chart(seconds, chart)
        timing.figure(chart, "wall-clock seconds of each stage's last run")
    timing_table = Table(["stage", "seconds"], table_id="timings-table")
    for name, value in seconds.items():
        timing_table.add([name, _fmt(value)])
    timing.table(timing_table)
    sections.append(timing)

    for stage, evaluator in STAGE_EVALS:
        sections.append(_stage_section(ctx, stage, evaluator, merged[stage], params.max_images_per_stage))

    failed = sum(v["passed"] is False for v in verdicts)
    measured = sum(v["passed"] is not None for v in verdicts)
    subtitle = (f"subject {ctx.subject}; generated {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; "
                f"{measured - failed}/{measured} measured targets met")
    out.write_html(render_document(params.title, subtitle, sections))
    out.write_summary({"metrics": merged, "targets": verdicts})
    ctx.metrics["targets_measured"] = measured
    ctx.metrics["targets_failed"] = failed
    ctx.log.info("report: %d/%d measured targets met -> %s", measured - failed, measured, out.html_path)


STAGE = Stage(
    name="report",
    inputs=tuple(name for pair in STAGE_EVALS for name in pair if name),
    params=ReportParams,
    run=run,
    external_inputs=bench_results_folder,
    reads_metrics=True,  # the report shows every stage's figures, timings included
    doc="A self-contained HTML report of every stage's figures against the targets.",
)
