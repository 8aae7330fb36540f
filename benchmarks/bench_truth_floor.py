"""How clean the training targets are: the PSNR ceiling the virtual capture's own noise sets.

The studio renders each OLAT image with a few jittered light samples per bar and pixel,
jittered sub-pixel samples on the silhouette only, and shot + read sensor noise (see
``hardware.studio.renderer``). A model is scored against those noisy images, so their
noise is a floor under its error. This bench re-renders OLAT pulses of a subject's capture
as the capture did (its render settings and noise seeds, the true cameras) and
again cleanly (``TRUTH_BAR_SAMPLES`` light samples per bar, 6 x 6 silhouette samples, no
sensor noise), shrinks both to the train stage's width with the same filter (INTER_AREA),
scales them by the train stage's exposure (``image_scale`` from the subject's train metrics,
else the 99.5th percentile of the clean foreground, as the train stage computes it) and
reports PSNR(captured, clean) per image and for the mean squared error over all.

The pulses here are spread over the rig; the images the train stage scores its held-out lights
on can be far noisier (glints of a bar sampled at 3 points): ``bench_light_oracle``'s "clean
render" column is the same figure on exactly those images.

Knobs: ``TRUTH_SUBJECT`` (default alice; needs ``make subject S=<subject>`` first),
``TRUTH_PULSES`` (OLAT pulses, default 4, under bars spread over the rig), ``TRUTH_CAMERAS``
(every k-th camera, default 3), ``TRUTH_BAR_SAMPLES`` (default 24), ``TRUTH_WIDTH`` (default:
the tiny preset's training width). About a minute on one core. Writes
``bench-results/truth_floor_<subject>.json``.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from benchmarks.train_runs import ROOT, tiny_train_params


def main() -> dict:
    import cv2

    from hardware.studio.performance import FrameState
    from hardware.studio.renderer import RenderSettings, VirtualStudio
    from hardware.studio.subject import make_subject
    from pipeline.errors import PipelineError
    from pipeline.workspace import Workspace, workspace_root
    from scene.camera import Rigid
    from scene.rig import default_rig
    from stages.capture.output import CaptureTruth

    subject = os.environ.get("TRUTH_SUBJECT", "alice")
    pulses = int(os.environ.get("TRUTH_PULSES", "4"))
    every_camera = int(os.environ.get("TRUTH_CAMERAS", "3"))
    bar_samples = int(os.environ.get("TRUTH_BAR_SAMPLES", "24"))
    width = int(os.environ.get("TRUTH_WIDTH", "0")) or int(tiny_train_params()["image_width_px"])
    try:
        ws = Workspace(workspace_root(ROOT), subject)
        truth = CaptureTruth(ws.output_path("capture", "truth"))
        studio_json = truth.studio()
    except (PipelineError, OSError, ValueError) as err:
        print(f"truth floor: no capture for subject '{subject}' ({err}); run `make subject S={subject}` first")
        return {}
    frames = truth.frames()
    lit = truth.lights_per_pulse()
    cameras = truth.cameras()[::every_camera]
    captured = RenderSettings(**studio_json["render_settings"])
    clean = replace(captured, bar_samples=bar_samples, edge_samples=6, shot_noise_gain=0.0, read_noise=0.0)
    person = make_subject(studio_json["subject"], studio_json["identity_seed"], texture_size=studio_json["texture_size"])
    # The capture stage films with the default rig (its params hold no other); the bars' ids match the truth's.
    noisy_studio, clean_studio = VirtualStudio(default_rig(), person, captured), VirtualStudio(default_rig(), person, clean)
    first_pulse_of_bar: dict[int, int] = {}
    for i, light in enumerate(lit):
        if isinstance(light, int):
            first_pulse_of_bar.setdefault(light, i)
    bars = sorted(first_pulse_of_bar)  # bars spread over the rig, one pulse each
    picked = [first_pulse_of_bar[bars[k * len(bars) // pulses]] for k in range(min(pulses, len(bars)))]
    pairs = []
    for i in picked:
        frame = FrameState(int(frames["index"][i]), str(frames["take"][i]), float(frames["time_s"][i]),
                           frames["weights"][i].astype(np.float64),
                           Rigid(frames["world_from_head_R"][i], frames["world_from_head_t"][i]))
        for cam in cameras:
            height = int(round(cam.height * width / cam.width))
            a = noisy_studio.render(frame, cam, lit[i])
            b = clean_studio.render(frame, cam, lit[i], noise=False)
            shrink = (lambda img: cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA))
            pairs.append((i, lit[i], cam.name, shrink(a.rgb), shrink(b.rgb), shrink(b.alpha)))
    scale, scale_from = _exposure(ws, pairs)
    per_image, sq = [], []
    for i, bar, cam, a, b, _ in pairs:
        err = float(((scale * (a - b)) ** 2).mean())
        sq.append(err)
        per_image.append({"pulse": i, "bar": bar, "camera": cam, "psnr_db": _psnr(err)})
        print(f"pulse {i:3d} bar {bar:2d} {cam}: {_psnr(err):.2f} dB", flush=True)
    floor = _psnr(float(np.mean(sq)))
    print(f"truth floor, {subject}: PSNR(captured, clean) {floor:.2f} dB at {width} px wide over {len(sq)} images "
          f"(exposure x{scale:.2f} from {scale_from}): a perfect model, rendering the clean images, scores "
          "this against the captured ones")
    results = {"subject": subject, "width_px": width, "image_scale": scale, "image_scale_from": scale_from,
               "captured_settings": asdict(captured), "clean_settings": asdict(clean),
               "psnr_db": floor, "images": per_image}
    out = ROOT / "bench-results"
    out.mkdir(exist_ok=True)
    (out / f"truth_floor_{subject}.json").write_text(json.dumps(results, indent=1))
    return results


def _psnr(mse: float) -> float:
    return float(10.0 * np.log10(1.0 / max(mse, 1e-20)))


def _exposure(ws, pairs: list) -> tuple[float, str]:
    """The train stage's image scale for this subject, else its rule applied to the clean renders."""
    from pipeline.errors import PipelineError

    try:
        metrics = json.loads((Path(ws.output_path("train")) / "metrics.json").read_text())
        return float(metrics["image_scale"]), "the subject's train metrics"
    except (PipelineError, OSError, ValueError, KeyError):  # no train output yet
        foreground = np.concatenate([b[alpha >= 0.5].reshape(-1) for *_, b, alpha in pairs])
        return 1.0 / max(float(np.percentile(foreground, 99.5)), 1e-12), "the clean renders' 99.5th percentile"


if __name__ == "__main__":
    main()
