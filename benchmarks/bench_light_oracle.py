"""How well a held-out light can be predicted from the training lights' images: the light-sampling ceiling.

The novel-light splits score a model on frames lit by 3 held-out interior bars. A model learns
what a light does from the training bars alone, so the rig's bar spacing bounds what
interpolation in light space can reach, however good the model. This bench measures that
bound on perfect data. On the very (frame, camera) pairs the train stage scores its novel-light
and "both" splits on (its splits, ``eval_images`` pairs a split, TRAvatar*'s light directions,
all computed by the train stage's own functions from the subject's workspace), it renders the
frame without sensor noise (``ORACLE_BAR_SAMPLES`` light samples per bar) under the held-out bar
and under every training bar at the capture's size, shrinks them to the training width as the
train stage's loader does (INTER_AREA), and predicts the held-out image from the training bars'
images of the same frame and camera:

- ``barycentric``: TRAvatar*'s rule (``avatar.travatar.LightBasis``: barycentric weights in
  the Delaunay triangle of training-bar directions around the held-out bar), then the train
  stage's per-image exposure scale: TRAvatar* with a perfect image under every training bar;
- ``triangle_fit``: the same 3 bars, their non-negative weights fitted to the target itself;
- ``triangle_tile_fit``: the same 3 bars, weights fitted to the target in each 8 x 8-pixel tile
  of its own: a mix of the neighbouring lights that varies over the image, as a decoder
  conditioned on each primitive's light direction can make;
- ``all_bars_fit``: every training bar, non-negative weights fitted to the target itself: the
  best that any fixed mix of training-light images can do for that image.

The fitted ones see the answer: they are ceilings for methods that blend training-light
images (TRAvatar* is one), not methods, and not bounds for every model (a model that renders
no glint can beat a blend that copies other lights' glints to the wrong places). ``clean render`` is the
held-out image itself, rendered without noise: a perfect model. All are scored as the train
stage scores (its image scale, PSNR of the split's mean squared error) against the images the
capture recorded (``vs_captured``, read by the train stage's loader: the same numbers as
``pipeline show -S <subject> train`` reports for the models) and against the clean render
(``vs_clean``, in the JSON).

Knobs: ``ORACLE_SUBJECT`` (default bob; needs the subject's workspace up to ``stabilize``,
``make subject S=<subject>``), ``ORACLE_IMAGES`` (pairs a split, default the train stage's
``eval_images``), ``ORACLE_BAR_SAMPLES`` (default 16). Cost: one render per training bar and
image, about 0.2 s each at 240 x 320 (the train stage's 12 images a split: about 2.5 minutes on
one core for both splits). Writes ``bench-results/light_oracle_<subject>.json``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace

import numpy as np
from scipy.optimize import nnls

from benchmarks.train_runs import ROOT, tiny_train_params

ORACLES: tuple[str, ...] = ("barycentric", "triangle_fit", "triangle_tile_fit", "all_bars_fit")
TILE_PX = 8
SPLITS_WITH_HELD_OUT_LIGHT: tuple[str, ...] = ("novel_light", "novel_both")


def exposure_fit(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``pred`` scaled by the train stage's least-squares exposure factor onto ``target`` (one image)."""
    import torch

    from avatar.metrics import exposure_scale

    scale = exposure_scale(torch.from_numpy(np.asarray(pred, np.float64))[None],
                           torch.from_numpy(np.asarray(target, np.float64))[None])
    return pred * float(scale[0])


