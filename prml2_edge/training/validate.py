"""Training-side evaluation: streaming z estimates, z RMSE and 60 s dead reckoning (NumPy EKF).

Streaming inference (method.md): a new window every ``stride`` samples; each window's decoder
outputs cover its last L - H steps, and at every 50 Hz step the EKF consumes the newest output
available at that time. With ``stride = 1`` that is the last decoder output of the window
ending at that step. With ``stride > 1`` the steps between two windows are fed the newest
window's last output (held), which is what a live system without extra latency can do.
The first L - 1 samples of a drive have no estimate (NaN).

Dead reckoning (method.md "Evaluation protocol"): non-overlapping 60 s windows, each starting
from the true pose with the ground-truth dynamic state, the NumPy EKF fed with the guarded
streaming estimates at every step; position error per step against ground truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.dead_reckoning import DeadReckoningErrors, path_length_m
from prml2_edge.ekf.numpy_ekf import Ekf, default_initial_covariance, default_process_noise
from prml2_edge.evaluation.osd import drive_bias, osd_baseline_z
from prml2_edge.guard import physics_guard
from prml2_edge.progress import Progress
from prml2_edge.training.model import Prml2Model

DR_WINDOW_S = 60.0


@dataclass
class StreamOutput:
    """Per-sample streaming estimates of one drive: ``mean``/``var`` (N, 5) [SI], NaN before L - 1."""

    mean: np.ndarray
    var: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: samples that have an estimate."""
        return np.all(np.isfinite(self.mean), axis=1)


def sliding_windows(onboard: np.ndarray, window_len: int) -> np.ndarray:
    """Read-only view (N - L + 1, L, 9) of every window of ``onboard`` (N, 9); window k ends at k + L - 1."""
    onboard = np.ascontiguousarray(onboard)
    return np.lib.stride_tricks.sliding_window_view(onboard, window_len, axis=0).transpose(0, 2, 1)


