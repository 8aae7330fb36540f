"""Import a real capture folder (layout: ``stages/capture/README.md``) without copying images twice.

The folder is checked first by ``stages.capture.check`` (the checks ``pipeline check-capture``
runs): any problem that blocks the import is raised at once, all of them in one error, each
naming its file and what to do. Among them, every path must stay inside the source folder:
symbolic links that lead outside it are refused.

Images are hard-linked into the output (one copy on disk; a copy is made only when the
workspace is on another file system).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import InputError
from pipeline.stage import StageContext
from scene.colour import luminance
from stages.capture.check import (FolderScan, bar_count, image_size_problem, read_capture_image, rig_aspect_problem,
                                  scan_folder)
from stages.capture.layout import link_or_copy
from stages.capture.output import CaptureOutput
from stages.capture.placement import label_and_place

def _refuse(scan: FolderScan) -> None:
    """Raise one ``InputError`` listing every problem that blocks the import (none: return)."""
    blocking = scan.blocking
    if blocking:
        lines = "\n  ".join(p.line() for p in blocking)
        raise InputError(f"capture folder {scan.folder.root} cannot be imported ({len(blocking)} problem(s); "
                         f"`pipeline check-capture {scan.folder.root}` lists them all):\n  {lines}")


def _brightness(ctx: StageContext, scan: FolderScan) -> tuple[list[list[float]], tuple[int, int]]:
    """Per camera, the mean luminance of each image in arrival order; and the images' (height, width)."""
    brightness: list[list[float]] = []
    first = None
    with ctx.progress(len(scan.images), "cameras") as progress:
        for paths in scan.images.values():
            values = []
            for path in paths:
                try:
                    img = read_capture_image(path)
                except ValueError as err:
                    scan.report(path, str(err))
                    _refuse(scan)
                if first is None:
                    first = (path, img.shape)
                    if rig_aspect_problem(scan, path, img.shape):
                        _refuse(scan)
                elif image_size_problem(scan, path, img.shape, first):
                    _refuse(scan)
                values.append(float(luminance(img[..., :3]).mean()) if img.shape[2] >= 3 else float(img.mean()))
            brightness.append(values)
            progress.advance(1)
    return brightness, first[1][:2]


def import_capture(ctx: StageContext, source: Path) -> dict:
    """Label and link a real capture into ``ctx.out``; returns ``{"manifest", "metrics"}``."""
    scan = scan_folder(source)
    _refuse(scan)
    info, entries = scan.info, scan.entries
    cam_names = list(scan.images)
    brightness, (height, width) = _brightness(ctx, scan)
    fps = float(info["fps"])
    # Time stamps are used only when every camera has them.
    frame_times = [scan.timestamps[c] for c in cam_names] if set(scan.timestamps) == set(cam_names) else None

    n_triggers = max((int(round(e["time_us"] * 1e-6 * fps)) for e in entries), default=-1) + 1
    takes_cfg = info.get("takes") or [{"name": "take", "frames": n_triggers}]
    take_of = [t["name"] for t in takes_cfg for _ in range(int(t["frames"]))]
    takes = tuple(t["name"] for t in takes_cfg)
    out = CaptureOutput(ctx.out)
    out.write_controller_log({"fps": fps, "entries": entries})
    manifest, metrics = label_and_place(
        out, ctx.log, ctx.subject, fps, cam_names, bar_count(scan), takes, take_of, entries, brightness, n_triggers,
        received=lambda cam, r: scan.images[cam][r], place=link_or_copy, frame_times=frame_times)
    manifest.update(subject=str(info.get("subject", ctx.subject)), width=width, height=height)
    out.write_manifest(manifest)
    for src_dir, dst_dir in ((scan.folder.scans_dir, out.scans_dir), (scan.folder.calib_dir, out.calib_dir)):
        for path in scan.extra_files:
            if src_dir in path.parents:
                dst = dst_dir / path.relative_to(src_dir)
                dst.parent.mkdir(parents=True, exist_ok=True)
                link_or_copy(path.resolve(), dst)
    metrics.update(imported_images=sum(len(v) for v in scan.images.values()))
    return {"manifest": manifest, "metrics": metrics}
