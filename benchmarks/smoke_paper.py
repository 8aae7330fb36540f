"""The ``paper`` preset's train and relight code paths on a CPU, reduced to what a CPU can run in minutes.

``make smoke-paper`` (and the slow-marked ``tests/integration/test_paper_preset.py``) runs the
train stage and then the relight stage with ``configs/presets/paper.yaml``'s sections, changed
only where a CPU cannot afford them (``CPU_REDUCTIONS``):

- kept: 768 x 1024 training images (the capture's size), N = 64 primitives a side and M = 16
  voxels a primitive, the latent size, the memory-mapped training images (the preset's 768 px
  frames are spilled to disk and gathered per batch), a whole take held out as the novel
  performance, checkpoints, outputs, and a 768 x 1024 relight frame;
- reduced: 2 iterations of each model at batch 2, the decoders' channels (32 to 16 wide instead
  of 256 to 32) and 16 raymarch steps, one evaluation image a split, assessment renders at
  96 x 128 (``train.assess_width_px``) and 256 px comparison figures (``train.figure_height_px``).

The input is a synthetic capture at 768 x 1024 (2 cameras, 36 frames, rendered like the train
tests'), not the virtual studio's: the studio's stages upstream of train have their own tests
at their own sizes, and rendering them at 768 x 1024 would take most of CI's time.

It checks the shapes, the spilled data, the checkpoints and every output, and writes the
timings and the projected peak GPU memory of the paper's full configuration at batch 12
(``stages.train.memory``) to ``bench-results/smoke_paper.json``. Nothing here is an accuracy
figure.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench-results"

#: What the smoke run changes in the paper preset's train and relight sections, and nothing else.
CPU_REDUCTIONS: dict[str, dict[str, Any]] = {
    "train": {
        "iterations": 2, "baseline_iterations": 2, "batch_size": 2, "rays_per_image": 1024,
        "avatar": {"encoder_hidden": 64, "base_channels": 32, "rgb_channels": [32, 32, 16, 16, 16, 16, 48],
                   "alpha_channels": [32, 32, 16, 16, 16, 16, 16], "geometry_channels": 16, "steps_per_ray": 16},
        "eval_images": 1, "curve_every": 1, "curve_images": 1, "checkpoint_every": 1, "previews": 1,
        "assess_width_px": 96, "figure_height_px": 256,
        "resident_limit_gb": 0.01,  # the paper's captures are spilled; this one must be too
        "threads": 2,
    },
    "relight": {"envmaps": [], "orbit_frames": 1, "turntable_frames": 0, "dolly_zoom_frames": 0,
                "naive_timing_frames": 0, "bake_check": False, "steps_per_ray": 16},
}
#: The synthetic capture: the paper's image width, two cameras, a 27-frame take and a 9-frame one.
CAPTURE = {"width_px": 768, "cameras": 2, "frames_per_take": (27, 9)}


def paper_params(stage: str) -> dict[str, Any]:
    """The paper preset's section of ``stage`` with the CPU reductions applied."""
    from benchmarks.bench_seeds import merge_params
    from pipeline.yamlio import read_yaml_mapping

    preset = read_yaml_mapping(ROOT / "configs" / "presets" / "paper.yaml", "configs/presets/paper.yaml")
    return merge_params(dict(preset.get(stage) or {}), CPU_REDUCTIONS.get(stage, {}))


def projected_paper_memory(batch: int = 12) -> dict[str, float]:
    """Projected peak training memory (GB) of the paper's full configuration at ``batch`` images of 8192 rays."""
    import numpy as np

    from avatar.config import AvatarConfig
    from avatar.layout import build_layout
    from scene.face_rig import load_face_rig
    from scene.view import ViewSpec
    from stages.train.memory import project_training_memory

    config = AvatarConfig.paper()
    face = load_face_rig()
    neutral = np.asarray(face.vertices(None, np.zeros(len(face.expression_names))), np.float32)
    layout = build_layout(neutral, face.triangles, config.prims_per_side)
    view = ViewSpec(768, 1024, 0.6, 30.0)
    projection = project_training_memory(config, layout, view.camera(view.front_eye()), batch, 8192, sample_rays=512)
    return projection.as_dict()


def _check(ok: bool, what: str, problems: list[str]) -> None:
    if not ok:
        problems.append(what)


