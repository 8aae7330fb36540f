"""How far a novel light can be predicted from the training lights' images: the light-sampling ceiling.

The novel-light split scores a model on frames lit by 3 held-out interior bars. Any model
learns what a novel light does from the training bars alone, so the rig's bar spacing
bounds what interpolation in light space can reach, however good the model. This bench
measures that bound on perfect data: for frames of the novel-light split (the train stage's
own split rule), it renders the frame cleanly (no sensor noise, ``ORACLE_BAR_SAMPLES`` light
samples per bar) under the held-out bar and under every training bar, at the capture's size,
shrinks all to the train stage's width (INTER_AREA, as its loader does) and predicts the held-out image from the
training bars' images of the same frame and camera three ways:

- ``barycentric``: TRAvatar*'s rule (``avatar.travatar.LightBasis``: the Delaunay triangle of
  the training bars' head-space directions around the held-out bar, barycentric weights),
  then the train stage's per-image exposure scale;
- ``triangle_fit``: the same 3 bars, their non-negative weights fitted to the target itself;
- ``all_bars_fit``: every training bar, non-negative weights fitted to the target itself: the
  best any fixed mix of training-light images can do for that image.

The fitted oracles see the answer, so they are ceilings, not methods. Each is scored against
the clean render (``vs_clean``) and against the image the capture recorded (``vs_captured``:
the train stage's own target, read by its loader, with its noise; see ``bench_truth_floor``),
with the train stage's exposure scale, splits and TRAvatar*'s light directions, computed by
the train stage's own functions from the subject's workspace: ``vs_captured`` is on the scale of
the novel-light PSNR that ``pipeline show -S <subject> train`` reports.

Knobs: ``ORACLE_SUBJECT`` (default bob; needs the subject's capture, ``make subject S=<subject>``
or ``pipeline run -S <subject> --until capture``), ``ORACLE_FRAMES`` (frames per held-out bar,
default 2, from the novel-light split then from "both"), ``ORACLE_CAMERAS`` (every k-th camera, default 2),
``ORACLE_BAR_SAMPLES`` (default 16). About 2 minutes on one core with the defaults (30 renders per
image; cost grows with frames x cameras x bars). Writes ``bench-results/light_oracle_<subject>.json``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace

import numpy as np
from scipy.optimize import nnls

from benchmarks.train_runs import ROOT, tiny_train_params

ORACLES: tuple[str, ...] = ("barycentric", "triangle_fit", "all_bars_fit")


def exposure_fit(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``pred`` scaled by the least-squares factor onto ``target`` (``avatar.metrics.exposure_scale``)."""
    den = float((pred * pred).sum())
    return pred * (float((pred * target).sum()) / den if den > 0 else 0.0)


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
    return {"barycentric": exposure_fit(flat @ barycentric, goal).reshape(shape),
            "triangle_fit": (flat[:, triangle] @ tri_w).reshape(shape),
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
    from scene.camera import Rigid, load_cameras
    from scene.rig import default_rig
    from stages.train.data import load_train_data
    from stages.train.splits import make_splits
    from stages.train.stage import TrainParams, bar_directions, exposure_of

    subject = os.environ.get("ORACLE_SUBJECT", "bob")
    per_bar = int(os.environ.get("ORACLE_FRAMES", "2"))
    every_camera = int(os.environ.get("ORACLE_CAMERAS", "2"))
    bar_samples = int(os.environ.get("ORACLE_BAR_SAMPLES", "16"))
    params = TrainParams(**tiny_train_params())
    try:
        ws = Workspace(workspace_root(ROOT), subject)
        truth = ws.output_path("capture", "truth")
        studio_json = json.loads((truth / "studio.json").read_text())
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
                         params.held_out_fraction)
    train_frames = np.flatnonzero(splits.train)
    scale = exposure_of(data, train_frames)
    training_bars = sorted(int(b) for b in np.unique(data.bar[train_frames]))
    basis = LightBasis(np.stack([bar_dirs[b] for b in training_bars]))

    frames = np.load(truth / "frames.npz")
    pulse_of_frame = {int(idx): i for i, idx in enumerate(frames["index"])}
    cameras = {c.name: c for c in load_cameras(truth / "cameras.json")}
    cameras = [(j, cameras[name]) for j, name in enumerate(data.camera_names) if j % every_camera == 0]
    captured = RenderSettings(**studio_json["render_settings"])
    # Silhouette samples as captured: bench_truth_floor's 6 x 6 would cost 2.5x the time here.
    clean = replace(captured, bar_samples=bar_samples, shot_noise_gain=0.0, read_noise=0.0)
    person = make_subject(studio_json["subject"], studio_json["identity_seed"], texture_size=studio_json["texture_size"])
    clean_studio = VirtualStudio(default_rig(), person, clean)

    height, width = data.images.shape[2:4]
    rendered, renders = [], 0
    # Frames of both held-out-light splits (novel light, and both: the held-out take's end).
    novel = np.flatnonzero(splits.novel_light | splits.novel_both)
    for held in splits.held_out_bars:
        for k in novel[data.bar[novel] == held][:per_bar]:
            i = pulse_of_frame[int(data.frame_index[k])]
            frame = FrameState(int(frames["index"][i]), str(frames["take"][i]), float(frames["time_s"][i]),
                               frames["weights"][i].astype(np.float64),
                               Rigid(frames["world_from_head_R"][i], frames["world_from_head_t"][i]))
            weights = basis.weights(data.light_pos_head[k][None])[0]  # as TRAvatar* weighs this frame's light
            for j, cam in cameras:

                def shrink(img: np.ndarray) -> np.ndarray:
                    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)

                basis_images = np.stack([shrink(clean_studio.render(frame, cam, b, noise=False).rgb)
                                         for b in training_bars])
                renders += 1 + len(training_bars)
                rendered.append(({"frame": int(data.frame_index[k]), "bar": int(held), "camera": cam.name,
                                  "split": "novel_light" if splits.novel_light[k] else "novel_both"},
                                 shrink(clean_studio.render(frame, cam, int(held), noise=False).rgb),
                                 np.asarray(data.images[k, j], np.float64), basis_images, weights))
    if not rendered:
        print(f"light oracle: subject '{subject}' has no frames lit by a held-out bar")
        return {}
    sq = {f"{o}_{vs}": [] for o in ORACLES for vs in ("vs_clean", "vs_captured")}
    sq["clean_render_vs_captured"] = []
    images = []
    for row, target, recorded, basis_images, weights in rendered:
        row["clean_vs_captured_psnr_db"] = psnr_of_mse(float(((scale * (target - recorded)) ** 2).mean()))
        sq["clean_render_vs_captured"].append(10 ** (-row["clean_vs_captured_psnr_db"] / 10))
        for vs, goal in (("vs_clean", target), ("vs_captured", recorded)):
            for oracle, pred in oracle_predictions(goal, basis_images, weights).items():
                err = float(((scale * (pred - goal)) ** 2).mean())
                sq[f"{oracle}_{vs}"].append(err)
                row[f"{oracle}_{vs}_psnr_db"] = psnr_of_mse(err)
        images.append(row)
        print(f"frame {row['frame']:3d} ({row['split']}) bar {row['bar']:2d} {row['camera']}: " + ", ".join(
            f"{o} {row[f'{o}_vs_clean_psnr_db']:.2f}" for o in ORACLES) + " dB (vs clean)", flush=True)
    summary = {key: psnr_of_mse(float(np.mean(v))) for key, v in sq.items()}
    per_held = {}
    for held in splits.held_out_bars:
        rows = [r for r in images if r["bar"] == held]
        per_held[int(held)] = {o: psnr_of_mse(float(np.mean([10 ** (-r[f"{o}_vs_clean_psnr_db"] / 10) for r in rows])))
                               for o in ORACLES}
    wall = time.perf_counter() - start
    print(f"light oracle, {subject}: held-out bars {list(splits.held_out_bars)}, {len(training_bars)} training bars, "
          f"{len(images)} images at {width} px wide, {renders} renders in {wall:.0f} s")
    for vs in ("vs_clean", "vs_captured"):
        print(f"  {vs:11s} " + "  ".join(f"{o} {summary[f'{o}_{vs}']:.2f} dB" for o in ORACLES))
    print(f"  the clean render itself vs captured: {summary['clean_render_vs_captured']:.2f} dB (the targets' noise)")
    for held, row in per_held.items():
        print(f"  bar {held:2d} (vs clean) " + "  ".join(f"{o} {row[o]:.2f}" for o in ORACLES))
    results = {"subject": subject, "width_px": width, "image_scale": scale, "held_out_bars": list(splits.held_out_bars),
               "training_bars": training_bars, "clean_settings": {"bar_samples": bar_samples},
               "psnr_db": summary, "psnr_db_per_held_out_bar_vs_clean": per_held, "images": images,
               "renders": renders, "wall_s": wall}
    out = ROOT / "bench-results"
    out.mkdir(exist_ok=True)
    (out / f"light_oracle_{subject}.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
