"""relight_eval: the relit renders against the studio's ground truth (same map, light, view, expression).

For the first ``frames_per_sequence`` frames of every environment-map and point-light
sequence of ``relight/renders.json``, the studio ray traces the true subject (rebuilt from
``capture.truth/studio.json``, expression from ``frames.npz`` at the rendered mesh's frame,
head at the origin) under the same map (every direction, shadows, nothing masked) or point
light, from the same camera. Predictions are scaled to the truth's exposure (least squares,
as the paper does for novel lights; the network's light units are its own), both are
normalised by the truth's 99th-percentile head pixel, then PSNR and SSIM are taken.

Output: ``truth/<sequence>/<i:06d>.exr`` (the references), ``compare/<sequence>_<i>.png``
(truth | relit) and metrics ``envmap_psnr_mean``, ``envmap_ssim_mean``,
``pointlight_psnr_mean``, ``pointlight_ssim_mean`` and per-map ``envmap_<map>_psnr``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from pydantic import Field

from avatar.metrics import exposure_scale, psnr, ssim
from pipeline.errors import InputError
from pipeline.stage import Stage, StageContext, StageParams
from scene.camera import Camera
from scene.envmap import read_envmap
from scene.comparison_figure import ComparisonRow, write_comparison_figure
from scene.image_io import write_exr, write_png_srgb
from stages.capture.output import CaptureTruth
from stages.relight.output import RelightEvalOutput, RelightOutput


class RelightEvalParams(StageParams):
    """How much of the relight output to check, and how finely the truth integrates a map."""

    frames_per_sequence: int = Field(1, ge=1, description="Frames checked per sequence (from the first).")
    truth_directions: int = Field(1024, ge=16, description="Directional lights the studio integrates an environment map with.")


def compare_images(pred: np.ndarray, truth: np.ndarray, truth_alpha: np.ndarray) -> tuple[float, float, float]:
    """(PSNR dB, SSIM, exposure scale) of ``pred`` scaled to ``truth`` (both [H, W, 3] linear)."""
    p = torch.as_tensor(pred, dtype=torch.float64)[None]
    t = torch.as_tensor(truth, dtype=torch.float64)[None]
    s = exposure_scale(p, t)
    head = truth[truth_alpha > 0.5]
    white = float(np.percentile(head, 99)) if head.size else float(truth.max())
    white = max(white, 1e-8)
    p = (p * s[:, None, None, None]) / white
    t = t / white
    return float(psnr(p, t)[0]), float(ssim(p.float(), t.float())[0]), float(s[0])


def run(ctx: StageContext) -> None:
    from hardware.studio.envmap_truth import (frame_from_weights, render_envmap_truth, render_point_truth,
                                              subject_from_truth)

    params: RelightEvalParams = ctx.params
    relight, truth_out = RelightOutput(ctx.input("relight")), CaptureTruth(ctx.input("capture.truth"))
    out = RelightEvalOutput(ctx.out)
    manifest = relight.renders()
    weights_all = truth_out.frames(keys=("weights",))["weights"]
    try:
        subject = subject_from_truth(truth_out.path)
    except ValueError as err:
        raise InputError(f"relight_eval: {err}") from err
    # The relight stage drives the head with the first tracked mesh: capture frame 0.
    frame = frame_from_weights(weights_all[0])
    scores: dict[str, list[tuple[float, float]]] = {"envmap": [], "point": []}
    rows: dict[str, list[ComparisonRow]] = {"envmap": [], "point": []}
    out.compare_dir.mkdir()
    for name, records in manifest.items():
        for rec in records[:params.frames_per_sequence]:
            kind = rec.get("kind")
            if kind not in ("envmap", "point") or rec.get("mesh_index", 0) != 0:
                continue
            camera = Camera.from_dict(rec["camera"], "head")
            if kind == "envmap":
                envmap = read_envmap(rec["envmap"]).rotated_about_y(math.radians(rec["rotation_deg"]))
                truth = render_envmap_truth(subject, frame, camera, envmap, params.truth_directions)
            else:
                truth = render_point_truth(subject, frame, camera, np.asarray(rec["position"]), np.ones(3))
            pred = relight.frame(name, rec["index"])[..., :3]
            value_psnr, value_ssim, scale = compare_images(pred, truth.rgb, truth.alpha)
            scores[kind].append((value_psnr, value_ssim))
            if kind == "envmap":
                ctx.metrics[f"envmap_{Path(rec['envmap']).stem}_psnr"] = value_psnr
            out.truth_path(name, rec["index"]).parent.mkdir(parents=True, exist_ok=True)
            write_exr(out.truth_path(name, rec["index"]), truth.rgb)
            exposure = 0.8 / max(float(np.percentile(truth.rgb[truth.alpha > 0.5], 99))
                                 if (truth.alpha > 0.5).any() else 1.0, 1e-8)
            write_png_srgb(out.compare_path(name, rec["index"]),
                           np.concatenate([truth.rgb, pred * scale], axis=1), exposure=exposure)
            what = (f"map {Path(rec['envmap']).stem} turned {rec['rotation_deg']:.0f} deg" if kind == "envmap"
                    else "point light at (" + ", ".join(f"{v:.2f}" for v in rec["position"]) + ") m")
            rows[kind].append(ComparisonRow(f"{what}, frame {rec['index']}", truth.rgb, {"ours": pred * scale},
                                            truth_alpha=truth.alpha, notes={"ours": f"{value_psnr:.1f} dB"}))
            ctx.log.info("%s frame %d: PSNR %.2f dB, SSIM %.3f", name, rec["index"], value_psnr, value_ssim)
    captions = {}
    for kind, words in (("envmap", "Environment maps"), ("point", "Point lights")):
        if rows[kind]:
            h, w = rows[kind][0].truth.shape[:2]
            write_comparison_figure(out.figure_path(kind), rows[kind], f"{words}: the studio's ray-traced truth "
                                    f"against the relit head ({w} x {h} px)")
            captions[kind] = (f"{words}: the studio's ray-traced ground truth of the same subject, light, camera and "
                              f"expression, the relit head (scaled to the truth's exposure; PSNR above each) and its "
                              f"per-pixel error. Rendered at the relight stage's {w} x {h} px"
                              + (", drawn larger" if h < 256 else ""))
    out.captions_path.write_text(json.dumps(captions, indent=1))
    for kind, key in (("envmap", "envmap"), ("point", "pointlight")):
        if scores[kind]:
            ctx.metrics[f"{key}_psnr_mean"] = float(np.mean([s[0] for s in scores[kind]]))
            ctx.metrics[f"{key}_ssim_mean"] = float(np.mean([s[1] for s in scores[kind]]))
            ctx.metrics[f"{key}_frames_checked"] = len(scores[kind])
        else:
            ctx.log.warning("relight_eval: no %s frames to check in relight/renders.json", kind)


STAGE = Stage(
    name="relight_eval",
    inputs=("relight", "capture.truth"),
    params=RelightEvalParams,
    run=run,
    evaluates="relight",
    doc="PSNR/SSIM of envmap and point-light relights against the studio's ray-traced ground truth.",
)
