"""Import a real capture folder (layout: ``stages/capture/README.md``) without copying images twice.

Images are hard-linked into the output (one copy on disk; a copy is made only when the
workspace is on another file system). Every path is checked to stay inside the source
folder: symbolic links or names that lead outside it are refused.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path


from pipeline.errors import InputError
from pipeline.stage import StageContext
from stages.capture.placement import label_and_place
from scene.colour import luminance
from scene.image_io import read_exr
from stages.capture.output import CaptureOutput


def _inside(root: Path, path: Path) -> Path:
    """``path`` resolved; ``InputError`` if it leaves ``root`` (symlink or ``..``)."""
    resolved = path.resolve()
    if resolved != root and root not in resolved.parents:
        raise InputError(f"{path}: leads outside the capture folder {root} (symbolic link or '..'); "
                         "copy the file into the folder instead")
    return resolved


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` to ``dst``; copy once when linking is impossible (another file system)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _read_json(root: Path, name: str) -> object:
    path = _inside(root, root / name)
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: missing or not valid JSON ({err}); see stages/capture/README.md") from err


def import_capture(ctx: StageContext, source: Path) -> dict:
    """Label and link a real capture into ``ctx.out``; returns ``{"manifest", "metrics"}``."""
    root = Path(source).resolve()
    info = _read_json(root, "capture.json")
    log_raw = _read_json(root, "controller_log.json")
    if not isinstance(info, dict) or "fps" not in info:
        raise InputError(f"{root / 'capture.json'}: needs at least 'fps' (see stages/capture/README.md)")
    entries = log_raw.get("entries") if isinstance(log_raw, dict) else log_raw
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "light" in e and "time_us" in e
                                                for e in entries):
        raise InputError(f"{root / 'controller_log.json'}: expected a list of entries with 'light' and "
                         "'time_us' (see stages/capture/README.md)")
    fps = float(info["fps"])
    cam_root = _inside(root, root / "cameras")
    if not cam_root.is_dir():
        raise InputError(f"{root}: no 'cameras' folder; put each camera's images in cameras/<cam>/")
    cam_names = sorted(p.name for p in cam_root.iterdir() if p.is_dir())
    if not cam_names:
        raise InputError(f"{cam_root}: no camera folders")
    files: dict[str, list[Path]] = {}
    frame_times: list[list[float]] | None = []
    brightness: list[list[float]] = []
    width = height = None
    with ctx.progress(len(cam_names), "cameras") as progress:
        for cam in cam_names:
            paths = sorted(_inside(root, p) for p in (cam_root / cam).glob("*.exr"))
            if not paths:
                raise InputError(f"{cam_root / cam}: no .exr images")
            files[cam] = paths
            values = []
            for path in paths:
                try:
                    img = read_exr(path)
                except ValueError as err:
                    raise InputError(str(err)) from err
                if width is None:
                    height, width = img.shape[:2]
                elif img.shape[:2] != (height, width):
                    raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, the capture's first "
                                     f"image is {width}x{height}; all images must have one size")
                values.append(float(luminance(img[..., :3]).mean()) if img.shape[2] >= 3 else float(img.mean()))
            brightness.append(values)
            stamps_path = cam_root / cam / "timestamps.json"
            if frame_times is not None and stamps_path.is_file():
                stamps = json.loads(_inside(root, stamps_path).read_text())
                if not isinstance(stamps, list) or len(stamps) != len(paths):
                    raise InputError(f"{stamps_path}: expected a list of {len(paths)} times in seconds, one per image")
                frame_times.append([float(t) for t in stamps])
            else:
                frame_times = None  # time stamps are used only when every camera has them
            progress.advance(1)

    n_triggers = max((int(round(e["time_us"] * 1e-6 * fps)) for e in entries), default=-1) + 1
    takes_cfg = info.get("takes") or [{"name": "take", "frames": n_triggers}]
    take_of = [t["name"] for t in takes_cfg for _ in range(int(t["frames"]))]
    takes = tuple(t["name"] for t in takes_cfg)
    out = CaptureOutput(ctx.out)
    out.write_controller_log({"fps": fps, "entries": entries})
    manifest, metrics = label_and_place(
        out, ctx.log, ctx.subject, fps, cam_names, int(info.get("bars", 32)), takes, take_of, entries, brightness, n_triggers,
        received=lambda cam, r: files[cam][r], place=link_or_copy, frame_times=frame_times)
    manifest.update(subject=str(info.get("subject", ctx.subject)), width=width, height=height)
    out.write_manifest(manifest)
    for optional in (out.scans_dir, out.calib_dir):
        src = root / optional.name
        if src.is_dir():
            _inside(root, src)
            for path in sorted(src.rglob("*")):
                if path.is_file():
                    dst = optional / path.relative_to(src)
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    link_or_copy(_inside(root, path), dst)
    metrics.update(imported_images=sum(len(v) for v in files.values()))
    return {"manifest": manifest, "metrics": metrics}