def run(scratch: Path) -> dict[str, Any]:
    """Synthetic capture -> train -> relight in ``scratch``; the figures and the problems found (none is a pass)."""
    from pipeline.scratch import run_stage_in_folder
    from stages.relight.stage import STAGE as RELIGHT
    from stages.train.stage import STAGE as TRAIN

    sys.path.insert(0, str(ROOT / "tests" / "stages" / "train"))
    from train_synth import make_capture

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    inputs = make_capture(scratch / "synth", **CAPTURE)
    seconds["synthetic_capture"] = time.perf_counter() - start
    start = time.perf_counter()
    train = run_stage_in_folder(TRAIN, scratch / "train_run", inputs, paper_params("train"), subject="paper-smoke")
    seconds["train_stage"] = time.perf_counter() - start
    start = time.perf_counter()
    relight = run_stage_in_folder(RELIGHT, scratch / "relight_run", {"train": train, "track": inputs["track"],
                                                                      "capture": inputs["capture"]},
                                  paper_params("relight"), subject="paper-smoke")
    seconds["relight_stage"] = time.perf_counter() - start
    problems = output_problems(inputs, train, relight)
    metrics = json.loads((train / "metrics.json").read_text())
    start = time.perf_counter()
    memory = projected_paper_memory()
    seconds["memory_projection"] = time.perf_counter() - start
    return {"seconds": seconds, "train_iterations_per_second": metrics.get("iterations_per_second"),
            "train_peak_memory_mb": metrics.get("peak_memory_mb"),
            "relight_metrics": json.loads((relight / "metrics.json").read_text()),
            "projected_paper_training_memory_batch12": memory, "reductions": CPU_REDUCTIONS, "capture": CAPTURE,
            "problems": problems}


def output_problems(inputs: dict[str, Path], train: Path, relight: Path) -> list[str]:
    """What is wrong with the train and relight outputs of a smoke run (empty: every check passed)."""
    import cv2
    import numpy as np

    from stages.capture.output import CaptureOutput
    from stages.relight.output import RelightOutput
    from stages.train.output import TrainOutput

    problems: list[str] = []
    metrics = json.loads((train / "metrics.json").read_text())
    out = TrainOutput(train)
    _check(metrics.get("image_width_px") == 768, f"trained at {metrics.get('image_width_px')} px, not 768", problems)
    _check(metrics.get("assess_width_px") == 96, f"assessed at {metrics.get('assess_width_px')} px, not 96", problems)
    _check(metrics.get("capacity_prims_per_side") == 64 and metrics.get("capacity_voxel_res") == 16,
           f"N={metrics.get('capacity_prims_per_side')}, M={metrics.get('capacity_voxel_res')}, not 64 and 16", problems)
    _check(metrics.get("images_memory_mapped") == 1, "the training images were not memory-mapped", problems)
    _check(metrics.get("iterations") == 2 and metrics.get("travatar_iterations") == 2,
           "each model should have run 2 iterations", problems)
    for model in ("ours", "travatar"):
        for split in ("val_light", "val_perf", "novel_light", "novel_perf", "novel_both"):
            value = metrics.get(f"{model}_{split}_psnr")
            _check(value is not None and np.isfinite(value), f"{model}_{split}_psnr is {value}", problems)
        _check((out.model_dir(model) / "model.safetensors").is_file(), f"no saved {model} model", problems)
    checkpoints = sorted(p.name for p in (train.parent / ".cache" / "train").rglob("*.pt"))
    _check({"ours.pt", "travatar.pt"} <= set(checkpoints), f"checkpoints written: {checkpoints}", problems)
    splits = json.loads(out.splits_path.read_text())
    manifest = CaptureOutput(inputs["capture"]).manifest(keys=("frames",))
    speech = {f["index"] for f in manifest["frames"] if f.get("take") == "speech"}
    _check(splits["held_out_take"] == "speech" and not speech & set(splits["train"]) and splits["novel_perf"]
           and set(splits["novel_perf"]) <= speech, "the novel performance is not the whole last take", problems)
    preview = cv2.imread(str(out.previews_dir / "novel_light_0.png"))
    _check(preview is not None and preview.shape[:2] == (128, 3 * 96),
           f"preview shape {None if preview is None else preview.shape}", problems)
    figure = cv2.imread(str(out.comparisons_dir / "novel_light.png"))
    _check(figure is not None and figure.shape[0] >= 256, "no 256 px comparison figure", problems)
    relit = RelightOutput(relight)
    orbit = relit.renders().get("point_orbit", [])
    shape = relit.frame("point_orbit", 0).shape if orbit else None
    _check(shape is not None and shape[:2] == (1024, 768), f"relight frame shape {shape}", problems)
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scratch", type=Path, default=None, help="working folder (default: a temporary one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    with tempfile.TemporaryDirectory(prefix="smoke-paper-") as tmp:
        result = run(args.scratch or Path(tmp))
    OUT.mkdir(exist_ok=True)
    (OUT / "smoke_paper.json").write_text(json.dumps(result, indent=1) + "\n")
    memory = result["projected_paper_training_memory_batch12"]
    print(f"paper preset, reduced for a CPU: {json.dumps(result['seconds'])} s; projected peak training memory of "
          f"the paper's configuration at batch 12: {memory['projected_peak_gb']:.2f} GB (a lower bound)")
    for problem in result["problems"]:
        print(f"problem: {problem}")
    return 1 if result["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
