"""The report's light-interpolation section: ``benchmarks/bench_light_oracle.py`` beside the models.

For the report's subject: on the images the train stage scores its held-out lights on, what a
perfect render scores against the captured targets, what blending the training lights' perfect
images scores (TRAvatar*'s rule, and blends fitted to the answer), and what ours and TRAvatar*
score in the train stage's metrics. The oracle is measured on one capture: when the report's
models were trained on another (``capture_fingerprint``) or held out other bars, the figures
are not comparable, and the section leaves the models out and says why.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from stages.capture.output import CaptureOutput
from stages.report.html import Section, Table

#: The oracle's columns, in the order of its JSON keys' prefixes.
ORACLE_COLUMNS = (("clean_render_vs_captured", "perfect render"),
                  ("barycentric_vs_captured", "TRAvatar*'s rule on perfect images"),
                  ("triangle_fit_vs_captured", "3 bars, fitted"),
                  ("triangle_tile_fit_vs_captured", "3 bars, fitted per 8 px tile"),
                  ("all_bars_fit_vs_captured", "all training bars, fitted"))
SPLIT_LABELS = {"novel_light": "novel light", "novel_both": "both"}


def capture_fingerprint(capture: Path) -> str | None:
    """A short hash naming one capture's content: its manifest and its first camera's first OLAT frame.

    Two captures of the same performance with other render settings (light samples per bar,
    noise) hold other OLAT images, so their oracles differ; the fingerprint tells them apart
    without hashing every frame (a full-on frame would not: it is rendered the same way). None
    when the folder has no readable manifest.
    """
    capture = CaptureOutput(capture)
    try:
        text = capture.manifest_bytes()
        frames = json.loads(text).get("frames", [])
    except (OSError, ValueError, AttributeError):
        return None
    digest = hashlib.sha256(text)
    olat = [f["index"] for f in frames if isinstance(f, dict) and isinstance(f.get("light"), int)
            and f.get("status", "ok") == "ok" and "index" in f]
    cameras = capture.frame_cameras()
    if olat and cameras:
        frame = capture.frame_path(cameras[0].name, int(olat[0]))
        if frame.is_file():
            digest.update(frame.read_bytes())
    return digest.hexdigest()[:16]


def light_oracle_section(bench_folder: Path, subject: str, train: dict[str, float],
                         capture: str | None = None) -> Section | None:
    """The section, or None when ``light_oracle_<subject>.json`` is missing or unreadable.

    ``train``: the train stage's metrics (``{model}_{split}_psnr``, ``{model}_novel_light_psnr_bar{id}``).
    ``capture``: ``capture_fingerprint`` of the capture the report's models were trained on; the
    models are shown beside the oracle only when it was measured on that capture (or either
    fingerprint is unknown) with the same held-out bars.
    """
    path = Path(bench_folder) / f"light_oracle_{subject}.json"
    if not path.is_file():
        return None
    try:
        result = json.loads(path.read_text(encoding="utf-8"))
        per_split = {split: {key: float(result["psnr_db_per_split"][split][key]) for key, _ in ORACLE_COLUMNS}
                     for split in SPLIT_LABELS if split in result["psnr_db_per_split"]}
        held = sorted(int(b) for b in result["held_out_bars"])
    except (ValueError, KeyError, TypeError):
        return None
    prefix = "ours_novel_light_psnr_bar"
    trained_held = sorted(int(k[len(prefix):]) for k in train if k.startswith(prefix) and k[len(prefix):].isdigit())
    oracle_capture = result.get("capture_fingerprint")
    same_capture = capture is None or oracle_capture is None or oracle_capture == capture
    comparable = trained_held == held and same_capture
    section = Section("How far interpolating the training lights goes (PSNR, dB)", "light-oracle")
    section.paragraph(
        f"`benchmarks/bench_light_oracle.py` on the train stage's own held-out-light images ({result.get('images_per_split')} "
        f"a split, held-out bars {', '.join(map(str, held))}): each image predicted from perfect renders of the same frame "
        "and camera under the training bars. The fitted blends see the answer: they bound methods that blend "
        "training-light images (TRAvatar* is one), not every model. Scored against the captured images, as the "
        "train stage scores the models.")
    models = (("ours", "ours"), ("travatar", "TRAvatar*")) if comparable else ()
    table = Table(["split"] + [label for _, label in ORACLE_COLUMNS] + [name for _, name in models],
                  table_id="light-oracle-table")
    for split, row in per_split.items():
        cells = [SPLIT_LABELS[split]] + [f"{row[key]:.2f}" for key, _ in ORACLE_COLUMNS]
        for model, _ in models:
            value = train.get(f"{model}_{split}_psnr")
            cells.append("-" if value is None else f"{float(value):.2f}")
        table.add(cells)
    section.table(table)
    if not comparable:
        why = (f"held out bars {', '.join(map(str, trained_held)) or '(none recorded)'}, not the oracle's"
               if same_capture else "was trained on another capture than the oracle's")
        section.paragraph(f"The train run {why}, so the models are left out. Run "
                          f"`ORACLE_SUBJECT={subject} python -m benchmarks.run_all light_oracle` again.", "note")
    return section
