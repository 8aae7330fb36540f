"""The OLAT order of the light bars: consecutive OLAT lights as dissimilar as possible.

Dissimilarity of two bars = the angle between their directions seen from the head centre.
The capture pattern ``F, O1, O2, F, O3, O4, ..., F, O31, O32`` repeats, so every pair of
consecutive OLAT frames counts, whether adjacent in time (O1, O2) or separated by a
full-on frame (O2, O3), and the cycle closes (O32 -> O1 of the next cycle). The order is
therefore a Hamiltonian *cycle* over the bars, and the measure (the ``sequence`` metrics in
docs/design.md) is the mean and the minimum of its edge angles.

We solve it lexicographically: first the largest achievable minimum angle (a bottleneck
travelling-salesman problem), then the largest sum of angles among the cycles whose every
edge reaches that minimum. The exact method is an integer program (HiGHS through
``scipy.optimize.milp``): binary edge variables, two edges per bar, subtour-elimination cuts
added lazily until the solution is one cycle; the bottleneck is a search over thresholds,
starting from the analytic bound (``olat_upper_bounds``), which the rig usually reaches.
For 32 bars it takes tens of milliseconds. The local method (farthest-neighbour and random
starts, then 2-opt and or-opt moves) needs no solver and serves as a cross-check and a
fallback when the integer program hits its time limit.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import csr_matrix


@dataclass(frozen=True)
class OrderResult:
    """A solved OLAT order and its figures (angles in degrees)."""

    olat_order: tuple[int, ...]       # indices into the bar array, in capture order
    angles_deg: np.ndarray            # [B] angle of each consecutive pair, the last one closing the cycle
    mean_deg: float
    min_deg: float
    method: str                       # "exact" or "local" (what produced the order)


def bar_directions(bar_centres_world: np.ndarray, head_centre_world: np.ndarray) -> np.ndarray:
    """Unit directions from the head centre to each bar centre, [B, 3]."""
    offsets = np.asarray(bar_centres_world, float) - np.asarray(head_centre_world, float)  # [B, 3]
    norms = np.linalg.norm(offsets, axis=1, keepdims=True)
    if np.any(norms < 1e-9):
        bad = int(np.argmin(norms[:, 0]))
        raise ValueError(f"bar {bad} sits at the head centre; its direction is undefined")
    return offsets / norms


def angle_matrix_deg(directions: np.ndarray) -> np.ndarray:
    """Pairwise angles in degrees between unit directions [B, 3] -> [B, B]."""
    cosines = np.clip(directions @ directions.T, -1.0, 1.0)  # [B, B]
    return np.degrees(np.arccos(cosines))


def cycle_angles_deg(angles_deg: np.ndarray, order: np.ndarray | list[int]) -> np.ndarray:
    """Angles of consecutive pairs along the cyclic ``order`` ([B]; the last closes the cycle)."""
    order = np.asarray(order, int)
    return angles_deg[order, np.roll(order, -1)]


def random_baseline_mean_deg(angles_deg: np.ndarray, seed: int, samples: int = 256) -> float:
    """Mean consecutive angle averaged over ``samples`` seeded random orders."""
    rng = np.random.default_rng(seed)
    n = angles_deg.shape[0]
    means = [cycle_angles_deg(angles_deg, rng.permutation(n)).mean() for _ in range(samples)]
    return float(np.mean(means))


def olat_upper_bounds(angles_deg: np.ndarray) -> tuple[float, float]:
    """Upper bounds (min angle, mean angle) over all cyclic orders.

    In a cycle every bar has two neighbours, so no edge at a bar can beat that bar's second
    largest angle (bounds the minimum), and a bar's two edges sum to at most its two largest
    angles (half of that, summed over bars, bounds the total).
    """
    masked = angles_deg.copy()
    np.fill_diagonal(masked, -np.inf)
    top2 = -np.sort(-masked, axis=1)[:, :2]  # [B, 2] the two largest angles at each bar
    min_bound = float(top2[:, 1].min())
    mean_bound = float(top2.sum() / 2.0 / angles_deg.shape[0])
    return min_bound, mean_bound


def _farthest_neighbour_tour(weights: np.ndarray, start: int) -> np.ndarray:
    n = weights.shape[0]
    tour = [start]
    free = np.ones(n, bool)
    free[start] = False
    for _ in range(n - 1):
        row = np.where(free, weights[tour[-1]], -np.inf)
        nxt = int(np.argmax(row))
        tour.append(nxt)
        free[nxt] = False
    return np.array(tour)


def _two_opt(tour: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, bool]:
    """One pass of best-improvement 2-opt per position (maximising the cycle's weight)."""
    n = len(tour)
    improved = False
    for i in range(n - 1):
        a, b = tour[i], tour[i + 1]
        # Candidate second edges (c, d) = (tour[j], tour[j+1]) for j in i+2 .. n-1 (cyclic).
        js = np.arange(i + 2, n if i > 0 else n - 1)
        if js.size == 0:
            continue
        c = tour[js]
        d = tour[(js + 1) % n]
        gains = weights[a, c] + weights[b, d] - weights[a, b] - weights[c, d]  # [len(js)]
        k = int(np.argmax(gains))
        if gains[k] > 1e-9:
            j = int(js[k])
            tour[i + 1:j + 1] = tour[i + 1:j + 1][::-1].copy()
            improved = True
    return tour, improved


def _or_opt(tour: np.ndarray, weights: np.ndarray, max_segment: int = 3) -> tuple[np.ndarray, bool]:
    """One pass of or-opt: move a segment of 1..max_segment bars elsewhere, maybe reversed."""
    n = len(tour)
    improved = False
    for length in range(1, max_segment + 1):
        for start in range(n):
            if n - length < 3:
                break
            idx = [(start + k) % n for k in range(length)]
            seg = tour[idx]
            prev, nxt = tour[(start - 1) % n], tour[(start + length) % n]
            removal_gain = weights[prev, nxt] - weights[prev, seg[0]] - weights[seg[-1], nxt]
            rest = np.array([tour[(start + length + k) % n] for k in range(n - length)])  # cyclic, starts at nxt
            u, v = rest, np.roll(rest, -1)  # insert between u and v
            # Inserting between prev and nxt (the last pair of rest) restores the tour: skip it.
            fwd = weights[u, seg[0]] + weights[seg[-1], v] - weights[u, v]
            rev = weights[u, seg[-1]] + weights[seg[0], v] - weights[u, v]
            fwd[-1] = rev[-1] = -np.inf
            best_fwd, best_rev = int(np.argmax(fwd)), int(np.argmax(rev))
            gain_fwd, gain_rev = removal_gain + fwd[best_fwd], removal_gain + rev[best_rev]
            if max(gain_fwd, gain_rev) > 1e-9:
                pos, piece = (best_fwd, seg) if gain_fwd >= gain_rev else (best_rev, seg[::-1])
                tour = np.concatenate([rest[:pos + 1], piece, rest[pos + 1:]])
                improved = True
    return tour, improved


def _local_search(tour: np.ndarray, weights: np.ndarray, max_passes: int = 200) -> np.ndarray:
    tour = tour.copy()
    for _ in range(max_passes):
        tour, a = _two_opt(tour, weights)
        tour, b = _or_opt(tour, weights)
        if not (a or b):
            break
    return tour


def _best_cycle(weights: np.ndarray, rng: np.random.Generator, restarts: int) -> np.ndarray:
    """The best cycle found by local search from farthest-neighbour and random starts."""
    n = weights.shape[0]
    starts = [_farthest_neighbour_tour(weights, s) for s in range(min(n, 4))]
    starts += [rng.permutation(n) for _ in range(restarts)]
    best, best_score = None, -np.inf
    for start in starts:
        tour = _local_search(start, weights)
        score = float(cycle_angles_deg(weights, tour).sum())
        if score > best_score + 1e-9:
            best, best_score = tour, score
    return best


def _max_min_cycle(angles_deg: np.ndarray, rng: np.random.Generator, restarts: int) -> tuple[float, np.ndarray]:
    """Largest threshold for which a cycle with every edge at least that angle is found.

    Binary search over the distinct angles up to the analytic bound; feasibility of a
    threshold is a local search minimising the number of edges below it.
    """
    bound, _ = olat_upper_bounds(angles_deg)
    n = angles_deg.shape[0]
    upper = angles_deg[np.triu_indices(n, 1)]
    candidates = np.unique(upper[upper <= bound + 1e-9])
    lo, hi = 0, len(candidates) - 1
    best_tau, best_tour = float(candidates[0]), None
    while lo <= hi:
        mid = (lo + hi) // 2
        tau = float(candidates[mid])
        # Weight: 0 for an edge that reaches tau, -1 for one below it, plus a tiny share of the
        # angle so the search prefers wide edges among equally feasible ones.
        weights = np.where(angles_deg >= tau - 1e-9, 0.0, -1.0) + 1e-4 * angles_deg / 180.0
        tour = _best_cycle(weights, rng, restarts)
        if cycle_angles_deg(angles_deg, tour).min() >= tau - 1e-9:
            best_tau, best_tour = tau, tour
            lo = mid + 1
        else:
            hi = mid - 1
    if best_tour is None:
        best_tour = _best_cycle(angles_deg, rng, restarts)
        best_tau = float(cycle_angles_deg(angles_deg, best_tour).min())
    return best_tau, best_tour


def _cycle_components(n: int, edges: list[tuple[int, int]]) -> list[list[int]]:
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for i, j in edges:
        neighbours[i].append(j)
        neighbours[j].append(i)
    seen = np.zeros(n, bool)
    components = []
    for start in range(n):
        if seen[start]:
            continue
        stack, component = [start], []
        seen[start] = True
        while stack:
            u = stack.pop()
            component.append(u)
            for v in neighbours[u]:
                if not seen[v]:
                    seen[v] = True
                    stack.append(v)
        components.append(component)
    return components


def _edges_to_tour(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for i, j in edges:
        neighbours[i].append(j)
        neighbours[j].append(i)
    tour, previous = [0], -1
    while len(tour) < n:
        current = tour[-1]
        nxt = neighbours[current][0] if neighbours[current][0] != previous else neighbours[current][1]
        previous = current
        tour.append(nxt)
    return np.array(tour)


class SolverLimitReached(Exception):
    """The integer program hit its time or cut limit without a proven answer."""


def exact_max_cycle(weights: np.ndarray, allowed: np.ndarray, time_limit_s: float = 10.0,
                    max_rounds: int = 200) -> np.ndarray | None:
    """The Hamiltonian cycle of largest total weight using only ``allowed`` edges, or None if none exists.

    Integer program: one binary per allowed edge, every bar on exactly two edges, and for every
    subtour of the current solution a cut "at least two edges leave this set"; re-solved until
    the solution is a single cycle. Raises ``SolverLimitReached`` on hitting the limits.

    Args:
        weights: [B, B] symmetric edge weights (maximised).
        allowed: [B, B] boolean mask of usable edges.
        time_limit_s: total budget over all rounds.
        max_rounds: rounds of subtour cuts.
    """
    n = weights.shape[0]
    rows, cols = np.triu_indices(n, 1)
    keep = allowed[rows, cols]
    rows, cols = rows[keep], cols[keep]
    m = len(rows)
    if m < n:
        return None
    edge_index = np.arange(m)
    degree = csr_matrix((np.ones(2 * m), (np.concatenate([rows, cols]), np.concatenate([edge_index, edge_index]))),
                        shape=(n, m))
    constraints = [LinearConstraint(degree, 2.0, 2.0)]
    cost = -weights[rows, cols]  # milp minimises
    deadline = time.perf_counter() + time_limit_s
    for _ in range(max_rounds):
        remaining = deadline - time.perf_counter()
        if remaining <= 0:
            raise SolverLimitReached("time limit")
        result = milp(cost, constraints=constraints, integrality=np.ones(m), bounds=Bounds(0, 1),
                      options={"time_limit": remaining})
        if result.status == 2:
            return None  # infeasible: no cycle uses only allowed edges
        if result.status != 0 or result.x is None:
            raise SolverLimitReached(result.message)
        chosen = result.x > 0.5
        edges = list(zip(rows[chosen].tolist(), cols[chosen].tolist()))
        components = _cycle_components(n, edges)
        if len(components) == 1:
            return _edges_to_tour(n, edges)
        for component in components:
            inside = np.zeros(n, bool)
            inside[component] = True
            crossing = (inside[rows] != inside[cols]).astype(float)  # [m]
            constraints.append(LinearConstraint(crossing[None, :], 2.0, np.inf))
    raise SolverLimitReached(f"no single cycle after {max_rounds} rounds of cuts")


def _exact_order(angles_deg: np.ndarray, time_limit_s: float) -> np.ndarray:
    """Max-min then max-sum cycle, exactly (raises ``SolverLimitReached`` on the limits)."""
    bound, _ = olat_upper_bounds(angles_deg)
    n = angles_deg.shape[0]
    upper = angles_deg[np.triu_indices(n, 1)]
    candidates = np.unique(upper[upper <= bound + 1e-9])  # ascending; the bound itself is one of them
    deadline = time.perf_counter() + time_limit_s

    def best_at(tau: float) -> np.ndarray | None:
        remaining = deadline - time.perf_counter()
        if remaining <= 0:
            raise SolverLimitReached("time limit")
        return exact_max_cycle(angles_deg, angles_deg >= tau - 1e-9, remaining)

    # The bound is usually reachable: try it first, then bisect below it.
    tour = best_at(float(candidates[-1]))
    if tour is not None:
        return tour
    lo, hi, best = 0, len(candidates) - 2, None
    while lo <= hi:
        mid = (lo + hi) // 2
        found = best_at(float(candidates[mid]))
        if found is not None:
            best, lo = found, mid + 1
        else:
            hi = mid - 1
    if best is None:
        raise SolverLimitReached("no cycle found at any threshold")
    return best


def _local_order(angles_deg: np.ndarray, seed: int, restarts: int) -> np.ndarray:
    """Max-min then max-sum cycle by local search (no optimality guarantee)."""
    n = angles_deg.shape[0]
    rng = np.random.default_rng(seed)
    tau, tour = _max_min_cycle(angles_deg, rng, restarts)
    # Keep every edge at or above tau: edges below it pay far more than any sum of angles gains.
    penalty = 1e3 * 180.0 * n
    weights = np.where(angles_deg >= tau - 1e-9, angles_deg, angles_deg - penalty)
    candidate = _local_search(_best_cycle(weights, rng, restarts), weights)
    seeded = _local_search(tour, weights)
    for other in (candidate, seeded):
        if cycle_angles_deg(weights, other).sum() > cycle_angles_deg(weights, tour).sum() + 1e-9:
            tour = other
    return tour


def solve_olat_order(angles_deg: np.ndarray, seed: int = 0, restarts: int = 8, method: str = "exact",
                     time_limit_s: float = 20.0) -> OrderResult:
    """The cyclic order maximising the minimum, then the sum, of consecutive angles.

    Args:
        angles_deg: [B, B] symmetric pairwise angles between bar directions, degrees.
        seed: seeds the local search's random restarts (results are deterministic).
        restarts: random starts per local search, besides the farthest-neighbour ones.
        method: "exact" (integer program; falls back to "local" if it hits ``time_limit_s``)
            or "local" (local search only).
        time_limit_s: budget of the exact method.

    Returns:
        The order as bar indices, rotated to start at index 0, in the direction whose
        second bar has the lower index (so equal cycles give equal orders).
    """
    angles_deg = np.asarray(angles_deg, float)
    n = angles_deg.shape[0]
    if angles_deg.shape != (n, n) or n < 3:
        raise ValueError(f"need a square angle matrix of at least 3 bars, got shape {angles_deg.shape}")
    if method not in ("exact", "local"):
        raise ValueError(f"method must be 'exact' or 'local', got {method!r}")
    used = method
    tour = None
    if method == "exact":
        try:
            tour = _exact_order(angles_deg, time_limit_s)
        except SolverLimitReached:
            used = "local"
    if tour is None:
        tour = _local_order(angles_deg, seed, restarts)
    tour = np.roll(tour, -int(np.argmin(tour)))
    if tour[-1] < tour[1]:
        tour = np.concatenate([tour[:1], tour[1:][::-1]])
    angles = cycle_angles_deg(angles_deg, tour)
    return OrderResult(tuple(int(b) for b in tour), angles, float(angles.mean()), float(angles.min()), used)
