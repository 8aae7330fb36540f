"""A small capture folder rendered by the virtual studio, for the matte tests and benchmark.

It follows the ``capture`` / ``capture.truth`` contracts (``stages.capture.output``) closely
enough for the matte stages: the manifest, the frames and, in the truth folder, the mattes.
The light pattern is the studio's, ``F, O, O, F, ...``;
optionally some frames show an empty studio (no person: backdrop and sensor noise only).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.capture.output import CaptureOutput, CaptureTruth


def render_mini_capture(capture_dir: Path, truth_dir: Path, identity_seed: int = 1, image_scale: float = 0.125,
                        camera_names: tuple[str, ...] = ("cam00", "cam03"), frame_count: int = 7,
                        olat_bars: tuple[int, ...] = (7, 14, 2, 25), empty_frames: tuple[int, ...] = (),
                        performance_seed: int | None = None) -> dict:
    """Render the capture; returns its manifest."""
    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject
    from scene.image_io import write_exr, write_png16
    from scene.rig import default_rig

    capture, truth = CaptureOutput(capture_dir), CaptureTruth(truth_dir)
    rig = default_rig()
    cameras = [c for c in rig.cameras_at(image_scale) if c.name in camera_names]
    subject = make_subject(f"mini-{identity_seed}", seed=identity_seed, texture_size=256)
    performance = make_performance(seed=performance_seed if performance_seed is not None else identity_seed,
                                   frames_per_take=max(frame_count, 4), takes=("speech",))
    settings = RenderSettings(edge_samples=3, bar_samples=2, full_on_bar_samples=1, seed=identity_seed)
    studio = VirtualStudio(rig, subject, settings)
    frames, olat_cursor = [], 0
    for index in range(frame_count):
        light: str | int = "F"
        if index % 3 != 0:
            light = int(olat_bars[olat_cursor % len(olat_bars)])
            olat_cursor += 1
        frames.append({"index": index, "take": "speech", "time_s": index / rig.fps, "light": light, "status": "ok"})
        for cam in cameras:
            capture.frames_dir(cam.name).mkdir(parents=True, exist_ok=True)
            truth.matte_path(cam.name, index).parent.mkdir(parents=True, exist_ok=True)
            if index in empty_frames:
                rng = np.random.default_rng([identity_seed, index])
                rgb = np.maximum(rng.normal(0.0, settings.read_noise, (cam.height, cam.width, 3)), 0.0)
                alpha = np.zeros((cam.height, cam.width), np.float32)
            else:
                result = studio.render(performance[index], cam, light)
                rgb, alpha = result.rgb, result.alpha
            write_exr(capture.frame_path(cam.name, index), rgb.astype(np.float32), half=False)
            write_png16(truth.matte_path(cam.name, index), alpha)
    manifest = {"subject": f"mini-{identity_seed}", "fps": rig.fps, "width": cameras[0].width,
                "height": cameras[0].height, "cameras": [c.name for c in cameras], "bars": len(rig.light_bars()),
                "takes": ["speech"], "frames": frames}
    capture_dir.mkdir(parents=True, exist_ok=True)
    capture.write_manifest(manifest)
    return manifest
