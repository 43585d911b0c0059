"""Tuning on the validation split: the OSD baseline's noise (:func:`tune_osd`) and the "uncertainty off"
ablation's constant variances (:func:`tune_constant_variance`), each from runs of :func:`~.protocol.run_all`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from prml2_edge.evaluation.protocol import ModelSpec, WindowResult, WindowTask, run_all
from prml2_edge.schema import Z

OSD_Q_SCALES = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)  # process-noise scales tried first for the OSD baseline on val
MAX_GRID_EXTENSIONS = 8  # a grid whose minimum sits on an edge is extended by its end ratio up to this many times


def z_residual_var(results: Sequence[WindowResult], tasks: Sequence[WindowTask]) -> np.ndarray:
    """Mean squared error (5,) [SI^2] of the consumed z against ground truth (1.0 where unavailable)."""
    gt = {t.key: t.z_gt for t in tasks}
    err = np.concatenate([r.z - gt[r.task_key] for r in results], axis=0)
    ok = np.isfinite(err)
    sq = np.where(ok, err, 0.0) ** 2
    count = ok.sum(axis=0)
    var = np.where(count > 0, sq.sum(axis=0) / np.maximum(count, 1), 1.0)
    return np.maximum(var, 1e-8)


@dataclass
class Tuning:
    """What was tuned on the validation split, for the report."""

    notes: dict[str, dict] = field(default_factory=dict)


def tune_osd(spec: ModelSpec, val_tasks: Sequence[WindowTask], stride: int = 1, jobs: int = 1,
             q_scales: Sequence[float] = OSD_Q_SCALES, tuning: Tuning | None = None,
             on_done: Callable[[WindowResult], None] | None = None) -> ModelSpec:
    """OSD baseline: measurement variances = its z residual MSE on val (v_y: the mean square of the true
    v_y, its pseudo-measurement being 0), then the ``Q`` scale with the lowest mean 60 s position RMSE on val.

    An under-tuned baseline flatters the models: while the best scale is at an end of the grid, the
    grid is extended past that end (by the ratio of its last two points) until the minimum lies
    inside it, at most :data:`MAX_GRID_EXTENSIONS` times; the notes say whether it does.
    """
    first = run_all([replace(spec, const_var=None, q_scale=1.0)], val_tasks, stride, jobs, on_done)[spec.name]
    var = z_residual_var(first, val_tasks)
    # v_y: the kinematic model's pseudo-measurement 0, so its variance is the mean square of the true v_y
    var[Z.V_Y] = max(float(np.mean(np.concatenate([t.z_gt[:, Z.V_Y] for t in val_tasks]) ** 2)), 1e-8)
    def score(q: float) -> float:
        res = run_all([replace(spec, const_var=tuple(var), q_scale=q)], val_tasks, stride, jobs, on_done)[spec.name]
        return float(np.mean([r.rmse_m for r in res]))

    scores = {q: score(q) for q in q_scales}
    best, inside = _extend_grid(scores, score)
    if tuning is not None:
        tuning.notes[spec.name] = {"measurement_var": var.tolist(), "q_scale": best, "minimum_inside_grid": inside,
                                   "val_rmse_by_q_scale_m": {str(k): v for k, v in sorted(scores.items())}}
    return replace(spec, const_var=tuple(float(v) for v in var), q_scale=best)


def _extend_grid(scores: dict[float, float], score: Callable[[float], float]) -> tuple[float, bool]:
    """Extend a positive log-spaced grid ``scores`` (value -> loss, filled in place) past the end where its
    minimum sits until the minimum is inside; returns the best value and whether it is inside."""
    for _ in range(MAX_GRID_EXTENSIONS + 1):
        grid = sorted(scores)
        best = min(scores, key=scores.__getitem__)
        if len(grid) < 3 or grid[0] < best < grid[-1]:
            return best, len(grid) >= 3
        lo = best == grid[0]
        new = grid[0] * grid[0] / grid[1] if lo else grid[-1] * grid[-1] / grid[-2]
        scores[new] = score(new)
    best = min(scores, key=scores.__getitem__)
    return best, sorted(scores)[0] < best < sorted(scores)[-1]


def tune_constant_variance(spec: ModelSpec, val_tasks: Sequence[WindowTask], stride: int = 1, jobs: int = 1,
                           tuning: Tuning | None = None,
                           on_done: Callable[[WindowResult], None] | None = None) -> tuple[float, ...]:
    """Ablation "uncertainty off": constant variances = the model's guarded z residual MSE on val."""
    res = run_all([replace(spec, const_var=None)], val_tasks, stride, jobs, on_done)[spec.name]
    var = z_residual_var(res, val_tasks)
    if tuning is not None:
        tuning.notes[f"{spec.name} constant variance"] = {
            "measurement_var": var.tolist(), "val_rmse_m": float(np.mean([r.rmse_m for r in res]))}
    return tuple(float(v) for v in var)
