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


def paired_comparison(reference: Sequence[WindowResult], other: Sequence[WindowResult], *, n_boot: int = 2000,
                      seed: int = 0) -> dict[str, float | int | None]:
    """How ``reference`` compares with ``other`` on the windows both ran (paired by window).

    With a few dozen 60 s windows the spread over windows (± several metres) is as large as the gaps
    between good models, so a difference of means alone does not say which model is better. Returns
    the mean of ``rmse(other) - rmse(reference)`` per window [m] with a percentile-bootstrap 95 %
    interval (``n_boot`` resamples of the windows, fixed ``seed``), the ratio of mean RMSEs
    (reference / other) with its interval, and the share of windows where the reference has the lower
    RMSE. A positive difference whose interval excludes 0: the reference is better beyond the
    window-to-window spread.
    """
    ref = {r.task_key: r.rmse_m for r in reference}
    oth = {r.task_key: r.rmse_m for r in other}
    keys = sorted(set(ref) & set(oth))
    if not keys:
        return {"n_windows": 0}
    a = np.array([ref[k] for k in keys])
    b = np.array([oth[k] for k in keys])
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(keys), size=(n_boot, len(keys)))
    diff_boot = (b[idx] - a[idx]).mean(axis=1)
    ratio_boot = a[idx].mean(axis=1) / np.maximum(b[idx].mean(axis=1), 1e-12)
    lo, hi = np.percentile(diff_boot, [2.5, 97.5])
    rlo, rhi = np.percentile(ratio_boot, [2.5, 97.5])
    return {
        "n_windows": len(keys),
        "rmse_diff_mean_m": float((b - a).mean()), "rmse_diff_ci95_m": [float(lo), float(hi)],
        "rmse_ratio": float(a.mean() / max(b.mean(), 1e-12)), "rmse_ratio_ci95": [float(rlo), float(rhi)],
        "reference_wins": float(np.mean(a < b)),
    }


def coverage_text(cov: dict | None) -> str:
    """A :func:`coverage` result as ``92 / 95`` (2σ / 3σ %); ``–`` for none."""
    if not cov or "coverage_2sigma_pct" not in cov:
        return "–"
    return f"{cov['coverage_2sigma_pct']:.0f} / {cov['coverage_3sigma_pct']:.0f}"


def paired_text(p: dict | None) -> str:
    """A :func:`paired_comparison` result as ``+0.12 [-0.30, +0.55]`` (mean difference and its 95 % interval, m);
    ``–`` for none."""
    if p is None:
        return "–"
    lo, hi = p["rmse_diff_ci95_m"]
    return f"{p['rmse_diff_mean_m']:+.2f} [{lo:+.2f}, {hi:+.2f}]"
