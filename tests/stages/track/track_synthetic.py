"""Test helpers for the track stage: a small rendered capture with perfect calibration and truth.

(Synthetic landmark scenes without images live in ``stages.track.synthetic``.)
"""

from __future__ import annotations

import numpy as np


def write_capture(root, frames: int = 7, cameras: tuple[int, ...] = (0, 1, 2, 5, 6), scale: float = 0.3125,
                  render: bool = True, full_on_every: int = 3):
    """A small capture (virtual studio), perfect calibration and truth, in ``root``.

    Only full-on frames are rendered (tracking reads nothing else). Returns
    ``(capture, calibrate, truth)`` folders.
    """
    import json

    from hardware.studio import RenderSettings, VirtualStudio, make_performance, make_subject, scan_session
    from scene.camera import save_cameras
    from scene.image_io import write_exr
    from scene.rig import default_rig

    rig = default_rig()
    cams = [rig.cameras_at(scale)[k] for k in cameras]
    subject = make_subject("test", seed=1, texture_size=256)
    performance = make_performance(seed=1, takes=("rom",), frames_per_take=frames,
                                   head_center_world=np.asarray(rig.head_center_m))
    capture, calibrate, truth = root / "capture", root / "calibrate", root / "truth"
    for folder in (capture / "scans", calibrate, truth):
        folder.mkdir(parents=True)
    names, scans, faces = scan_session(subject)
    np.savez(capture / "scans" / "scans.npz", names=np.array(names), vertices=scans, faces=faces)
    lights = ["F" if f.index % full_on_every == 0 else 1 + f.index % 32 for f in performance]
    manifest = {"subject": "test", "fps": 24, "width": cams[0].width, "height": cams[0].height,
                "cameras": [c.name for c in cams], "bars": 32, "takes": ["rom"],
                "frames": [{"index": f.index, "take": f.take, "time_s": f.time_s, "light": light, "status": "ok"}
                           for f, light in zip(performance, lights)]}
    (capture / "manifest.json").write_text(json.dumps(manifest))
    save_cameras(calibrate / "cameras.json", cams)
    save_cameras(truth / "cameras.json", cams)
    np.savez(truth / "frames.npz", index=np.array([f.index for f in performance]),
             world_from_head_R=np.array([f.world_from_head.R for f in performance]),
             world_from_head_t=np.array([f.world_from_head.t for f in performance]),
             weights=np.array([f.expression_weights for f in performance]))
    np.savez(truth / "meshes.npz", vertices=np.array([subject.vertices(f.expression_weights) for f in performance],
                                                     dtype=np.float32), faces=subject.rig.triangles)
    if render:
        studio = VirtualStudio(rig, subject, RenderSettings(seed=1, full_on_bar_samples=1, edge_samples=1))
        for f, light in zip(performance, lights):
            if light != "F":
                continue
            for cam in cams:
                folder = capture / "frames" / cam.name
                folder.mkdir(parents=True, exist_ok=True)
                write_exr(folder / f"{f.index:06d}.exr", studio.render(f, cam, "F").rgb)
    return capture, calibrate, truth
