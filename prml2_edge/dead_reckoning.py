"""Dead-reckoning error metrics: the one home of RMSE, maximum error, drift and path length.

Used by ``prml2 evaluate`` (:class:`prml2_edge.evaluation.protocol.WindowResult`), training
validation (:class:`prml2_edge.training.validate.DrWindow`) and the demo / ``prml2 replay --truth``
(:func:`trajectory_metrics`). NumPy only (the edge runtime imports it).
"""

from __future__ import annotations

import math

import numpy as np


def path_length_m(xy: np.ndarray) -> float:
    """Length [m] of a planar path (n, 2)."""
    return float(np.sum(np.hypot(*np.diff(np.asarray(xy)[:, :2], axis=0).T)))


def drift_pct(final_error_m: float, distance_m: float) -> float:
    """Final position error over the distance travelled [%] (NaN below 1 m travelled)."""
    return float(100.0 * final_error_m / distance_m) if distance_m > 1.0 else math.nan


class DeadReckoningErrors:
    """Mixin for a window with per-step position errors ``pos_error_m`` (n,) [m] and ``distance_m`` [m]."""

    pos_error_m: np.ndarray
    distance_m: float

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.pos_error_m**2)))

    @property
    def max_error_m(self) -> float:
        return float(np.max(self.pos_error_m))

    @property
    def drift_pct(self) -> float:
        """Final position error over the distance travelled [%] (NaN below 1 m travelled)."""
        return drift_pct(float(self.pos_error_m[-1]), self.distance_m)


def trajectory_metrics(t_s: np.ndarray, est_xy: np.ndarray, gt_xy: np.ndarray, outage_start_s: float,
                       horizon_s: float = 60.0) -> dict:
    """Position error statistics over a GNSS outage.

    Returns ``rmse_m``, ``max_m``, ``final_m`` over the whole outage, ``distance_m`` travelled in it,
    ``drift_pct`` (final error / distance), and the same over the first ``horizon_s`` of the
    outage (``*_60s``: the paper's 60 s dead-reckoning window).
    """
    err = np.hypot(est_xy[:, 0] - gt_xy[:, 0], est_xy[:, 1] - gt_xy[:, 1])
    out = {}
    for suffix, mask in (("", t_s >= outage_start_s),
                         ("_60s", (t_s >= outage_start_s) & (t_s <= outage_start_s + horizon_s + 1e-9))):
        e = err[mask]
        if e.size < 2:
            continue
        dist = path_length_m(gt_xy[mask])
        out[f"rmse_m{suffix}"] = float(np.sqrt(np.mean(e ** 2)))
        out[f"max_m{suffix}"] = float(np.max(e))
        out[f"final_m{suffix}"] = float(e[-1])
        out[f"distance_m{suffix}"] = dist
        out[f"drift_pct{suffix}"] = drift_pct(float(e[-1]), dist)
        out[f"duration_s{suffix}"] = float(t_s[mask][-1] - t_s[mask][0])
    out["rmse_m_gnss"] = float(np.sqrt(np.mean(err[t_s < outage_start_s] ** 2))) if np.any(t_s < outage_start_s) \
        else float("nan")
    return out
