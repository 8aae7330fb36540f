"""Stage ``sequence``: the OLAT order of the rig's bars, the capture pattern and frame schedule,
and the LED controller program.

Output:
    sequence.json  {"olat_order": [bar ids], "pattern": ["F", 12, 3, "F", ...] (one cycle),
                    "fps", "cycles", "frames", "duration_s", "olat_per_full_on",
                    "program": {"steps": pattern, "repeat": cycles}, "program_crc32",
                    "head_center_m", "bars": [{"id", "azimuth_deg", "elevation_deg"}],
                    "schedule": [{"frame", "time_s", "light"}]}
    order.png      the order drawn on a sphere projection
    metrics.json   (written by the runner) angles of consecutive OLAT lights
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
from pydantic import Field

from hardware.led.protocol import program_crc32
from pipeline.errors import ConfigError
from pipeline.stage import Stage, StageContext, StageParams
from scene.rig import RigConfig, default_rig
from stages.sequence.output import SequenceOutput
from stages.sequence.order import (angle_matrix_deg, bar_directions, cycle_angles_deg, olat_upper_bounds,
                                   random_baseline_mean_deg, solve_olat_order)
from stages.sequence.plot import azimuth_elevation_deg, plot_order
from stages.sequence.schedule import build_pattern, build_schedule, olat_pairs_across_full_on


class SequenceParams(StageParams):
    """Params of the sequence stage."""

    rig: RigConfig = Field(default_factory=default_rig,
                           description="The studio rig (injected from configs/rig.yaml); bar positions and head centre.")
    fps: float | None = Field(None, gt=0, description="Capture frame rate in frames per second; None uses the rig's fps.")
    cycles: int = Field(4, ge=1, description="Repetitions of the pattern (one cycle = every bar once, with F frames).")
    olat_per_full_on: int = Field(2, ge=1, description="OLAT frames after each full-on (F) frame in the pattern.")
    seed: int = Field(0, description="Seed of the order search's random restarts and of the random baseline.")
    restarts: int = Field(8, ge=0, description="Random restarts of each local search (besides greedy starts).")
    random_baseline_samples: int = Field(256, ge=1, description="Random orders averaged for the random baseline.")
    method: Literal["exact", "local"] = Field(
        "exact", description="Order solver: 'exact' integer program (falls back to 'local' at its time limit) "
                             "or 'local' search (2-opt / or-opt).")
    time_limit_s: float = Field(20.0, gt=0, description="Time budget of the exact solver, seconds.")


def run(ctx: StageContext) -> None:
    """Solve the order, build the pattern and schedule, write sequence.json and order.png."""
    params: SequenceParams = ctx.params
    rig = params.rig
    if len(rig.bars) < 3:
        raise ConfigError(f"configs/rig.yaml: 'bars' has {len(rig.bars)} bars; the OLAT order needs at least 3")
    fps = params.fps if params.fps is not None else rig.fps
    bar_ids = [bar.id for bar in rig.bars]
    bar_centres_world = np.array([bar.center_m for bar in rig.bars], float)  # [B, 3]
    head_centre_world = np.asarray(rig.head_center_m, float)  # [3]
    try:
        directions = bar_directions(bar_centres_world, head_centre_world)  # [B, 3]
    except ValueError as err:
        raise ConfigError(f"configs/rig.yaml: {err}; move the bar or 'head_center_m'") from err
    angles_deg = angle_matrix_deg(directions)  # [B, B]

    start = time.perf_counter()
    result = solve_olat_order(angles_deg, seed=params.seed, restarts=params.restarts, method=params.method,
                              time_limit_s=params.time_limit_s)
    if result.method != params.method:
        ctx.log.warning("the exact order solver hit its %.0f s limit; using the local search's order "
                        "(raise sequence.time_limit_s for a proven optimum)", params.time_limit_s)
    solve_s = time.perf_counter() - start
    olat_order = [bar_ids[i] for i in result.olat_order]
    ctx.log.info("OLAT order of %d bars (%s): mean %.1f deg, min %.1f deg between consecutive lights (%.2f s)",
                 len(olat_order), result.method, result.mean_deg, result.min_deg, solve_s)

    pattern = build_pattern(olat_order, params.olat_per_full_on)
    schedule = build_schedule(pattern, params.cycles, fps)
    across = olat_pairs_across_full_on(pattern)
    naive = cycle_angles_deg(angles_deg, np.arange(len(bar_ids)))  # [B] bar-id order
    min_bound, mean_bound = olat_upper_bounds(angles_deg)
    azimuth, elevation = azimuth_elevation_deg(directions)
    crc = program_crc32(pattern, params.cycles)

    sequence = {
        "olat_order": olat_order,
        "pattern": pattern,
        "fps": fps,
        "cycles": params.cycles,
        "frames": len(schedule),
        "duration_s": len(schedule) / fps,
        "olat_per_full_on": params.olat_per_full_on,
        "program": {"steps": pattern, "repeat": params.cycles},
        "program_crc32": crc,
        "head_center_m": list(rig.head_center_m),
        "bars": [{"id": b, "azimuth_deg": round(float(a), 3), "elevation_deg": round(float(e), 3)}
                 for b, a, e in zip(bar_ids, azimuth, elevation)],
        "schedule": schedule,
    }
    out = SequenceOutput(ctx.out)
    out.write_sequence(sequence)
    plot_order(out.order_png_path, directions, result.olat_order, bar_ids, across,
               f"OLAT order: mean {result.mean_deg:.1f} deg, min {result.min_deg:.1f} deg "
               f"(naive {naive.mean():.1f}, bound {mean_bound:.1f}); dashed = across an F frame")

    angles = result.angles_deg  # [B] consecutive pairs in capture order, cyclic
    across_mask = np.array(across, bool)
    ctx.metrics.update({
        "olat_angle_mean_deg": result.mean_deg,
        "olat_angle_min_deg": result.min_deg,
        "naive_olat_angle_mean_deg": float(naive.mean()),
        "naive_olat_angle_min_deg": float(naive.min()),
        "random_olat_angle_mean_deg": random_baseline_mean_deg(angles_deg, params.seed, params.random_baseline_samples),
        "olat_angle_mean_upper_bound_deg": mean_bound,
        "olat_angle_min_upper_bound_deg": min_bound,
        "olat_angle_mean_adjacent_deg": float(angles[~across_mask].mean()) if (~across_mask).any() else 0.0,
        "olat_angle_mean_across_full_on_deg": float(angles[across_mask].mean()) if across_mask.any() else 0.0,
        "bars": len(bar_ids),
        "frames_per_cycle": len(pattern),
        "frames": len(schedule),
        "duration_s": len(schedule) / fps,
        "solve_seconds": solve_s,
        "solver_exact": 1.0 if result.method == "exact" else 0.0,
    })


STAGE = Stage(
    name="sequence",
    inputs=(),
    params=SequenceParams,
    run=run,
    doc="OLAT order of the LED bars (max dissimilarity), the capture pattern, schedule and controller program.",
)
