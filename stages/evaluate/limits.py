"""The measured warning zone: ``limits.json`` of the evaluate stage and the check a render can call.

The evaluate stage measures how far (in angle) a point light may move away from the nearest
light the model was trained with before the relit render falls under a PSNR threshold. It
writes that limit with the training light directions (head space, seen from the head's
centre) to ``limits.json``. A renderer asks ``light_warning(position_head, limits)`` for
every requested light and shows the message it returns::

    limits = read_limits(evaluate_dir / "limits.json")
    message = light_warning(np.array([0.0, 0.2, -3.0]), limits)
    if message:
        log.warning(message)

Only this file and ``numpy`` are needed, so a CLI can import it cheaply.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from stages.evaluate.output import LIMITS_FILE, EvaluateOutput  # noqa: F401  (LIMITS_FILE: re-exported)


@dataclass(frozen=True)
class LightLimits:
    """How far from the training lights a relit render stays above ``psnr_threshold_db``.

    Attributes:
        light_extrapolation_limit_deg: angle from the nearest training light direction where
            the measured PSNR first falls under the threshold.
        censored: nothing measured fell under the threshold; the limit is the widest angle tested.
        psnr_threshold_db: the threshold that defines the limit.
        centre_head: [3] head-space point the directions are taken from (metres).
        training_light_dirs_head: [L, 3] unit directions of the training lights from ``centre_head``.
    """

    light_extrapolation_limit_deg: float
    censored: bool
    psnr_threshold_db: float
    centre_head: tuple[float, float, float]
    training_light_dirs_head: tuple[tuple[float, float, float], ...]

    def angle_from_training_deg(self, position_head: np.ndarray) -> float:
        """Angle in degrees between the direction to ``position_head`` [3] and the nearest training light."""
        d = np.asarray(position_head, float).reshape(3) - np.asarray(self.centre_head, float)
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        dirs = np.asarray(self.training_light_dirs_head, float).reshape(-1, 3)
        dirs = dirs / np.maximum(np.linalg.norm(dirs, axis=-1, keepdims=True), 1e-12)
        return math.degrees(math.acos(float(np.clip(dirs @ d, -1.0, 1.0).max())))


def write_limits(path: Path, limits: LightLimits, extra: dict | None = None) -> None:
    """Write ``limits`` (and ``extra`` scalars, e.g. expression-scale limits) as JSON."""
    record = {**asdict(limits), **(extra or {})}
    record["centre_head"] = list(limits.centre_head)
    record["training_light_dirs_head"] = [list(d) for d in limits.training_light_dirs_head]
    Path(path).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")


def read_limits(path: Path) -> LightLimits:
    """Load ``limits.json``; ``ValueError`` naming the file when it is missing a field or malformed."""
    try:
        record = json.loads(Path(path).read_text(encoding="utf-8"))
        dirs = tuple(tuple(float(v) for v in d) for d in record["training_light_dirs_head"])
        if not dirs or any(len(d) != 3 for d in dirs):
            raise ValueError("training_light_dirs_head must be a non-empty list of 3-vectors")
        return LightLimits(float(record["light_extrapolation_limit_deg"]), bool(record["censored"]),
                           float(record["psnr_threshold_db"]), tuple(float(v) for v in record["centre_head"]),
                           dirs)
    except (OSError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: not a readable limits file ({err}); re-run `pipeline run --only evaluate`") from err


def light_warning(position_head: np.ndarray, limits: LightLimits, what: str = "light") -> str | None:
    """A warning message when ``position_head`` [3] lies beyond the measured limit, else None.

    A censored limit (nothing failed within the angles tested) never warns: the zone is unknown,
    not measured to be bad.
    """
    if limits.censored:
        return None
    angle = limits.angle_from_training_deg(position_head)
    if angle <= limits.light_extrapolation_limit_deg:
        return None
    pos = [round(float(v), 3) for v in np.asarray(position_head, float).reshape(3)]
    return (f"{what} at {pos} (head space, m) is {angle:.0f} degrees from the nearest training light; "
            f"the evaluate stage measured relit PSNR under {limits.psnr_threshold_db:g} dB beyond "
            f"{limits.light_extrapolation_limit_deg:.0f} degrees, so expect an unreliable render")


def orbit_light_positions(radius_m: float, frames: int, centre_head: np.ndarray) -> np.ndarray:
    """Positions [F, 3] of a horizontal light orbit starting in front (+z), as ``pipeline render --orbit`` makes them."""
    a = 2 * math.pi * np.arange(frames) / max(frames, 1)
    return np.asarray(centre_head, float) + radius_m * np.stack([np.sin(a), np.zeros(frames), np.cos(a)], -1)


def requested_light_warnings(limits_path: Path | None, point_lights_head=(), orbit_radius_m: float = 0.0,
                             orbit_frames: int = 0) -> list[str]:
    """Messages for the requested lights that lie beyond the measured limit ([] if none, or no limits file).

    ``point_lights_head``: [K, 3] head-space positions; an orbit of ``orbit_frames`` frames at
    ``orbit_radius_m`` gives one message listing its frames beyond the limit.
    """
    if limits_path is None or not Path(limits_path).is_file():
        return []
    try:
        limits = read_limits(Path(limits_path))
    except ValueError as err:
        return [f"cannot check the requested lights against the measured limit: {err}"]
    messages = []
    for k, p in enumerate(np.asarray(point_lights_head, float).reshape(-1, 3)):
        message = light_warning(p, limits, what=f"point light {k}")
        if message:
            messages.append(message)
    if orbit_radius_m > 0 and orbit_frames > 0:
        positions = orbit_light_positions(orbit_radius_m, orbit_frames, np.asarray(limits.centre_head))
        beyond = [i for i, p in enumerate(positions) if light_warning(p, limits) is not None]
        if beyond:
            messages.append(f"orbit: frames {beyond} ({len(beyond)} of {orbit_frames}) put the light more than "
                            f"{limits.light_extrapolation_limit_deg:.0f} degrees from the nearest training light, "
                            f"where the evaluate stage measured relit PSNR under {limits.psnr_threshold_db:.1f} dB; "
                            "expect unreliable frames there")
    return messages


def workspace_light_warnings(workspace, point_lights_head=(), orbit_radius_m: float = 0.0,
                             orbit_frames: int = 0) -> list[str]:
    """``requested_light_warnings`` with the limits of ``workspace``'s current evaluate output (if any).

    ``workspace``: a ``pipeline.workspace.Workspace`` (``read_ref`` / ``object_path``). A subject
    never evaluated gives [] (nothing measured, nothing to warn about).
    """
    ref = workspace.read_ref("evaluate")
    if ref is None or "out" not in ref.outputs:
        return []
    return requested_light_warnings(EvaluateOutput(workspace.object_path(ref.outputs["out"])).limits_path,
                                    point_lights_head, orbit_radius_m, orbit_frames)
