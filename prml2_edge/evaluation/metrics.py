"""Metrics of the paper's Tables 1-3 and Fig. 4 from :class:`~prml2_edge.evaluation.protocol.WindowResult`s."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from prml2_edge import schema
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
    }


def drift_curves(results: Sequence[WindowResult]) -> dict[str, np.ndarray]:
    """Mean and std over windows of the position error [m] and absolute heading error [deg] per step (Fig. 4)."""
    n = min(len(r.pos_error_m) for r in results)
    pos = np.stack([r.pos_error_m[:n] for r in results])
    yaw = np.degrees(np.abs(np.stack([r.yaw_error_rad[:n] for r in results])))
    return {"t_s": np.arange(n) * schema.DT_S, "pos_mean_m": pos.mean(0), "pos_std_m": pos.std(0),
            "yaw_mean_deg": yaw.mean(0), "yaw_std_deg": yaw.std(0)}


def z_errors(results: Sequence[WindowResult], tasks: Sequence[WindowTask]) -> np.ndarray:
    """(M, 5) z errors [SI] over all consumed samples (NaN where the model has no estimate)."""
    gt = {t.key: t.z_gt for t in tasks}
    err = np.concatenate([r.z - gt[r.task_key] for r in results], axis=0)
    return err[np.isfinite(err).any(axis=1)]
