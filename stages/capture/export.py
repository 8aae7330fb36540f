"""Write a capture stage's output as a capture folder in the import layout (``stages.capture.layout``).

What a studio would deliver from the same shoot: each camera's images in arrival order
(``cameras/<cam>/000000.exr``, ...: the camera's labelled frames in trigger order, so a frame
the camera lost is simply absent), the camera's time stamp of each image (its trigger's time,
on the controller's clock), the controller's log, ``capture.json`` (subject, fps, bars, the
cameras, the takes), the actor's scans and the calibration takes (``calib/``), and the rig it was filmed with (``rig.yaml``, in the form of
``configs/rig.yaml``: a virtual subject can name it with ``rig:``). The ground truth
(``capture.truth``) stays behind: a real capture has none.

Files are hard-linked where the file system allows (a copy otherwise), so an export costs no
disk space beside the workspace; they keep the workspace objects' read-only mode. Delete or
replace a file freely; do not edit one in place.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from pipeline.errors import InputError
from scene.rig import RigConfig
from stages.capture.layout import CaptureFolder, link_or_copy
from stages.capture.output import CaptureOutput


@dataclass(frozen=True)
class ExportSummary:
    """What ``export_capture`` wrote."""

    folder: Path
    cameras: int
    images: int
    log_entries: int
    calibration_files: int


def _takes(frames: list[dict]) -> list[dict]:
    """The takes in trigger order with their frame counts (runs of the frames' ``take``)."""
    takes: list[dict] = []
    for frame in frames:
        if takes and takes[-1]["name"] == frame["take"]:
            takes[-1]["frames"] += 1
        else:
            takes.append({"name": frame["take"], "frames": 1})
    return takes


def check_destination(dest: Path) -> None:
    """``InputError`` unless ``dest`` is new or an empty folder (callers check before a long render)."""
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise InputError(f"{dest}: exists and is not an empty folder; give a new or empty folder to export into")


def _empty_destination(dest: Path) -> CaptureFolder:
    check_destination(dest)
    dest.mkdir(parents=True, exist_ok=True)
    return CaptureFolder(dest.resolve())


def _link_tree(src: Path, dst: Path) -> int:
    """Link every file under ``src`` to the same place under ``dst``; returns how many."""
    count = 0
    for path in sorted(src.rglob("*")):
        if path.is_file():
            target = dst / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            link_or_copy(path, target)
            count += 1
    return count


def _write_rig(folder: CaptureFolder, rig: Mapping[str, Any]) -> None:
    import yaml

    header = ("# The rig this capture was filmed with (the form of configs/rig.yaml). The virtual studio's\n"
              "# design is exact; a real studio's rig file holds its nominal design. Checked against the\n"
              "# folder by `pipeline check-capture`.\n")
    plain = json.loads(json.dumps(dict(rig)))
    ordered = {key: plain[key] for key in RigConfig.model_fields if key in plain}  # as configs/rig.yaml reads
    folder.rig_path.write_text(header + yaml.safe_dump(ordered, sort_keys=False, default_flow_style=None, width=200))


def export_capture(capture_dir: Path, dest: Path, rig: Mapping[str, Any] | None = None) -> ExportSummary:
    """Write the capture output at ``capture_dir`` as an import-layout folder at ``dest`` (new or empty).

    ``rig``: the rig the capture was filmed with (``RigConfig`` JSON form), written as ``rig.yaml``.
    """
    capture = CaptureOutput(capture_dir)
    manifest = capture.manifest(keys=("fps", "cameras", "bars", "frames"))
    frames = capture.frames_of(manifest)
    log = capture.controller_log()
    folder = _empty_destination(Path(dest))
    time_of = {int(f["index"]): float(f["time_s"]) for f in frames}
    images = 0
    for cam in manifest["cameras"]:
        folder.camera_dir(cam).mkdir(parents=True)
        received = [i for i in sorted(time_of) if capture.has_frame(cam, i)]
        for arrival, index in enumerate(received):
            link_or_copy(capture.frame_path(cam, index), folder.image_path(cam, arrival))
        folder.timestamps_path(cam).write_text(json.dumps([time_of[i] for i in received]))
        images += len(received)
    folder.log_path.write_text(json.dumps({"entries": log["entries"]}, indent=1))
    info = {"subject": manifest.get("subject"), "fps": manifest["fps"], "bars": manifest["bars"],
            "cameras": list(manifest["cameras"]), "takes": _takes(frames)}
    folder.info_path.write_text(json.dumps(info, indent=1))
    if rig is not None:
        _write_rig(folder, rig)
    if capture.scans_dir.is_dir():
        _link_tree(capture.scans_dir, folder.scans_dir)
    calibration_files = _link_tree(capture.calib_dir, folder.calib_dir) if capture.calib_dir.is_dir() else 0
    return ExportSummary(folder=folder.root, cameras=len(manifest["cameras"]), images=images,
                         log_entries=len(log["entries"]), calibration_files=calibration_files)
