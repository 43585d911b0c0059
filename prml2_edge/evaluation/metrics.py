"""Metrics of the paper's Tables 1-3 and Fig. 4 from :class:`~prml2_edge.evaluation.protocol.WindowResult`s."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import coverage_pct
from prml2_edge.evaluation.protocol import WindowResult, WindowTask


def _nan_to_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def z_rmse(results: Sequence[WindowResult], tasks: Sequence[WindowTask]) -> tuple[dict[str, float | None], int]:
    """Per-component RMSE of the consumed z [SI] (Table 1; None where the model has no estimate) and the
    number of samples with an estimate."""
    gt = {t.key: t.z_gt for t in tasks}
    err = np.concatenate([r.z - gt[r.task_key] for r in results], axis=0)
    ok = np.isfinite(err)
    out = {}
    for i, name in enumerate(schema.STATE_NAMES):
        out[name] = _nan_to_none(float(np.sqrt(np.mean(err[ok[:, i], i] ** 2)))) if ok[:, i].any() else None
    return out, int(ok.any(axis=1).sum())


def dr_summary(results: Sequence[WindowResult]) -> dict[str, float | int | None]:
    """Mean and std over windows of the 60 s position RMSE and ME [m], drift [%] and final heading error [deg]."""
    if not results:
        return {"n_windows": 0}
    rmse = np.array([r.rmse_m for r in results])
    me = np.array([r.max_error_m for r in results])
    drift = np.array([r.drift_pct for r in results])
    yaw_final = np.degrees(np.abs([r.yaw_error_rad[-1] for r in results]))
    fired = sum(r.guard_fired for r in results)
    used = sum(r.model_steps for r in results)
    return {
        "n_windows": len(results),
        "rmse_mean_m": float(rmse.mean()), "rmse_std_m": float(rmse.std()),
        "me_mean_m": float(me.mean()), "me_std_m": float(me.std()),
        "drift_mean_pct": _nan_to_none(float(np.nanmean(drift))) if np.isfinite(drift).any() else None,
        "drift_std_pct": _nan_to_none(float(np.nanstd(drift))) if np.isfinite(drift).any() else None,
        "final_yaw_error_mean_deg": float(yaw_final.mean()),
        "distance_mean_m": float(np.mean([r.distance_m for r in results])),
        "guard_fire_rate": float(fired / used) if used else 0.0,
        **coverage(results),
    }


def coverage(results: Sequence[WindowResult]) -> dict[str, float]:
    """Share of steps [%] whose 2D position error lies inside the reported 1/2/3-sigma ellipses
    (:func:`prml2_edge.ekf.numpy_ekf.coverage_pct`); the start row of each window (error 0) is left out."""
    m2 = [r.mahal2[1:] for r in results if r.mahal2 is not None]
    return coverage_pct(np.concatenate(m2)) if m2 else {}
