"""How well ``RenderSettings.bar_samples`` integrates a bar's specular glint on the eyes.

Renders a still, neutral head from the front camera under single bars (OLAT) with 1, 4 and
16 stratified samples per bar and pixel, against a 256-sample reference (no sensor noise),
and reports, over the eyes' glint pixels (inside the eyeballs' image, brighter than three
times the eyes' median): the mean relative error, the fraction of glint pixels below half the
reference (a streak broken into dots), and the whole image's RMSE.

Usage: ``python -m benchmarks.bench_bar_glint [SCALE] [BARS] [SAMPLES]``, e.g.
``python -m benchmarks.bench_bar_glint 0.5 2,9,20 1,4,16`` (about 2 minutes on one core).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from hardware.studio import RenderSettings, VirtualStudio, make_subject
from hardware.studio.performance import FrameState
from scene.camera import Rigid
from scene.rig import default_rig

REFERENCE_SAMPLES = 256
EYE_RADIUS_M = 0.012


def main(scale: float = 0.5, bars: tuple[int, ...] = (2, 9, 20), counts: tuple[int, ...] = (1, 4, 16)) -> None:
    rig = default_rig()
    subject = make_subject("alice", seed=0, texture_size=256)
    frame = FrameState(0, "still", 0.0, np.zeros(57, np.float32), Rigid(np.eye(3), np.asarray(rig.head_center_m)))
    cam = rig.cameras_at(scale)[0]

    def render(samples: int, bar: int) -> tuple[np.ndarray, float]:
        studio = VirtualStudio(rig, subject, RenderSettings(edge_samples=2, bar_samples=samples))
        start = time.perf_counter()
        return studio.render(frame, cam, bar, noise=False).rgb.mean(-1), time.perf_counter() - start

    eye_uv, eye_depth = cam.project(VirtualStudio(rig, subject).geometry(frame).eye_centres_world)
    yy, xx = np.mgrid[:cam.height, :cam.width]
    eyes = np.zeros((cam.height, cam.width), bool)
    for (u, v), depth in zip(eye_uv, eye_depth):
        eyes |= (xx - u) ** 2 + (yy - v) ** 2 < (EYE_RADIUS_M * cam.fx / depth) ** 2
    for bar in bars:
        ref, seconds = render(REFERENCE_SAMPLES, bar)
        glint = eyes & (ref > 3 * np.median(ref[eyes]))
        print(f"bar {bar}: reference ({REFERENCE_SAMPLES} samples) {seconds:.1f} s, {glint.sum()} glint pixels")
        for samples in counts:
            img, seconds = render(samples, bar)
            rel = np.abs(img[glint] - ref[glint]) / ref[glint]
            broken = np.mean(img[glint] < 0.5 * ref[glint])
            rmse = np.sqrt(np.mean((img - ref) ** 2))
            print(f"  bar_samples {samples:3d}: {seconds:5.2f} s  glint rel err {rel.mean():.3f}  "
                  f"glint pixels < half ref {broken:.3f}  image rmse {rmse:.5f}")


if __name__ == "__main__":
    args = sys.argv[1:]
    main(float(args[0]) if args else 0.5,
         tuple(int(b) for b in args[1].split(",")) if len(args) > 1 else (2, 9, 20),
         tuple(int(c) for c in args[2].split(",")) if len(args) > 2 else (1, 4, 16))
