"""Held-out splits made by the train stage: novel light, novel performance, both."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from avatar.travatar import direction_uv

SPLITS = ("novel_light", "novel_perf", "novel_both")


@dataclass(frozen=True)
class Splits:
    """Frame masks [F] of each split and the held-out bars and take."""

    train: np.ndarray
    novel_light: np.ndarray
    novel_perf: np.ndarray
    novel_both: np.ndarray
    held_out_bars: tuple[int, ...]
    held_out_take: str

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
                held_out_take: str, held_out_fraction: float) -> Splits:
    """Masks over frames: training, novel light (3 interior bars), novel performance (a take), both.

    The novel performance is the final ``held_out_fraction`` of ``held_out_take`` (by default
    the capture's last take): a held-out segment of a performance the model never saw, while
    the beginning of that take still trains the model (a tiny capture has one OLAT cycle per
    take, so holding out a whole take would halve the training lights). ``held_out_fraction``
    1 holds out the whole take.
    """
    takes = list(dict.fromkeys(take.tolist()))
    name = held_out_take or (takes[-1] if takes else "")
    in_take = np.flatnonzero(take == name)
    cut = int(round(len(in_take) * (1.0 - held_out_fraction)))
    perf = np.zeros(len(take), bool)
    perf[in_take[cut:]] = True
    if held_out_fraction < 1.0:
        name = f"{name}[{cut}:]"
    both_takes = set(bar[perf].tolist()) & set(bar[~perf].tolist())
    held_bars = interior_bars({b: d for b, d in bar_dirs.items() if b in set(bar.tolist())}, held_out_bars,
                              both_takes)
    light = np.isin(bar, held_bars)
    return Splits(train=~perf & ~light, novel_light=~perf & light, novel_perf=perf & ~light,
                  novel_both=perf & light, held_out_bars=tuple(int(b) for b in held_bars), held_out_take=name)


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
