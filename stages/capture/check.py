"""Validate a capture folder against the import layout (``stages.capture.layout``) before anything runs.

``scan_folder(root)`` reads everything but the pixels: ``capture.json``, the studio's rig file
(``rig.yaml``, optional), the controller's log,
the camera folders, their time stamps, and where every file really lives (a symbolic link may
not lead out of the folder). ``check_images(scan)`` opens every image: readable, float
(HALF or FLOAT channels) and one size. ``check_capture(root)`` is both: a list of ``Problem``,
each naming the file (relative to the folder), what is wrong and what to do; empty when the
folder is complete.

The importer (``stages.capture.importer``) runs the same scan and the same image reader, and
refuses the folder on every problem with ``blocks_import``. The others it takes, setting the
affected frames aside as dropped, as it does with a real rig's dropped frames: a camera short
of images, or triggers the controller's log has no entry for. ``pipeline check-capture``
reports both kinds (``--allow-gaps`` accepts the second).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stages.capture.layout import CaptureFolder

_LAYOUT_DOC = "see stages/capture/README.md"
_MAX_LISTED = 8  # indices listed in one line before "and N more"


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a capture folder.

    Attributes:
        where: the file or folder, relative to the capture folder (``cameras/cam03``).
        what: what is wrong and what to do about it.
        blocks_import: the importer refuses the folder; False: it imports, with frames dropped.
    """

    where: str
    what: str
    blocks_import: bool = True

    def line(self) -> str:
        """The line ``pipeline check-capture`` prints."""
        suffix = "" if self.blocks_import else " (it would import with these frames dropped)"
        return f"{self.where}: {self.what}{suffix}"


@dataclass
class FolderScan:
    """What ``scan_folder`` read, for the importer; ``problems`` lists what is wrong with it.

    Attributes:
        folder: the capture folder (its root resolved).
        info: ``capture.json`` when it is valid, else None.
        rig: what ``rig.yaml`` says when it is present and valid: ``cameras`` (names in camera-id
            order), ``bars`` (how many, or None), ``fps`` and ``size`` ((width, height) or None).
        entries: the controller log's entries when valid, else None.
        images: per camera folder (sorted names), its images in arrival order.
        timestamps: per camera with a valid ``timestamps.json``, one time (s) per image.
        extra_files: files under ``scans/`` and ``calib/``, each inside the folder.
        problems: everything wrong, in the order found.
    """

    folder: CaptureFolder
    info: dict[str, Any] | None = None
    rig: dict[str, Any] | None = None
    entries: list[dict[str, Any]] | None = None
    images: dict[str, list[Path]] = field(default_factory=dict)
    timestamps: dict[str, list[float]] = field(default_factory=dict)
    extra_files: list[Path] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)

    def report(self, path: Path, what: str, blocks_import: bool = True) -> None:
        self.problems.append(Problem(self.folder.relative(path), what, blocks_import))

    def escapes(self, path: Path) -> bool:
        """Whether ``path`` really lives outside the folder (a symbolic link out); reports it if so."""
        resolved = path.resolve()
        root = self.folder.root
        if resolved == root or root in resolved.parents:
            return False
        self.report(path, f"leads outside the capture folder (symbolic link to {resolved}); "
                          "copy the file into the folder instead of linking to it")
        return True

    @property
    def blocking(self) -> list[Problem]:
        return [p for p in self.problems if p.blocks_import]