def oracle_predictions(target: np.ndarray, basis_images: np.ndarray, barycentric: np.ndarray
                       ) -> dict[str, np.ndarray]:
    """The three predictions of ``target`` [H, W, 3] from training-light images [L, H, W, 3].

    ``barycentric`` [L] holds TRAvatar*'s weights for the held-out light (three non-zero).
    Returns ``{oracle: image [H, W, 3]}`` for ``ORACLES``, each already exposure-matched.
    """
    flat = basis_images.reshape(len(basis_images), -1).T.astype(np.float64)  # [P, L]
    goal = target.reshape(-1).astype(np.float64)
    triangle = np.flatnonzero(barycentric > 0)
    tri_w, _ = nnls(flat[:, triangle], goal)
    all_w, _ = nnls(flat, goal)
    shape = target.shape
    tiled = np.zeros(shape)
    for y in range(0, shape[0], TILE_PX):
        for x in range(0, shape[1], TILE_PX):
            tile = basis_images[triangle, y:y + TILE_PX, x:x + TILE_PX].reshape(len(triangle), -1).T
            w, _ = nnls(tile.astype(np.float64), target[y:y + TILE_PX, x:x + TILE_PX].reshape(-1).astype(np.float64))
            tiled[y:y + TILE_PX, x:x + TILE_PX] = (tile @ w).reshape(tiled[y:y + TILE_PX, x:x + TILE_PX].shape)
    return {"barycentric": exposure_fit(flat @ barycentric, goal).reshape(shape),
            "triangle_fit": (flat[:, triangle] @ tri_w).reshape(shape),
            "triangle_tile_fit": tiled,
            "all_bars_fit": (flat @ all_w).reshape(shape)}


def psnr_of_mse(mse: float) -> float:
    return float(10.0 * np.log10(1.0 / max(mse, 1e-20)))


