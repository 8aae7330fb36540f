"""The train stage's splits: training, validation (held-out light, held-out performance) and test.

Validation and test each hold out their own interior bars and their own frames of the
performance, disjoint from each other: every automatic choice (learning-curve points, pruning
figures, any setting) is made on validation, and the test splits are only measured at the end.
No validation or test frame trains the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass
from scipy.spatial import ConvexHull

from avatar.capacity import count_expression_modes
from avatar.layout import expression_basis
from avatar.travatar import direction_uv

#: The test splits, measured once at the end (their metric keys are ``{model}_{split}_*``).
SPLITS = ("novel_light", "novel_perf", "novel_both")
#: The validation splits: held-out light and held-out performance, disjoint from the test splits.
VAL_SPLITS = ("val_light", "val_perf")
#: Every held-out split, validation first.
HELD_OUT_SPLITS = VAL_SPLITS + SPLITS
#: Every mask of ``Splits``: each frame is in exactly one.
ALL_SPLITS = ("train",) + HELD_OUT_SPLITS + ("unused",)


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class ValidationSplit:
    """How much validation holds out (the train stage nests it as ``train.validation``)."""

    bars: int = Field(2, ge=1, description="Interior bars held out for the validation-light split, chosen by the "
                      "test bars' rule among the bars the test does not hold out.")
    fraction: float = Field(0.25, gt=0, lt=1, description="Frames held out for the validation-performance split, "
                            "as a fraction of the held-out take: the segment just before the test's "
                            "novel-performance segment (reaching into the previous take when the test holds out "
                            "the whole take).")


@dataclass(frozen=True)
class Splits:
    """Frame masks [F] of each split (``ALL_SPLITS``; each frame in exactly one) and what they hold out.

    Attributes:
        train: unlit by any held-out bar and outside both held-out segments.
        val_light, novel_light: a validation / test bar, frames of the training performance.
        val_perf, novel_perf: the validation / test segment, lit by a training bar.
        novel_both: the test segment lit by a test bar.
        unused: held-out frames of no split (the validation segment under a held-out bar, the test
            segment under a validation bar), kept out so that no split mixes validation and test.
        held_out_bars, held_out_take: the test's bars and segment (``take[start:]``).
        val_bars, val_segment: validation's bars and segment (``take[start:end]``, ``+``-joined
            where it spans takes).
    """

    train: np.ndarray
    val_light: np.ndarray
    val_perf: np.ndarray
    novel_light: np.ndarray
    novel_perf: np.ndarray
    novel_both: np.ndarray
    unused: np.ndarray
    held_out_bars: tuple[int, ...]
    held_out_take: str
    val_bars: tuple[int, ...]
    val_segment: str

    def mask(self, name: str) -> np.ndarray:
        return getattr(self, name)


def interior_bars(bar_dirs: dict[int, np.ndarray], count: int, preferred: set[int] | None = None) -> list[int]:
    """``count`` bars inside the convex hull of all bar directions, far from its edge and from each other.

    Interior bars keep the held-out lights inside the training lights' hull, so that
    TRAvatar*'s interpolation is defined and the comparison is a fair interpolation test.
    """
    ids = sorted(bar_dirs)
    uv = direction_uv(np.stack([bar_dirs[i] for i in ids]))  # [B, 2]
    hull = ConvexHull(uv)
    # Distance of every bar to the hull's boundary (the hull equations are unit-normal half-planes).
    depth = -(uv @ hull.equations[:, :2].T + hull.equations[:, 2]).max(-1)  # [B] >= 0 inside
    candidates = [i for i in range(len(ids)) if i not in set(hull.vertices) and depth[i] > 1e-6]
    # Prefer bars lit in both the training and the held-out take, so that every split has frames.
    good = [i for i in candidates if preferred is None or ids[i] in preferred]
    if len(good) >= count:
        candidates = good
    chosen: list[int] = []
    while candidates and len(chosen) < count:
        def score(i: int) -> float:
            spread = min((np.linalg.norm(uv[i] - uv[j]) for j in chosen), default=np.inf)
            return min(depth[i], 0.5 * spread)
        best = max(candidates, key=score)
        chosen.append(best)
        candidates.remove(best)
    return sorted(ids[i] for i in chosen)


def make_splits(take: np.ndarray, bar: np.ndarray, bar_dirs: dict[int, np.ndarray], held_out_bars: int,
                held_out_take: str, held_out_fraction: float, validation: ValidationSplit) -> Splits:
    """Masks over frames: training, validation (its own bars, its own segment) and test (light, performance, both).

    The test's novel performance is the final ``held_out_fraction`` of ``held_out_take`` (by
    default the capture's last take): a held-out segment of a performance the model never saw,
    while the beginning of that take still trains the model (a tiny capture has one OLAT cycle
    per take, so holding out a whole take would halve the training lights). ``held_out_fraction``
    1 holds out the whole take. Validation's segment is the ``validation.fraction`` of that take
    just before it; its bars are chosen after the test's, among the others.
    """
    takes = list(dict.fromkeys(take.tolist()))
    name = held_out_take or (takes[-1] if takes else "")
    in_take = np.flatnonzero(take == name)
    cut = int(round(len(in_take) * (1.0 - held_out_fraction)))
    perf = np.zeros(len(take), bool)
    perf[in_take[cut:]] = True
    if held_out_fraction < 1.0:
        name = f"{name}[{cut}:]"
    val_segment = _segment_before(len(take), in_take, cut, int(round(len(in_take) * validation.fraction)))
    seen_perf = ~perf & ~val_segment
    lit, seen, in_perf = set(bar.tolist()), set(bar[seen_perf].tolist()), set(bar[perf].tolist())
    # Test bars: preferably lit in the test segment and in the training performance, so that every test split
    # has frames. From every lit bar, so that a capture lighting each bar once (the smoke preset) still has
    # frames of novel light and novel performance together.
    held_bars = interior_bars({b: d for b, d in bar_dirs.items() if b in lit}, held_out_bars, seen & in_perf)
    # Validation bars by the same rule among the rest (the test bars are interior: the hull stays the same),
    # preferring bars lit in the training performance (validation-light frames) and unlit in the test segment,
    # whose frames they would take from the test splits.
    val_bars = interior_bars({b: d for b, d in bar_dirs.items() if b in lit and b not in held_bars},
                             validation.bars, seen - in_perf)
    test_light, val_light = np.isin(bar, held_bars), np.isin(bar, val_bars)
    seen_light = ~test_light & ~val_light
    return Splits(train=seen_perf & seen_light, val_light=seen_perf & val_light, val_perf=val_segment & seen_light,
                  novel_light=seen_perf & test_light, novel_perf=perf & seen_light, novel_both=perf & test_light,
                  unused=(val_segment & ~seen_light) | (perf & val_light),
                  held_out_bars=tuple(int(b) for b in held_bars), held_out_take=name,
                  val_bars=tuple(int(b) for b in val_bars), val_segment=_segment_name(take, val_segment))


def _segment_before(num_frames: int, in_take: np.ndarray, cut: int, count: int) -> np.ndarray:
    """Mask [F] of the ``count`` frames just before position ``cut`` of the take's frames ``in_take``.

    The frames before the test segment in capture order: the take's own when the test holds
    out only its end, the previous take's end when it holds out all of it.
    """
    start = int(in_take[cut]) if cut < len(in_take) else (int(in_take[-1]) + 1 if len(in_take) else num_frames)
    mask = np.zeros(num_frames, bool)
    mask[max(0, start - count):start] = True
    return mask


def _segment_name(take: np.ndarray, segment: np.ndarray) -> str:
    """``take[start:end]`` per take the segment spans (positions within the take), ``+``-joined."""
    parts = []
    for name in dict.fromkeys(take[segment].tolist()):
        positions = np.flatnonzero(segment[take == name])
        parts.append(f"{name}[{positions[0]}:{positions[-1] + 1}]")
    return " + ".join(parts)


def nearest_training_distance_mm(vertices: np.ndarray, train: np.ndarray, query: np.ndarray,
                                 chunk: int = 256) -> np.ndarray:
    """Per query frame, the RMS vertex distance (mm) to its nearest training frame's mesh.

    ``vertices`` [F, V, 3] head-space meshes (metres); ``train``, ``query`` [F] masks. A
    frame in both masks is not its own neighbour, so a training frame gets the distance to
    its nearest *other* training frame: the spacing of the training expressions, against
    which a held-out split's distance says how far it extrapolates (a held-out expression
    several times further from the training set than training frames are from each other is
    out of distribution).

    RMS over vertices is the Euclidean distance of the flattened meshes over sqrt(V), so all
    pairs come from one matrix product (|q|^2 + |t|^2 - 2 q.t) in float64 on offsets from the
    training mean: memory [chunk, F_train], not [chunk, F_train, V], for thousands of frames.
    """
    train_idx, query_idx = np.flatnonzero(train), np.flatnonzero(query)
    num_vertices = vertices.shape[1]
    mean = np.asarray(vertices[train_idx], np.float64).mean(0)
    ref = (np.asarray(vertices[train_idx], np.float64) - mean).reshape(len(train_idx), -1)  # [T, 3V]
    ref_sq = (ref * ref).sum(-1)  # [T]
    out = np.full(len(query_idx), np.nan)
    for start in range(0, len(query_idx), chunk):
        rows = query_idx[start:start + chunk]
        q = (np.asarray(vertices[rows], np.float64) - mean).reshape(len(rows), -1)  # [Q, 3V]
        sq = (q * q).sum(-1)[:, None] + ref_sq[None] - 2.0 * q @ ref.T  # [Q, T]
        dist = np.sqrt(np.maximum(sq, 0.0) / num_vertices) * 1000.0
        dist[rows[:, None] == train_idx[None]] = np.inf  # not its own neighbour
        out[start:start + len(rows)] = dist.min(1)
    return out


def expression_reach_sd(vertices: np.ndarray, train: np.ndarray, query: np.ndarray,
                        variance: float = 0.999) -> np.ndarray:
    """Per query frame, how many training standard deviations its mesh reaches along its most extreme expression mode.

    ``vertices`` [F, V, 3] head-space meshes; ``train``, ``query`` [F] masks. The modes are
    the training meshes' principal directions about their mean that hold ``variance`` of
    their spread (the capacity rule's expression modes); along each, a frame's coefficient is
    divided by the training frames' standard deviation, and the largest absolute value is
    returned. Where the nearest-mesh distance says how far a frame lies from the training
    expressions, this says whether it lies beyond their range: a frame further out along some
    mode than any training frame asks the networks to extrapolate, not interpolate. Meshes
    that never move give zeros.

    The principal directions come from the [T, T] Gram matrix of the offsets in float64, so
    the cost is T^2 V, bounded for thousands of frames of tens of thousands of vertices by
    the caller's choice of vertices (the train stage passes the guide mesh).
    """
    train_idx, query_idx = np.flatnonzero(train), np.flatnonzero(query)
    if len(train_idx) < 2:
        return np.zeros(len(query_idx))
    ref = np.asarray(vertices[train_idx], np.float64)
    modes = count_expression_modes(ref, variance)  # the capacity rule's count, so the two name the same modes
    if modes == 0:
        return np.zeros(len(query_idx))
    mean = ref.mean(0)
    directions = expression_basis(ref - mean, modes)  # [K, 3V] unit principal directions
    # Training frames' std along each (population, about the mean).
    std = np.sqrt(np.mean(((ref - mean).reshape(len(train_idx), -1) @ directions.T) ** 2, axis=0))
    q = (np.asarray(vertices[query_idx], np.float64) - mean).reshape(len(query_idx), -1)
    return np.abs(q @ directions.T / std[None]).max(1)
