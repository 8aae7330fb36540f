"""The accuracy targets the issues set, checked in the report.

Each target names a stage, a metric key of that stage's merged metrics (its own and its
evaluation's), a comparison, and either a number or another key of the same stage
(``"baseline_mae_olat"``: ours must beat the baseline).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping


@dataclass(frozen=True)
class Target:
    """One acceptance figure.

    Attributes:
        stage: stage whose merged metrics hold ``key``.
        key: metric key (units in the name).
        op: ``"<="`` or ``">="``.
        bound: a number, or the name of another metric of the same stage to compare against.
        what: a few words a supervisor reads in the table.
    """

    stage: str
    key: str
    op: str
    bound: float | str
    what: str

    def check(self, metrics: Mapping[str, float]) -> tuple[float | None, float | None, bool | None]:
        """(value, bound value, passed); ``None`` where the metric has not been measured."""
        value = metrics.get(self.key)
        bound = metrics.get(self.bound) if isinstance(self.bound, str) else self.bound
        if value is None or bound is None:
            return value, bound, None
        passed = value <= bound if self.op == "<=" else value >= bound
        return float(value), float(bound), bool(passed)


TARGETS: tuple[Target, ...] = (
    Target("calibrate", "reproj_rms_px", "<=", 0.3, "reprojection RMS"),
    Target("calibrate", "focal_err_pct_max", "<=", 0.2, "focal length error"),
    Target("calibrate", "center_err_mm_max", "<=", 1.0, "camera centre error"),
    Target("calibrate", "rotation_err_deg_max", "<=", 0.05, "camera rotation error"),
    Target("lightcal", "bar_center_err_mm_max", "<=", 10.0, "LED bar centre error"),
    Target("track", "vertex_err_mm_mean_full", "<=", 1.0, "vertex error, full-on frames"),
    Target("track", "vertex_err_mm_mean_olat", "<=", 1.5, "vertex error, OLAT frames (interpolated)"),
    Target("track", "rotation_err_deg_mean", "<=", 0.2, "head rotation error"),
    Target("matte", "mae_olat", "<=", 0.01, "matte MAE on OLAT frames"),
    Target("matte", "mae_full", "<=", "baseline_mae_full", "matte MAE (full-on) vs classical baseline"),
    Target("matte", "mae_olat", "<=", "baseline_mae_olat", "matte MAE (OLAT) vs classical baseline"),
    Target("matte", "grad_err_olat", "<=", "baseline_grad_err_olat", "matte gradient error vs baseline"),
    Target("train", "ours_novel_light_psnr", ">=", 30.0, "held-out light PSNR (dB)"),
    Target("train", "ours_novel_light_psnr", ">=", "travatar_novel_light_psnr", "novel light: ours vs TRAvatar*"),
    Target("train", "ours_novel_perf_psnr", ">=", "travatar_novel_perf_psnr", "novel performance: ours vs TRAvatar*"),
    Target("train", "ours_novel_both_psnr", ">=", "travatar_novel_both_psnr", "both held out: ours vs TRAvatar*"),
    Target("relight", "envmap_seconds_per_frame", "<=", "naive_envmap_seconds_per_frame",
           "voxel-space envmap sum vs naive per-light raymarch"),
    Target("relight", "bake_speedup_vs_sum", ">=", 50.0, "envmap frame from the bake vs the voxel-space sum (x)"),
    Target("relight", "bake_psnr_vs_sum_db", ">=", 40.0, "bake frame vs voxel-space sum, same frame (dB)"),
)