def _ranges(indices: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``, at most ``_MAX_LISTED`` runs."""
    runs: list[list[int]] = []
    for i in sorted(indices):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:_MAX_LISTED])
    return text + (f" and {len(runs) - _MAX_LISTED} more" if len(runs) > _MAX_LISTED else "")


def _read_json(scan: FolderScan, path: Path, what_it_holds: str) -> Any | None:
    if not path.is_file():
        scan.report(path, f"missing; it holds {what_it_holds} ({_LAYOUT_DOC})")
        return None
    if scan.escapes(path):
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        scan.report(path, f"not valid JSON ({err}); fix it or write it again ({_LAYOUT_DOC})")
        return None


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_info(scan: FolderScan) -> None:
    path = scan.folder.info_path
    info = _read_json(scan, path, 'the capture\'s frame rate, e.g. {"fps": 24, "bars": 32}')
    if info is None:
        return
    if not isinstance(info, dict):
        scan.report(path, 'must be a JSON object, e.g. {"fps": 24, "bars": 32}')
        return
    bad = len(scan.problems)
    fps = info.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0:
        scan.report(path, f"'fps' must be the cameras' frame rate in Hz (a positive number), got {fps!r}")
    bars = info.get("bars", 32)
    if not _is_count(bars) or bars == 0:
        scan.report(path, f"'bars' must be the number of LED bars (a positive integer), got {bars!r}")
    cameras = info.get("cameras")
    if cameras is not None and (not isinstance(cameras, list) or not cameras
                                or not all(isinstance(c, str) and c for c in cameras)
                                or len(set(cameras)) != len(cameras)):
        scan.report(path, f"'cameras' must list the camera folders' names once each, got {cameras!r}")
    takes = info.get("takes")
    if takes is not None and (not isinstance(takes, list) or not takes or not all(
            isinstance(t, dict) and isinstance(t.get("name"), str) and _is_count(t.get("frames")) for t in takes)):
        scan.report(path, "'takes' must list the takes in trigger order, e.g. "
                          f'[{{"name": "rom", "frames": 48}}], got {takes!r}')
    if len(scan.problems) == bad:
        scan.info = info


def _check_rig(scan: FolderScan) -> None:
    """``rig.yaml``: the form of configs/rig.yaml (cameras as names or full entries); checked against capture.json."""
    import yaml

    path = scan.folder.rig_path
    if not path.is_file() or scan.escapes(path):
        return
    try:
        rig = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        scan.report(path, f"not valid YAML ({err}); fix it or write it again")
        return
    if not isinstance(rig, dict):
        scan.report(path, "must be a mapping with 'cameras' (names, in camera-id order), e.g. 'cameras: [cam00, cam01]'")
        return
    bad = len(scan.problems)
    cameras = rig.get("cameras")
    names = [c.get("name") if isinstance(c, dict) else c for c in cameras] if isinstance(cameras, list) else None
    if not names or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
        scan.report(path, "'cameras' must list the cameras once each, by name or as entries with a 'name' "
                          f"(as in configs/rig.yaml), got {cameras!r}")
    bars = rig.get("bars")
    if bars is not None and (not isinstance(bars, list) or not bars or any(
            not isinstance(b, dict) or b.get("id") != i for i, b in enumerate(bars))):
        scan.report(path, "'bars' must list the LED bars with ids 0..N-1 in order, e.g. "
                          "[{id: 0, center_m: [x, y, z]}, ...] (nominal positions, metres)")
    fps = rig.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0):
        scan.report(path, f"'fps' must be a positive number, got {fps!r}")
    width, height = rig.get("width_px"), rig.get("height_px")
    if (width is None) != (height is None) or (width is not None and not (_is_count(width) and _is_count(height)
                                                                          and width > 0 and height > 0)):
        scan.report(path, f"'width_px' and 'height_px' must both be positive integers, got {width!r}, {height!r}")
    if len(scan.problems) > bad:
        return
    scan.rig = {"cameras": names, "bars": len(bars) if bars else None, "fps": fps,
                "size": (width, height) if width is not None else None}
    info = scan.info
    if info is None:
        return
    for key, rig_value in (("fps", fps), ("bars", scan.rig["bars"])):
        if rig_value is not None and key in info and float(info[key]) != float(rig_value):
            scan.report(path, f"'{key}' is {rig_value:g}, capture.json says {info[key]:g}: make them agree")
    if info.get("cameras") and info["cameras"] != names:
        scan.report(path, f"'cameras' ({', '.join(names)}) differ from capture.json's ({', '.join(info['cameras'])}): "
                          "make them agree")


def _entries_of(raw: Any) -> Any:
    return raw.get("entries") if isinstance(raw, dict) else raw


def bar_count(scan: FolderScan) -> int:
    """The capture's LED bars: capture.json's 'bars', else rig.yaml's, else the default rig's 32."""
    rig_bars = scan.rig["bars"] if scan.rig else None
    return int((scan.info or {}).get("bars") or rig_bars or 32)


def _check_log(scan: FolderScan) -> None:
    path = scan.folder.log_path
    raw = _read_json(scan, path, "the LED controller's log (pipeline hw log)")
    if raw is None:
        return
    entries = _entries_of(raw)
    if not isinstance(entries, list) or not entries:
        scan.report(path, 'expected {"entries": [{"light": "F", "time_us": 0}, ...]} (or a bare list) '
                          f"with one entry per trigger pulse ({_LAYOUT_DOC})")
        return
    bars = bar_count(scan) if scan.info else None
    bad: list[str] = []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict) or "light" not in entry or "time_us" not in entry:
            bad.append(f"entry {k} needs 'light' and 'time_us'")
            continue
        light, time_us = entry["light"], entry["time_us"]
        if light != "F" and not (_is_count(light) and (bars is None or light < bars)):
            bad.append(f"entry {k}: 'light' must be \"F\" or a bar id 0..{(bars or 1) - 1}, got {light!r}")
        if isinstance(time_us, bool) or not isinstance(time_us, (int, float)) or time_us < 0:
            bad.append(f"entry {k}: 'time_us' must be the trigger's time in microseconds, got {time_us!r}")
    if bad:
        more = f" and {len(bad) - _MAX_LISTED} more" if len(bad) > _MAX_LISTED else ""
        scan.report(path, "; ".join(bad[:_MAX_LISTED]) + more)
        return
    times = [float(e["time_us"]) for e in entries]
    back = [k for k in range(1, len(times)) if times[k] < times[k - 1]]
    if back:
        k = back[0]
        scan.report(path, f"entries are not in time order: entry {k} (time_us {times[k]:g}) comes after entry "
                          f"{k - 1} (time_us {times[k - 1]:g}); sort the entries by time_us")
        return
    scan.entries = entries
    if scan.info is None:
        return  # the frame of each entry needs the frame rate
    fps = float(scan.info["fps"])
    frame_of = [int(round(t * 1e-6 * fps)) for t in times]
    seen: dict[int, int] = {}
    for k, index in enumerate(frame_of):
        if index in seen:
            scan.report(path, f"entries {seen[index]} and {k} fall on the same frame {index} at {fps:g} fps; "
                              "is 'fps' in capture.json the trigger rate?")
            scan.entries = None
            return
        seen[index] = k
    gaps = sorted(set(range(frame_of[-1] + 1)) - set(frame_of))
    if gaps:
        scan.report(path, f"no entry for frame(s) {_ranges(gaps)}: the controller did not act on those triggers, "
                          "so their frames import as dropped ('no light'); if it did fire them, the log is "
                          "incomplete: read it again from the controller (pipeline hw log)", blocks_import=False)


def _check_timestamps(scan: FolderScan, cam: str, n_images: int) -> None:
    path = scan.folder.timestamps_path(cam)
    if not path.is_file() or scan.escapes(path):
        return
    stamps = _read_json(scan, path, "the camera's time stamp of each image")
    if stamps is None:
        return
    if not isinstance(stamps, list) or not all(isinstance(t, (int, float)) and not isinstance(t, bool)
                                               for t in stamps):
        scan.report(path, "expected a list of times in seconds, one per image in arrival order")
        return
    if len(stamps) != n_images:
        scan.report(path, f"{len(stamps)} time stamps for {n_images} images: give one per image in arrival "
                          "order (remove the stamp of an image that was deleted)")
        return
    back = [k for k in range(1, len(stamps)) if not stamps[k] > stamps[k - 1]]
    if back:
        k = back[0]
        scan.report(path, f"time stamps out of order: image {k} ({stamps[k]:g} s) is not after image {k - 1} "
                          f"({stamps[k - 1]:g} s); the images sorted by file name must be in arrival order "
                          "(rename them, or fix the stamps)")
        return
    scan.timestamps[cam] = [float(t) for t in stamps]


def _check_cameras(scan: FolderScan) -> None:
    folder = scan.folder
    if not folder.cameras_dir.is_dir():
        scan.report(folder.cameras_dir, "missing; put each camera's images in cameras/<camera name>/")
        return
    if scan.escapes(folder.cameras_dir):
        return
    present = folder.camera_names()
    listed = scan.info.get("cameras") if scan.info else None
    source = "capture.json"
    if not listed and scan.rig:
        listed, source = scan.rig["cameras"], "rig.yaml"
    if listed:
        for cam in listed:
            if cam not in present:
                scan.report(folder.camera_dir(cam), f"missing: {source} lists this camera; copy its images "
                                                    "there, or drop it from 'cameras'")
        for cam in present:
            if cam not in listed:
                scan.report(folder.camera_dir(cam), f"not a camera of {source}'s 'cameras' "
                                                    f"({', '.join(listed)}): add it there, or move the folder out")
    if not present:
        scan.report(folder.cameras_dir, "no camera folders; put each camera's images in cameras/<camera name>/")
    for cam in present:
        cam_dir = folder.camera_dir(cam)
        if scan.escapes(cam_dir):
            continue
        images = folder.images(cam)
        if not images:
            scan.report(cam_dir, "no .exr images; put the camera's images here, linear RGB EXR, in arrival order")
            continue
        for path in images:
            scan.escapes(path)
        scan.images[cam] = images
        _check_timestamps(scan, cam, len(images))
    _check_counts(scan)


def _check_counts(scan: FolderScan) -> None:
    """A camera with fewer images than another lost frames: name the missing files when names tell."""
    if len(scan.images) < 2:
        return
    most = max(len(v) for v in scan.images.values())
    names = {cam: {p.name for p in paths} for cam, paths in scan.images.items()}
    every_name = set().union(*names.values())
    for cam, paths in scan.images.items():
        short = most - len(paths)
        if short <= 0:
            continue
        others = [c for c, v in scan.images.items() if len(v) == most]
        missing = sorted(every_name - names[cam])
        if len(missing) == short:
            listed = ", ".join(missing[:_MAX_LISTED]) + (f" and {short - _MAX_LISTED} more"
                                                          if short > _MAX_LISTED else "")
            indices = [int(Path(n).stem) for n in missing if Path(n).stem.isdigit()]
            index_note = f" (index {_ranges(indices)})" if len(indices) == len(missing) else ""
            what = (f"{len(paths)} images, {others[0]} has {most}: missing {listed}{index_note}, which "
                    f"{others[0]} has; restore it from the camera, or import without it")
        else:
            what = (f"{len(paths)} images, {others[0]} has {most}: this camera lost {short} frame(s); "
                    "restore them from the camera, or import without them")
        scan.report(scan.folder.camera_dir(cam), what, blocks_import=False)


def _check_extras(scan: FolderScan) -> None:
    for folder in (scan.folder.scans_dir, scan.folder.calib_dir):
        if not folder.is_dir() or scan.escapes(folder):
            continue
        for path in sorted(folder.rglob("*")):
            if path.is_file() and not scan.escapes(path):
                scan.extra_files.append(path)


def scan_folder(root: str | Path) -> FolderScan:
    """Everything about the folder but the pixels; ``scan.problems`` lists what is wrong."""
    scan = FolderScan(CaptureFolder(Path(root).resolve()))
    if not scan.folder.root.is_dir():
        scan.report(scan.folder.root, f"not a folder; give a capture folder ({_LAYOUT_DOC})")
        return scan
    _check_info(scan)
    _check_rig(scan)
    _check_log(scan)
    _check_cameras(scan)
    _check_extras(scan)
    return scan


def read_capture_image(path: Path) -> np.ndarray:
    """One capture image as float32 [H, W, C] (R, G, B(, A), or Y(, A)); ``ValueError`` saying what to do.

    Reads the file once and checks the channels' own types, which ``scene.image_io.read_exr``
    casts away: integer channels are not linear light, so the labeller's brightness would be wrong.
    """
    from scene.image_io import read_exr_channels, stack_channels

    try:
        channels = read_exr_channels(path, fix="export it again from the camera")
    except ValueError as err:  # the caller names the file, relative to the capture folder
        raise ValueError(str(err).removeprefix(f"{path}: ")) from err
    integer = sorted(name for name, pixels in channels.items() if pixels.dtype.kind != "f")
    if integer:
        raise ValueError(f"channel(s) {', '.join(integer)} hold {channels[integer[0]].dtype} values, not linear "
                         "float: export the images as HALF or FLOAT EXR in linear RGB")
    return stack_channels(path, channels)


def image_size_problem(scan: FolderScan, path: Path, shape: tuple[int, ...],
                       first: tuple[Path, tuple[int, ...]]) -> bool:
    """Report ``path`` when its size differs from the capture's first image; returns whether it did."""
    first_path, first_shape = first
    if shape[:2] == first_shape[:2]:
        return False
    scan.report(path, f"image is {shape[1]}x{shape[0]}, {scan.folder.relative(first_path)} is "
                      f"{first_shape[1]}x{first_shape[0]}; every image of a capture must have one size")
    return True


def rig_aspect_problem(scan: FolderScan, path: Path, shape: tuple[int, ...]) -> bool:
    """Report the capture's first image when its shape is not the rig's (at any scale); returns whether it did."""
    size = scan.rig["size"] if scan.rig else None
    if size is None or abs(shape[1] * size[1] - shape[0] * size[0]) <= 0.01 * shape[0] * size[0]:
        return False
    scan.report(path, f"image is {shape[1]}x{shape[0]}, rig.yaml says the sensors are {size[0]}x{size[1]} "
                      "(another aspect ratio): fix width_px/height_px there, or export the images uncropped")
    return True


def check_images(scan: FolderScan) -> None:
    """Open every image of the scan: readable, float, one size; problems go to ``scan.problems``."""
    first: tuple[Path, tuple[int, ...]] | None = None
    for cam, paths in scan.images.items():
        for path in paths:
            try:
                shape = read_capture_image(path).shape
            except ValueError as err:
                scan.report(path, str(err))
                continue
            if first is None:
                first = (path, shape)
                rig_aspect_problem(scan, path, shape)
            else:
                image_size_problem(scan, path, shape, first)


def check_capture(root: str | Path) -> list[Problem]:
    """Every problem of the capture folder at ``root`` (empty: it imports with nothing dropped)."""
    scan = scan_folder(root)
    check_images(scan)
    return scan.problems