def main() -> dict:
    import cv2

    import logging

    from avatar.travatar import LightBasis
    from hardware.studio.performance import FrameState
    from hardware.studio.renderer import RenderSettings, VirtualStudio
    from hardware.studio.subject import make_subject
    from pipeline.errors import PipelineError
    from pipeline.workspace import Workspace, workspace_root
    from scene.camera import Rigid
    from scene.rig import default_rig
    from stages.capture.output import CaptureTruth
    from stages.train.data import load_train_data
    from stages.train.evaluate import eval_pairs
    from stages.train.splits import make_splits
    from stages.report.light_oracle import capture_fingerprint
    from stages.train.params import TrainParams
    from stages.train.setup import bar_directions, exposure_of

    subject = os.environ.get("ORACLE_SUBJECT", "bob")
    bar_samples = int(os.environ.get("ORACLE_BAR_SAMPLES", "16"))
    params = TrainParams(**tiny_train_params())
    images_per_split = int(os.environ.get("ORACLE_IMAGES", "0")) or params.eval_images
    try:
        ws = Workspace(workspace_root(ROOT), subject)
        truth = CaptureTruth(ws.output_path("capture", "truth"))
        studio_json = truth.studio()
        inputs = {k: ws.output_path(k) for k in ("capture", "stabilize", "track", "matte", "lightcal")}
    except (PipelineError, OSError, ValueError) as err:
        print(f"light oracle: no capture for subject '{subject}' ({err}); run `make subject S={subject}` first")
        return {}
    start = time.perf_counter()
    # The train stage's own data, splits, light directions and exposure (from the pipeline's
    # calibrated bars and tracked poses); the renders below use the studio's truth.
    data = load_train_data(inputs, params.image_width_px, logging.getLogger("bench.light_oracle"), params.max_frames)
    bar_dirs = bar_directions(data)
    splits = make_splits(data.take, data.bar, bar_dirs, params.held_out_bars, params.held_out_take,
                         params.held_out_fraction, params.validation)
    train_frames = np.flatnonzero(splits.train)
    scale = exposure_of(data, train_frames)
    training_bars = sorted(int(b) for b in np.unique(data.bar[train_frames]))
    basis = LightBasis(np.stack([bar_dirs[b] for b in training_bars]))

    frames = truth.frames(keys=("index",))
    pulse_of_frame = {int(idx): i for i, idx in enumerate(frames["index"])}
    cameras = {c.name: c for c in truth.cameras()}
    captured = RenderSettings(**studio_json["render_settings"])
    # Silhouette samples as captured: bench_truth_floor's 6 x 6 would cost 2.5x the time here.
    clean = replace(captured, bar_samples=bar_samples, shot_noise_gain=0.0, read_noise=0.0)
    person = make_subject(studio_json["subject"], studio_json["identity_seed"], texture_size=studio_json["texture_size"])
    clean_studio = VirtualStudio(default_rig(), person, clean)

    height, width = data.images.shape[2:4]
    rendered, renders = [], 0
    # The very (frame, camera) pairs the train stage scores its held-out-light splits on.
    for split in SPLITS_WITH_HELD_OUT_LIGHT:
        for k, j in eval_pairs(np.flatnonzero(splits.mask(split)), len(data.camera_names), images_per_split):
            i = pulse_of_frame[int(data.frame_index[k])]
            frame = FrameState(int(frames["index"][i]), str(frames["take"][i]), float(frames["time_s"][i]),
                               frames["weights"][i].astype(np.float64),
                               Rigid(frames["world_from_head_R"][i], frames["world_from_head_t"][i]))
            cam, held = cameras[data.camera_names[j]], int(data.bar[k])

            def shrink(img: np.ndarray) -> np.ndarray:
                return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)

            basis_images = np.stack([shrink(clean_studio.render(frame, cam, b, noise=False).rgb) for b in training_bars])
            renders += 1 + len(training_bars)
            rendered.append(({"frame": int(data.frame_index[k]), "bar": held, "camera": cam.name, "split": split},
                             shrink(clean_studio.render(frame, cam, held, noise=False).rgb),
                             np.asarray(data.images[k, j], np.float64), basis_images,
                             basis.weights(data.light_pos_head[k][None])[0]))  # as TRAvatar* weighs this light
    if not rendered:
        print(f"light oracle: subject '{subject}' has no frames lit by a held-out bar")
        return {}
    images = []
    for row, target, recorded, basis_images, weights in rendered:
        row["clean_render_vs_captured_psnr_db"] = psnr_of_mse(float(((scale * (target - recorded)) ** 2).mean()))
        for vs, goal in (("vs_clean", target), ("vs_captured", recorded)):
            for oracle, pred in oracle_predictions(goal, basis_images, weights).items():
                row[f"{oracle}_{vs}_psnr_db"] = psnr_of_mse(float(((scale * (pred - goal)) ** 2).mean()))
        images.append(row)
        print(f"frame {row['frame']:3d} ({row['split']}) bar {row['bar']:2d} {row['camera']}: " + ", ".join(
            f"{o} {row[f'{o}_vs_captured_psnr_db']:.2f}" for o in ORACLES) + " dB", flush=True)
    keys = ["clean_render_vs_captured"] + [f"{o}_{vs}" for vs in ("vs_captured", "vs_clean") for o in ORACLES]

    def pooled(rows: list[dict]) -> dict[str, float]:
        """PSNR of the mean squared error over ``rows``, per key (as the train stage pools a split)."""
        return {key: psnr_of_mse(float(np.mean([10 ** (-r[f"{key}_psnr_db"] / 10) for r in rows]))) for key in keys}

    per_split = {split: pooled([r for r in images if r["split"] == split]) for split in SPLITS_WITH_HELD_OUT_LIGHT
                 if any(r["split"] == split for r in images)}
    per_bar = {int(b): pooled([r for r in images if r["bar"] == b]) for b in splits.held_out_bars
               if any(r["bar"] == b for r in images)}
    wall = time.perf_counter() - start
    print(f"light oracle, {subject}: held-out bars {list(splits.held_out_bars)}, {len(training_bars)} training bars, "
          f"the train stage's {images_per_split} images per split at {width} px wide, {renders} renders in {wall:.0f} s")
    print("  PSNR dB against the captured images (the train stage's targets and exposure):")
    print(f"  {'':13s} {'clean render':>12s} " + " ".join(f"{o:>12s}" for o in ORACLES))
    for name, row in list(per_split.items()) + [(f"bar {b}", row) for b, row in per_bar.items()]:
        print(f"  {name:13s} {row['clean_render_vs_captured']:12.2f} "
              + " ".join(f"{row[f'{o}_vs_captured']:12.2f}" for o in ORACLES))
    results = {"subject": subject, "capture_fingerprint": capture_fingerprint(inputs["capture"]),
               "width_px": width, "image_scale": scale, "images_per_split": images_per_split,
               "held_out_bars": list(splits.held_out_bars), "training_bars": training_bars,
               "clean_settings": {"bar_samples": bar_samples}, "psnr_db_per_split": per_split,
               "psnr_db_per_held_out_bar": per_bar, "images": images, "renders": renders, "wall_s": wall}
    out = ROOT / "bench-results"
    out.mkdir(exist_ok=True)
    (out / f"light_oracle_{subject}.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