def stream_predict(model: Prml2Model, onboard: np.ndarray, *, stride: int = 1, batch_size: int = 512,
                   progress: Progress | None = None) -> StreamOutput:
    """Streaming model estimates for a drive (before the physics guard).

    Parameters
    ----------
    model
        The PRML2 model (put in eval mode here).
    onboard
        (N, 9) raw onboard signals [SI, canonical order].
    stride
        Samples between windows (see the module docstring).
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    L = model.cfg.window_len
    n = len(onboard)
    mean = np.full((n, schema.NUM_STATES), np.nan)
    var = np.full((n, schema.NUM_STATES), np.nan)
    if n < L:
        return StreamOutput(mean, var)
    views = sliding_windows(np.asarray(onboard, dtype=np.float32), L)  # (N-L+1, L, 9)
    starts = np.arange(0, len(views), stride)
    ends = starts + L - 1
    last_mean = np.empty((len(starts), schema.NUM_STATES))
    last_var = np.empty_like(last_mean)
    model.eval()
    with torch.no_grad():
        for i in range(0, len(starts), batch_size):
            sel = starts[i : i + batch_size]
            m, v = model(torch.from_numpy(np.ascontiguousarray(views[sel])))
            last_mean[i : i + len(sel)] = m[:, -1].double().numpy()
            last_var[i : i + len(sel)] = v[:, -1].double().numpy()
            if progress is not None:
                progress.update(len(sel))
    # every sample from the first window end on takes the newest window ending at or before it
    k = np.searchsorted(ends, np.arange(L - 1, n), side="right") - 1  # (N-L+1,)
    mean[L - 1 :] = last_mean[k]
    var[L - 1 :] = last_var[k]
    return StreamOutput(mean, var)


def guarded(stream: StreamOutput, mu: float) -> tuple[StreamOutput, np.ndarray]:
    """The physics guard (NumPy, as at runtime) on streaming estimates: ``(guarded, fired (N,) bool)``."""
    valid = stream.valid
    mean, var = stream.mean.copy(), stream.var.copy()
    fired = np.zeros(len(valid), dtype=bool)
    mean[valid], var[valid], fired[valid] = physics_guard(mean[valid], var[valid], schema.accel_limit_mps2(mu))
    return StreamOutput(mean, var), fired


@dataclass
class DrWindow(DeadReckoningErrors):
    """One dead-reckoning window: per-step position error [m] and distance travelled [m]."""

    drive: str
    start: int
    pos_error_m: np.ndarray
    distance_m: float


def dead_reckon(z_mean: np.ndarray, z_var: np.ndarray, z_gt: np.ndarray, pose_gt: np.ndarray, start: int,
                n_steps: int, Q: np.ndarray | None = None, P0: np.ndarray | None = None) -> np.ndarray:
    """Position errors (n_steps,) [m] of the NumPy EKF started at ``start`` from the true state.

    ``z_mean``/``z_var`` (N, 5) guarded estimates, ``z_gt`` (N, 5), ``pose_gt`` (N, 3) [x east m,
    y north m, psi rad]. Step ``start`` is the initial state (error 0); steps ``start + 1 ...`` each
    predict and update with that step's estimate.
    """
    x0 = np.zeros(schema.EkfState.DIM)
    x0[schema.EkfState.POS] = pose_gt[start, :2]
    x0[schema.EkfState.YAW] = pose_gt[start, 2]
    x0[list(schema.Z_TO_EKF_INDEX)] = z_gt[start]
    ekf = Ekf(x0, default_initial_covariance() if P0 is None else P0,
              default_process_noise(schema.DT_S) if Q is None else Q, schema.DT_S)
    errors = np.zeros(n_steps)
    for k in range(1, n_steps):
        t = start + k
        ekf.step(z_mean[t], z_var[t])
        d_x, d_y = ekf.x[schema.EkfState.POS] - pose_gt[t, :2]
        errors[k] = math.hypot(d_x, d_y)
    return errors


def dr_starts(n_samples: int, first_valid: int, window_steps: int) -> list[int]:
    """Starts of non-overlapping ``window_steps``-long windows in ``[first_valid, n_samples)``."""
    return list(range(first_valid, n_samples - window_steps + 1, window_steps))


@dataclass
class SplitReport:
    """Evaluation of one method on a list of drives (one split)."""

    z_rmse: dict[str, float] = field(default_factory=dict)  # per state name, SI
    osd_z_rmse: dict[str, float] = field(default_factory=dict)
    guard_fire_rate: float = 0.0
    dr_windows: list[DrWindow] = field(default_factory=list)
    n_samples: int = 0

    def dr_summary(self) -> dict[str, float]:
        """Mean and std over windows of the position RMSE and ME [m], drift [%], and the count."""
        if not self.dr_windows:
            return {"n_windows": 0}
        rmse = np.array([w.rmse_m for w in self.dr_windows])
        me = np.array([w.max_error_m for w in self.dr_windows])
        drift = np.array([w.drift_pct for w in self.dr_windows])
        return {"n_windows": len(self.dr_windows), "rmse_mean_m": float(rmse.mean()), "rmse_std_m": float(rmse.std()),
                "me_mean_m": float(me.mean()), "me_std_m": float(me.std()),
                "drift_mean_pct": float(np.nanmean(drift)) if np.isfinite(drift).any() else float("nan")}

    def to_dict(self) -> dict:
        return {"z_rmse": self.z_rmse, "osd_z_rmse": self.osd_z_rmse, "guard_fire_rate": self.guard_fire_rate,
                "n_samples": self.n_samples, "dead_reckoning_60s": self.dr_summary()}


def _rmse(sq_sum: np.ndarray, count: np.ndarray) -> dict[str, float]:
    return {name: (float(math.sqrt(sq_sum[i] / count[i])) if count[i] > 0 else float("nan"))
            for i, name in enumerate(schema.STATE_NAMES)}


@dataclass(frozen=True)
class Segment:
    """Samples ``[start, stop)`` of a full drive to evaluate on; the model sees the drive from 0 (context)."""

    drive: object  # prml2_edge.data.revsted.Drive with ground truth
    start: int
    stop: int
    mu: float


def split_segments(dataset, split: str) -> list[Segment]:
    """The evaluation segments of a split (:meth:`prml2_edge.data.datasets.Dataset.segments`); ``mu`` from
    each drive's metadata (1.0 if absent).

    Streaming needs L - 1 samples of history: a part that does not start its drive takes them
    from the samples before it (onboard signals only, as a live system would have them).
    """
    return [Segment(drive, a, b, float(drive.meta.get("mu", 1.0))) for drive, a, b in dataset.segments(split)
            if drive.has_ground_truth]


def evaluate_segments(model: Prml2Model, segments: list[Segment], *, stride: int = 1, mu: float | None = None,
                      dead_reckoning: bool = True, window_s: float = DR_WINDOW_S,
                      progress: bool | None = None) -> SplitReport:
    """z RMSE (model and OSD baseline) and 60 s dead reckoning of ``model`` on ``segments``.

    Parameters
    ----------
    segments
        What to evaluate (:func:`split_segments`).
    stride
        Streaming stride [samples].
    mu
        Friction coefficient for the guard; default each segment's ``mu``.
    window_s
        Dead-reckoning window [s]; windows are non-overlapping and lie inside a segment.
    """
    report = SplitReport()
    window_steps = int(round(window_s / schema.DT_S))
    sq = np.zeros(schema.NUM_STATES)
    cnt = np.zeros(schema.NUM_STATES)
    osd_sq = np.zeros(schema.NUM_STATES)
    osd_cnt = np.zeros(schema.NUM_STATES)
    fired = preds = 0
    L = model.cfg.window_len
    total = sum(max(0, seg.stop - max(seg.start, L - 1)) for seg in segments)
    bar = Progress(-(-total // stride) if total else 0, desc="evaluate", unit="win", enabled=progress)
    for seg in segments:
        drive = seg.drive
        ctx = max(0, seg.start - (L - 1))  # first sample the model needs
        onboard = drive.onboard[ctx : seg.stop]
        z_gt = drive.z_gt[ctx : seg.stop]
        pose_gt = drive.pose_gt[ctx : seg.stop]
        stream, fired_mask = guarded(stream_predict(model, onboard, stride=stride, progress=bar),
                                     seg.mu if mu is None else mu)
        inside = np.zeros(len(onboard), dtype=bool)
        inside[seg.start - ctx :] = True
        valid = stream.valid & inside
        fired += int(fired_mask[valid].sum())
        preds += int(valid.sum())
        err = stream.mean[valid] - z_gt[valid]
        sq += (err**2).sum(axis=0)
        cnt += valid.sum()
        report.n_samples += int(valid.sum())
        z_osd = osd_baseline_z(onboard, drive_bias(drive.onboard[seg.start : seg.stop], drive.onboard))
        osd_err = z_osd[valid] - z_gt[valid]
        ok = np.isfinite(osd_err)
        osd_sq += np.square(np.where(ok, osd_err, 0.0)).sum(axis=0)
        osd_cnt += ok.sum(axis=0)
        if dead_reckoning and valid.any():
            first = int(np.argmax(valid))
            for start in dr_starts(len(valid), first, window_steps):
                errors = dead_reckon(stream.mean, stream.var, z_gt, pose_gt, start, window_steps)
                distance = path_length_m(pose_gt[start : start + window_steps])
                report.dr_windows.append(DrWindow(drive.name, ctx + start, errors, distance))
    bar.close()
    report.z_rmse = _rmse(sq, cnt)
    report.osd_z_rmse = _rmse(osd_sq, osd_cnt)
    report.guard_fire_rate = fired / preds if preds else 0.0
    return report


def evaluate_split(model: Prml2Model, dataset, split: str, **kwargs) -> SplitReport:
    """:func:`evaluate_segments` on :func:`split_segments` ``(dataset, split)``."""
    return evaluate_segments(model, split_segments(dataset, split), **kwargs)
