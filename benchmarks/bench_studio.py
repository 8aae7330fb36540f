"""The virtual studio's render rate: rays per second and frames per second.

Renders cam00 of the default rig (subject seed 1, first frame of the performance) with one
bar lit (an OLAT image) and with every bar lit (a full-on image), at the tiny preset's
240x320 and at the paper's 768x1024 (1024x768 turned to portrait), with each preset's
sampling settings. A capture frame is 10 images; the F,O,O pattern makes one frame in
three full-on, so ``frames_per_second = 1 / (10 * (t_F + 2 t_O) / 3)`` on one core.
Prints the figures and writes ``bench-results/studio.json``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from hardware.studio import RenderSettings

ROOT = Path(__file__).resolve().parents[1]

#: The presets whose image size and studio sampling are timed.
PRESETS = ("tiny", "paper")


def preset_studio(name: str) -> tuple[float, "RenderSettings"]:
    """A preset's capture image scale and studio ``RenderSettings``, read from ``configs/presets/<name>.yaml``
    over the capture stage's defaults (so the bench times what the preset renders, not a copy of it)."""
    from pipeline.yamlio import read_yaml_mapping
    from stages.capture.stage import CaptureParams

    label = f"configs/presets/{name}.yaml"
    section = read_yaml_mapping(ROOT / label, label).get("capture") or {}
    params = CaptureParams(**{key: section[key] for key in ("image_scale", "render") if key in section})
    return params.image_scale, params.render


def _time_render(studio, frame, cam, lit, repeats: int) -> tuple[float, int]:
    studio.render(frame, cam, lit)  # warm caches (rays of this camera, BVH of this frame)
    start = time.perf_counter()
    rays = 0
    for _ in range(repeats):
        rays += studio.render(frame, cam, lit).rays
    return (time.perf_counter() - start) / repeats, rays // repeats


def main() -> dict:
    from hardware.studio import VirtualStudio, build_geometry, make_performance, make_subject
    from scene.rig import default_rig

    rig = default_rig()
    subject = make_subject("bench", seed=1, texture_size=512)
    frame = make_performance(seed=1, frames_per_take=3)[0]
    start = time.perf_counter()
    for _ in range(3):
        build_geometry(subject, frame)
    bvh_s = (time.perf_counter() - start) / 3
    results: dict[str, float | str] = {"bvh_build_seconds": bvh_s, "cpu_count": os.cpu_count() or 1,
                                       "note": "one process, one core's worth of numpy; timings are noisy on a shared machine"}
    print(f"BVH build + normals per frame: {bvh_s * 1000:.1f} ms")
    for name in PRESETS:
        scale, settings = preset_studio(name)
        cam = rig.cameras_at(scale)[0]
        studio = VirtualStudio(rig, subject, settings)
        repeats = 3 if name == "tiny" else 1
        t_olat, rays_olat = _time_render(studio, frame, cam, 5, repeats)
        t_full, rays_full = _time_render(studio, frame, cam, "F", repeats)
        per_frame_s = 10 * (t_full + 2 * t_olat) / 3
        res = {
            f"{name}_width_px": cam.width, f"{name}_height_px": cam.height,
            f"{name}_olat_image_seconds": t_olat, f"{name}_full_on_image_seconds": t_full,
            f"{name}_olat_rays_per_second": rays_olat / t_olat, f"{name}_full_on_rays_per_second": rays_full / t_full,
            f"{name}_frames_per_second": 1.0 / per_frame_s,
        }
        results.update(res)
        print(f"{name} {cam.width}x{cam.height}: OLAT image {t_olat:.3f} s ({rays_olat / t_olat / 1e6:.2f} Mrays/s), "
              f"full-on image {t_full:.3f} s ({rays_full / t_full / 1e6:.2f} Mrays/s), "
              f"{1.0 / per_frame_s:.3f} capture frames/s (10 cameras) on one core")
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "studio.json").write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
