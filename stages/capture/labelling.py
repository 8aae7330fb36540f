"""Label every received frame with its light by aligning each camera's frames to the
controller's log, and find dropped, repeated and shifted frames.

A camera that misses a trigger pulse delivers one frame fewer, so from there on its frames
sit one place earlier than the log says (shifted); one that delivers a frame twice, or an
exposure the controller did not act on (a dark frame), has one frame more. Image brightness
tells the lights apart: full-on frames are several times brighter than any OLAT frame, and
each bar lights a characteristic side of the face, so a camera sees a characteristic
brightness for each bar.

Features: per camera and received frame, the linear mean of the image, or better the means
of a coarse grid (2x2 quadrants): two bars that light a camera's view equally bright but
from different sides differ in the quadrants. The algorithm, per camera, on ``x = log``
of the features:

1. Split frames into full-on and OLAT by the widest gap of the total brightness near the
   rank that the log's share of full-on frames predicts, and align frames to log entries
   with a banded dynamic program (edit distance: match, drop a log entry, skip a frame)
   where a match costs the clip if the kinds disagree.
2. From the confidently matched frames (away from any drop or skipped frame), estimate each
   light's features in this camera (median) and the noise per feature (leave-one-out
   residuals); realign with the cost ``min(mean(z^2), clip)``, ``z`` the frame's deviation
   from its light's template in noise units; repeat until stable. Repeated cycles give
   every bar several frames; a light seen once keeps a vague template.
3. Unmatched frames equal to their predecessor (within ``repeat_rel_tol``) are
   ``repeated``; others are ``unexpected`` (e.g. dark: the controller missed the pulse).
   A matched frame beside a dropped entry that fits that entry about as well as its own is
   ``ambiguous`` (the images cannot tell which of the two was lost); others are ``ok``.
   A frame is ``shifted`` when its log entry differs from its position in the camera's
   stream (a naive labelling would have been wrong).

Optional per-frame time stamps (``frame_times_s``, e.g. camera hardware time stamps) add a
cost for matching a frame to a log entry at another time, which removes any ambiguity;
brightness then still catches a log that is out of step with the images.

Usage (capture stage)::

    from stages.capture.labelling import label_frames
    # brightness_per_camera[c]: [R_c, 4] linear means of the 2x2 image quadrants of every
    # received frame of camera c, in arrival order (or [R_c] image means)
    result = label_frames([e.light for e in log], brightness_per_camera, camera_names=names)
    for cam in result.cameras:          # per camera, per received frame
        cam.pulse[i], cam.light[i], cam.status[i]   # log index (-1: none), "F"/bar/None, status
    result.pulse_frame[c, k]            # "ok" frame of log entry k in camera c, -1 = none
    result.pulse_status[k]              # "ok" (every camera has it) or "dropped" (some camera lacks it)
    for line in result.warnings: ctx.log.warning(line)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence, Union

import numpy as np

Light = Union[str, int, None]  # "F", a bar id, or None (nothing lit)

_MATCH, _EXTRA, _DROP = 0, 1, 2


@dataclass(frozen=True)
class LabellingConfig:
    """Tuning of ``label_frames`` (costs are in squared noise units).

    Attributes:
        gap_cost: cost of dropping a log entry, and of skipping a received frame.
        clip_z2: a match never costs more than this (so a bad frame can still be matched
            when skipping it would shift everything after it).
        repeat_cost: cost of skipping a frame that equals its predecessor.
        repeat_rel_tol: relative brightness difference under which a frame equals its predecessor.
        noise_floor: smallest noise scale of log-brightness (0.02 = 2 %).
        max_shift: the band of the alignment: how far (in frames) a camera may drift
            from the log beyond the difference of their lengths.
        iterations: passes of template estimation and realignment.
        mismatch_z: matched frames further than this from their light's brightness are warned about.
        time_weight: cost per frame period of time-stamp disagreement (with ``frame_times_s``).
        event_margin: frames this close to a drop or an extra frame do not shape the
            brightness templates (their match may be the wrong one of two neighbours).
        dark_fraction: frames darker than this fraction of the lower quartile of the OLAT
            frames' brightness are dark exposures (nothing lit), never labelled with a light
            (on a face, the dimmest bar in a camera is about 0.2 of that quartile).
        feature_floor: added to every feature, as a fraction of its full-on level, before
            the log (quiets features that a light barely reaches).
        ambiguity_margin: a frame beside a dropped entry that fits that entry within this
            cost of its own is flagged ``ambiguous`` (brightness cannot tell which was lost).
    """

    gap_cost: float = 12.0
    clip_z2: float = 36.0
    repeat_cost: float = 1.0
    repeat_rel_tol: float = 1e-6
    noise_floor: float = 0.02
    max_shift: int = 64
    iterations: int = 4
    mismatch_z: float = 5.0
    time_weight: float = 20.0
    event_margin: int = 2
    ambiguity_margin: float = 2.0
    dark_fraction: float = 0.05
    feature_floor: float = 5e-4


@dataclass(frozen=True)
class CameraLabels:
    """Labels of one camera's received frames (index = position in the camera's stream).

    Attributes:
        camera: camera name.
        pulse: [R] log entry of each received frame, -1 for none (repeated / unexpected).
        light: [R] light of each frame: the log's light; a repeated frame has its original's.
        status: [R] ``"ok"``, ``"ambiguous"`` (beside a dropped frame and fitting its light
            about as well as its own), ``"repeated"`` or ``"unexpected"``; use only ``"ok"`` frames.
        shifted: [R] the frame's log entry differs from its position (naive label was wrong).
        z: [R] RMS deviation (over features) of each matched frame from its light's
            brightness, in noise units (nan for unmatched frames).
    """

    camera: str
    pulse: np.ndarray
    light: list[Light]
    status: list[str]
    shifted: np.ndarray
    z: np.ndarray


@dataclass(frozen=True)
class LabelResult:
    """Labels of every camera, and per log entry where its frames are.

    Attributes:
        cameras: one ``CameraLabels`` per camera, in input order.
        pulse_frame: [C, K] received ``"ok"`` frame of each log entry per camera, -1 if the
            camera has none (dropped, or its frame is ambiguous).
        pulse_status: [K] ``"ok"`` when every camera has an ``"ok"`` frame for the entry, else ``"dropped"``.
        warnings: human-readable lines naming camera, frame and log entry.
    """

    cameras: list[CameraLabels]
    pulse_frame: np.ndarray
    pulse_status: list[str]
    warnings: list[str] = field(default_factory=list)

    def dropped_frames(self) -> int:
        """Frames missing over all cameras (log entries times cameras without a frame)."""
        return int((self.pulse_frame < 0).sum())

    def count(self, status: str) -> int:
        """How many received frames (all cameras) have ``status``."""
        return sum(cam.status.count(status) for cam in self.cameras)

    def shifted_frames(self) -> int:
        """Received frames (all cameras) whose naive position label was wrong."""
        return int(sum(cam.shifted.sum() for cam in self.cameras))


def _light_classes(log_lights: Sequence[Light]) -> tuple[np.ndarray, list[Light]]:
    """Class index per log entry and the distinct lights (first appearance order)."""
    keys: dict[object, int] = {}
    order: list[Light] = []
    classes = np.empty(len(log_lights), int)
    for k, light in enumerate(log_lights):
        key = ("bar", light) if isinstance(light, (int, np.integer)) else ("tok", light)
        if key not in keys:
            keys[key] = len(order)
            order.append(int(light) if isinstance(light, (int, np.integer)) else light)
        classes[k] = keys[key]
    return classes, order


def _bright_threshold(x: np.ndarray, full_on_fraction: float) -> float:
    """Log-brightness separating full-on from OLAT frames.

    The widest gap between sorted values near the rank where the log's share of full-on
    frames puts it (a few dropped or dark frames move that rank only a little; a global
    widest gap could fall between dark frames and the rest).
    """
    values = np.sort(x)
    n = len(values)
    if n < 2:
        return float(values[0]) - 1.0 if n else 0.0
    split = n * (1.0 - full_on_fraction)  # expected count of frames below the threshold
    margin = max(2.0, 0.25 * n * min(full_on_fraction, 1.0 - full_on_fraction))
    lo = int(np.clip(np.floor(split - margin), 0, n - 2))
    hi = int(np.clip(np.ceil(split + margin), lo + 1, n - 1))
    gaps = np.diff(values)[lo:hi]  # gap i lies between values[lo + i] and values[lo + i + 1]
    i = lo + int(np.argmax(gaps))
    return float(0.5 * (values[i] + values[i + 1]))


MatchCost = Union[np.ndarray, Callable[[int, np.ndarray], np.ndarray]]


def align(match_cost: MatchCost, extra_cost: np.ndarray, drop_cost: float, band: int,
          n_log: int | None = None) -> np.ndarray:
    """Banded edit-distance alignment of R frames to K log entries.

    Args:
        match_cost: [R, K] cost of labelling frame r with log entry k, or a function
            ``(r, ks) -> costs`` giving row r at entries ``ks`` (only the band is evaluated,
            so long captures never need the dense [R, K] matrix).
        extra_cost: [R] cost of leaving frame r unmatched.
        drop_cost: cost of a log entry without a frame.
        band: allowed |k - r| drift beyond ``K - R``.
        n_log: K, needed when ``match_cost`` is a function.

    Returns:
        [R] log entry per frame, -1 for unmatched frames.
    """
    if callable(match_cost):
        if n_log is None:
            raise ValueError("align: n_log is needed with a match-cost function")
        row_cost = match_cost
    else:
        dense = np.asarray(match_cost, float)
        n_log = dense.shape[1]

        def row_cost(r: int, ks: np.ndarray) -> np.ndarray:
            return dense[r, ks]
    n_frames = len(extra_cost)
    below = band + max(0, n_frames - n_log)  # how far k may trail r
    above = band + max(0, n_log - n_frames)  # how far k may lead r
    width = below + above + 1
    # Column j of row r holds log position k = r - below + j (positions 0..K in the DP grid).
    inf = np.inf
    cost = np.full((n_frames + 1, width), inf)
    move = np.zeros((n_frames + 1, width), np.int8)
    j_all = np.arange(width)
    k0 = -below + j_all  # row 0
    valid = (k0 >= 0) & (k0 <= n_log)
    cost[0, valid] = k0[valid] * drop_cost
    move[0, valid] = _DROP
    for r in range(1, n_frames + 1):
        k = r - below + j_all  # [W]
        prev = cost[r - 1]
        best = np.full(width, inf)
        kind = np.zeros(width, np.int8)
        # Match frame r-1 with entry k-1: the previous row, same column.
        ok = (k >= 1) & (k <= n_log)
        diag = np.full(width, inf)
        diag[ok] = prev[ok] + row_cost(r - 1, k[ok] - 1)
        better = diag < best
        best[better], kind[better] = diag[better], _MATCH
        # Skip frame r-1: the previous row, next column (same k).
        extra = np.full(width, inf)
        extra[:-1] = prev[1:] + extra_cost[r - 1]
        extra[~((k >= 0) & (k <= n_log))] = inf
        better = extra < best
        best[better], kind[better] = extra[better], _EXTRA
        # Drop entries: same row, from the left; a running minimum of best - drop * j.
        running = np.minimum.accumulate(best - drop_cost * j_all) + drop_cost * j_all
        running[~((k >= 0) & (k <= n_log))] = inf
        dropped = running < best - 1e-12
        best = np.where(dropped, running, best)
        kind[dropped] = _DROP
        cost[r], move[r] = best, kind
    j = n_log - n_frames + below
    if not 0 <= j < width or not np.isfinite(cost[n_frames, j]):
        raise ValueError(f"{n_frames} frames cannot be aligned to {n_log} log entries within a drift of {band}")
    labels = np.full(n_frames, -1, int)
    r = n_frames
    while r > 0 or r - below + j > 0:
        step = move[r, j]
        if r == 0 or step == _DROP:
            j -= 1
        elif step == _MATCH:
            labels[r - 1] = r - below + j - 1
            r -= 1
        else:
            r -= 1
            j += 1
    return labels


def _near_alignment_events(labels: np.ndarray, n_log: int, margin: int) -> np.ndarray:
    """[R] frames within ``margin`` positions of an extra frame or of a dropped log entry."""
    n_frames = len(labels)
    events = np.zeros(n_frames + 1, bool)  # event "before frame r" (r = n_frames: at the end)
    events[:n_frames] |= labels < 0
    matched = np.flatnonzero(labels >= 0)
    expected = 0
    for r in matched:
        if labels[r] > expected:
            events[r] = True  # entries expected..labels[r]-1 were dropped just before frame r
        expected = labels[r] + 1
    if expected < n_log:
        events[n_frames] = True
    near = np.zeros(n_frames, bool)
    for r in np.flatnonzero(events):
        near[max(0, r - margin):min(n_frames, r + margin + 1)] = True
    return near


def _label_camera(x: np.ndarray, raw_total: np.ndarray, classes: np.ndarray, n_classes: int,
                  full_on_class: int | None, none_class: int | None,
                  times: np.ndarray | None, log_times: np.ndarray | None, period_s: float,
                  config: LabellingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Align one camera's log-brightness features ``x`` [R, D] to the log's classes [K].

    ``raw_total`` [R] is the linear features summed (without the soft floor). Returns the
    log entry per frame (-1: none), the RMS z per frame, repeat flags, ambiguity flags and
    the median noise scale.
    """
    n_frames, n_features = x.shape
    n_log = len(classes)
    repeated_like = np.zeros(n_frames, bool)
    if n_frames > 1:
        repeated_like[1:] = np.all(np.abs(np.diff(x, axis=0)) < config.repeat_rel_tol, axis=1)
    if n_log == 0:  # an empty log: no frame can be labelled
        return (np.full(n_frames, -1), np.full(n_frames, np.nan), repeated_like, np.zeros(n_frames, bool),
                config.noise_floor)
    extra_cost = np.where(repeated_like, config.repeat_cost, config.gap_cost)
    dark = np.zeros(n_frames, bool)

    # Kinds: full-on frames are far brighter than any OLAT frame, so a threshold on the total
    # brightness splits them.
    total = np.log(np.maximum(raw_total, 1e-30))  # [R] log of the summed features, without the soft floor
    full_on_fraction = float(np.mean(classes == full_on_class)) if full_on_class is not None else 0.0
    threshold = _bright_threshold(total, full_on_fraction) if full_on_class is not None else np.inf
    frame_bright = total > threshold  # [R]
    # Dark exposures (the controller missed the pulse: nothing lit) are skipped cheaply and
    # never take a log entry; otherwise one could stand in for a neighbouring dropped frame.
    # "Dark" is relative to the dim end of the OLAT frames (a bar behind a camera's view
    # still lights a rim), so a bar that barely reaches a camera is not mistaken for one.
    if (~frame_bright).sum() >= 20:
        # The lower quartile stays put when a few frames are dark.
        dark = total < np.quantile(total[~frame_bright], 0.25) + np.log(config.dark_fraction)
        extra_cost = np.where(dark, config.repeat_cost, extra_cost)
    # Log entries where the controller lit nothing (the program had run out) take dark frames only.
    entry_unlit = classes == none_class if none_class is not None else np.zeros(n_log, bool)  # [K]

    def row_costs(frame_class_costs: np.ndarray) -> Callable[[int, np.ndarray], np.ndarray]:
        """Match costs of frame r against entries ks from its per-class costs [R, n_classes]."""
        def row(r: int, ks: np.ndarray) -> np.ndarray:
            # A frame identical to its predecessor is a duplicate delivery, never a new
            # exposure (sensor noise differs between exposures): it takes no log entry.
            if repeated_like[r]:
                return np.full(len(ks), np.inf)
            if dark[r]:
                costs = np.where(entry_unlit[ks], 0.0, np.inf)
            else:
                costs = np.where(entry_unlit[ks], config.clip_z2, frame_class_costs[r, classes[ks]])
            if times is not None and log_times is not None:
                costs = costs + config.time_weight * np.minimum(np.abs(times[r] - log_times[ks]) / period_s, 10.0)
            return costs
        return row
    class_bright = np.array([c == full_on_class for c in range(n_classes)])  # [n_classes]
    # Mean and standard deviation, not median and MAD: OLAT brightness is multi-modal (bars
    # facing the camera, bars behind it) and every mode must look ordinary.
    kind_centre, kind_spread = np.zeros((2, n_features)), np.ones((2, n_features))  # (olat, full-on)
    for kind, members in enumerate((~frame_bright, frame_bright)):
        if members.any():
            kind_centre[kind] = x[members].mean(axis=0)
            kind_spread[kind] = np.maximum(config.noise_floor, x[members].std(axis=0))
    # A frame of the wrong kind for a class costs the clip outright.
    kind_penalty = np.where(frame_bright[:, None] == class_bright[None, :], 0.0, config.clip_z2)  # [R, n_classes]

    def class_costs(centre: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """[R, n_classes] mean over features of the squared deviation, clipped."""
        z2 = (((x[:, None, :] - centre[None]) / scale[None]) ** 2).mean(axis=2)  # [R, n_classes]
        return np.minimum(z2 + kind_penalty, config.clip_z2)

    # Pass 0: every class looks like its kind; a class's scale is 1.5 times its kind's spread,
    # so the cost only separates kinds and disfavours outliers (dark frames) within a kind.
    unknown_centre = kind_centre[class_bright.astype(int)]  # [n_classes, D]
    unknown_scale = 1.5 * kind_spread[class_bright.astype(int)]  # [n_classes, D]
    labels = align(row_costs(class_costs(unknown_centre, unknown_scale)), extra_cost,
                   config.gap_cost, config.max_shift, n_log)
    centre, scale = unknown_centre, unknown_scale
    known = np.zeros(n_classes, bool)
    sigma = np.full(n_features, config.noise_floor)
    unsure = np.zeros(n_frames, bool)
    for _ in range(config.iterations):
        matched = labels >= 0
        # A class's template is the median of its confidently matched frames: those away from
        # any drop or extra frame of this or an earlier pass, where the alignment may have
        # picked the wrong one of two neighbours (accumulating the zones keeps the passes from
        # oscillating). Classes without such frames keep the vague kind-level template.
        frame_class = np.where(matched, classes[np.maximum(labels, 0)], -1)
        unsure |= _near_alignment_events(labels, n_log, config.event_margin)
        confident = matched & ~unsure
        centre, scale = unknown_centre.copy(), unknown_scale.copy()
        known = np.zeros(n_classes, bool)
        for c in range(n_classes):
            values = x[confident & (frame_class == c)]  # [n, D]
            if not len(values):
                # No confident frame: the unsure ones are still better than the kind's template.
                values = x[matched & (frame_class == c)]
            if len(values):
                centre[c], known[c] = np.median(values, axis=0), True
        # Noise from leave-one-out residuals (a frame against the mean of its class's other
        # frames, scaled by sqrt((n - 1) / n)): residuals from the class's own median would
        # understate it (with three frames one residual is exactly zero).
        counts = np.bincount(frame_class[confident], minlength=n_classes).astype(float)  # [n_classes]
        use = confident & (counts[np.maximum(frame_class, 0)] > 1)
        if use.any():
            sums = np.zeros((n_classes, n_features))
            np.add.at(sums, frame_class[confident], x[confident])
            n_use = counts[frame_class[use]][:, None]  # [U, 1]
            others_mean = (sums[frame_class[use]] - x[use]) / (n_use - 1.0)  # [U, D]
            residuals = (x[use] - others_mean) * np.sqrt((n_use - 1.0) / n_use)
            sigma = np.maximum(config.noise_floor, 1.4826 * np.median(np.abs(residuals), axis=0))  # [D]
        scale[known] = sigma
        new_labels = align(row_costs(class_costs(centre, scale)), extra_cost,
                           config.gap_cost, config.max_shift, n_log)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
    z = np.full(n_frames, np.nan)
    matched = labels >= 0
    deviation = (x[matched] - centre[classes[labels[matched]]]) / scale[classes[labels[matched]]]  # [M, D]
    z[matched] = np.sqrt((deviation ** 2).mean(axis=1))
    final_cost = row_costs(class_costs(centre, scale))
    ambiguous = _ambiguous_next_to_drops(labels, final_cost, known[classes], config.ambiguity_margin)
    return labels, z, repeated_like, ambiguous, float(np.median(sigma))


def _ambiguous_next_to_drops(labels: np.ndarray, cost: Callable[[int, np.ndarray], np.ndarray],
                             entry_known: np.ndarray, margin: float) -> np.ndarray:
    """[R] matched frames beside a dropped entry that would fit that entry nearly as well.

    A drop between frames can be explained by moving it one entry earlier or later: the
    frame beside the gap then takes the dropped entry instead of its own. If that costs less
    than ``margin`` more, or either entry's light has no template of its own in this camera
    (``entry_known`` [K] false), brightness cannot tell which frame was lost: flagged.
    """
    n_log = len(entry_known)
    frame_of = np.full(n_log, -1)
    matched = np.flatnonzero(labels >= 0)
    frame_of[labels[matched]] = matched
    ambiguous = np.zeros(len(labels), bool)
    for k in np.flatnonzero(frame_of < 0):
        for neighbour in (k - 1, k + 1):
            if 0 <= neighbour < n_log and frame_of[neighbour] >= 0:
                r = frame_of[neighbour]
                unknown = not (entry_known[k] and entry_known[neighbour])
                own, other = cost(r, np.array([neighbour, k]))
                if unknown or other - own < margin:
                    ambiguous[r] = True
    return ambiguous


def label_frames(log_lights: Sequence[Light], brightness: Sequence[Sequence[float]] | np.ndarray,
                 camera_names: Sequence[str] | None = None,
                 frame_times_s: Sequence[Sequence[float]] | None = None,
                 log_times_s: Sequence[float] | None = None,
                 config: LabellingConfig | None = None) -> LabelResult:
    """Label every received frame of every camera with its light.

    Args:
        log_lights: [K] the controller log's light per pulse it acted on (``"F"``, bar id, None).
        brightness: per camera, the brightness of each received frame in arrival order,
            linear: [R] image means, or better [R, D] means over a coarse grid of the image
            (e.g. 2x2 quadrants, D = 4), which tell apart bars that light a camera's view
            equally but from different sides. A [C, R(, D)] array, or C arrays of different R.
        camera_names: names used in warnings (default ``cam00`` ...).
        frame_times_s: optional per camera time stamp of each received frame, seconds.
        log_times_s: [K] time of each log entry (``time_us / 1e6``); needed with ``frame_times_s``.
        config: tuning; defaults suit 32 bars and a few percent of image noise.

    Returns:
        A ``LabelResult``: per-frame labels and statuses, per-entry frames, warnings.

    Raises:
        ValueError: inconsistent lengths, or a camera too far out of step with the log
            (more missing or extra frames than ``config.max_shift``).
    """
    config = config or LabellingConfig()
    per_camera = [np.asarray(b, float) for b in brightness]
    per_camera = [b[:, None] if b.ndim == 1 else b for b in per_camera]  # [R, D]
    names = list(camera_names) if camera_names is not None else [f"cam{c:02d}" for c in range(len(per_camera))]
    if len(names) != len(per_camera):
        raise ValueError(f"{len(names)} camera names for {len(per_camera)} cameras")
    if frame_times_s is not None and (log_times_s is None or len(frame_times_s) != len(per_camera)):
        raise ValueError("frame_times_s needs log_times_s and one sequence per camera")
    classes, lights = _light_classes(log_lights)
    full_on_class = next((i for i, light in enumerate(lights) if light == "F"), None)
    none_class = next((i for i, light in enumerate(lights) if light is None), None)
    n_log = len(classes)
    log_times = np.asarray(log_times_s, float) if log_times_s is not None else None
    period_s = float(np.median(np.diff(log_times))) if log_times is not None and n_log > 1 else 1.0
    warnings: list[str] = []
    cameras: list[CameraLabels] = []
    pulse_frame = np.full((len(per_camera), n_log), -1, int)
    for c, (name, values) in enumerate(zip(names, per_camera)):
        if values.ndim != 2 or np.any(~np.isfinite(values)) or np.any(values < 0):
            raise ValueError(f"camera {name}: brightness must be [frames] or [frames, features], "
                             f"finite and >= 0")
        # A soft floor per feature, a small fraction of its full-on level (the brightest
        # frames): a quadrant that a bar barely reaches holds mostly noise, and its log would
        # swing wildly; the floor keeps such features quiet while dark frames stay far below.
        bright_level = np.quantile(values, 0.9, axis=0) if len(values) else np.ones(values.shape[1])  # [D]
        floor = np.maximum(bright_level * config.feature_floor, 1e-12)  # [D]
        x = np.log(values + floor)  # [R, D]
        times = None
        if frame_times_s is not None:
            times = np.asarray(frame_times_s[c], float)
            if len(times) != len(x):
                raise ValueError(f"camera {name}: {len(times)} time stamps for {len(x)} frames")
        try:
            labels, z, repeated_like, ambiguous, sigma = _label_camera(x, values.sum(axis=1), classes, len(lights), full_on_class, none_class, times,
                                                            log_times, period_s, config)
        except ValueError as err:
            raise ValueError(f"camera {name}: {err}; raise max_shift or check the controller log") from err
        status, frame_lights = [], []
        for r, k in enumerate(labels):
            if k >= 0:
                status.append("ambiguous" if ambiguous[r] else "ok")
                frame_lights.append(log_lights[k])
                if not ambiguous[r]:
                    pulse_frame[c, k] = r
            elif repeated_like[r]:
                status.append("repeated")
                frame_lights.append(frame_lights[-1] if frame_lights else None)
            else:
                status.append("unexpected")
                frame_lights.append(None)
        shifted = (labels >= 0) & (labels != np.arange(len(labels)))
        cameras.append(CameraLabels(name, labels, frame_lights, status, shifted, z))
        warnings.extend(_camera_warnings(name, labels, status, z, pulse_frame[c], log_lights, sigma, config))
    pulse_status = ["ok" if (pulse_frame[:, k] >= 0).all() else "dropped" for k in range(n_log)]
    return LabelResult(cameras, pulse_frame, pulse_status, warnings)


def _camera_warnings(name: str, labels: np.ndarray, status: list[str], z: np.ndarray,
                     frame_of_pulse: np.ndarray, log_lights: Sequence[Light], sigma: float,
                     config: LabellingConfig) -> list[str]:
    lines = []
    dropped = np.flatnonzero(frame_of_pulse < 0)
    if len(dropped):
        shown = ", ".join(f"{k} ({log_lights[k]})" for k in dropped[:10])
        lines.append(f"camera {name}: {len(dropped)} frame(s) missing for log entries {shown}"
                     f"{' ...' if len(dropped) > 10 else ''}; later frames relabelled")
    for kind in ("repeated", "unexpected", "ambiguous"):
        frames = [r for r, s in enumerate(status) if s == kind]
        if frames:
            lines.append(f"camera {name}: {len(frames)} {kind} frame(s) at received index "
                         f"{', '.join(map(str, frames[:10]))}{' ...' if len(frames) > 10 else ''}; excluded")
    far = np.flatnonzero(np.abs(np.nan_to_num(z)) > config.mismatch_z)
    if len(far):
        lines.append(f"camera {name}: {len(far)} frame(s) differ from their light's brightness by more than "
                     f"{config.mismatch_z} x {sigma:.3f} (log units), e.g. received frame {far[0]} "
                     f"(log entry {labels[far[0]]}, light {log_lights[labels[far[0]]]}); check them")
    return lines
