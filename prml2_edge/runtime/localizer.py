"""Streaming localisation: one code path for the live runtime and offline evaluation.

The pipeline docs/design.md draws, one stage a module:
:mod:`~prml2_edge.runtime.estimator` (window -> model -> physics guard -> z) feeds
:mod:`~prml2_edge.runtime.filter` (EKF with calibration states, raw cues, standstill, GNSS);
:class:`StreamingLocalizer` runs the two per 50 Hz row and reports the pose status.

:class:`StreamingLocalizer` works on plain arrays: the CAN pipeline feeds it assembled rows
(:meth:`StreamingLocalizer.step`), ``prml2 evaluate`` feeds it a drive
(:meth:`StreamingLocalizer.run_arrays`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import StepStatus, default_process_noise, wrap_angle
from prml2_edge.runtime.async_estimator import AsyncEstimator
from prml2_edge.runtime.cue_offset import NUISANCE_NAMES
from prml2_edge.runtime.estimator import Estimate, Estimator, Model
from prml2_edge.runtime.filter import PoseFilter
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.localizer_config import LocalizerConfig
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import CalState, EkfState

__all__ = ["LocalizerConfig", "Model", "StepOutput", "StreamingLocalizer", "Trajectory"]


@dataclass
class StepOutput:
    """The localiser's result for one 50 Hz step.

    ``x`` (8,) EKF state (:class:`prml2_edge.schema.EkfState`; NaN while initialising), ``psi``
    wrapped to [-pi, pi); ``pos_std_m`` radial one-sigma position uncertainty; ``yaw_std_rad``;
    ``outage_s`` time since the last absolute fix (GNSS or the initial pose) [s];
    ``valid`` (9,) per-signal validity of the row.
    """

    k: int
    t_s: float
    x: np.ndarray
    pos_std_m: float
    yaw_std_rad: float
    status: PoseStatus
    ekf_status: StepStatus | None
    model_used: bool
    inferred: bool
    guard_fired: bool
    gnss_fused: bool
    gnss_outage: bool
    outage_s: float
    degraded: bool
    valid: np.ndarray
    z: np.ndarray | None = None  # (5,) guarded model output used at this step
    z_var: np.ndarray | None = None
    bus_silent: bool = False  # no CAN frame at all for more than the assembler's bus_silent_s
    pos_cov: np.ndarray | None = None  # (2, 2) position covariance [m^2], world frame
    cal: np.ndarray | None = None  # (3,) calibration states (schema.CalState), when on
    cues_used: bool = False
    standstill: bool = False
    signals: np.ndarray | None = None  # (9,) the row's onboard signals [SI], canonical order (as the model saw them)
    gnss: GnssFix | None = None  # the GNSS fix that arrived in this row, valid or not (None: none arrived)
    substituted: np.ndarray | None = None  # (9,) bool: values the plausibility checks replaced (None: none)
    reasons: dict | None = None  # why the pose is degraded / GNSS not used: {signal or "gnss": reason}
    # time spent in the model, the guard and the filter at this step [ns] (the pipeline records them)
    infer_ns: int = 0
    guard_ns: int = 0
    filter_ns: int = 0

    def record(self) -> dict:
        """A flat, JSON-ready dict (non-finite numbers become None)."""
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        rec: dict = {"t_s": round(self.t_s, 6)}
        for name, value in zip(EkfState.NAMES, self.x, strict=True):
            rec[name] = num(value)
        rec["pos_std_m"] = num(self.pos_std_m)
        rec["yaw_std_rad"] = num(self.yaw_std_rad)
        rec["status"] = self.status.name
        rec["model_used"] = self.model_used
        rec["guard_fired"] = self.guard_fired
        rec["gnss_fused"] = self.gnss_fused
        rec["gnss_outage"] = self.gnss_outage
        rec["outage_s"] = num(self.outage_s)
        rec["degraded"] = self.degraded
        rec["bus_silent"] = self.bus_silent
        rec["ekf_status"] = None if self.ekf_status is None else self.ekf_status.name
        if self.cal is not None:
            for name, value in zip(CalState.NAMES, self.cal, strict=True):
                rec[name] = num(value)
            rec["standstill"] = self.standstill
        rec["valid"] = {n: bool(v) for n, v in zip(schema.SIGNAL_NAMES, self.valid, strict=True)}
        if self.substituted is not None and self.substituted.any():
            rec["substituted"] = [n for n, v in zip(schema.SIGNAL_NAMES, self.substituted, strict=True) if v]
        if self.reasons:
            rec["reasons"] = dict(self.reasons)
        return rec


@dataclass
class Trajectory:
    """Output of :meth:`StreamingLocalizer.run_arrays`: one entry per input row.

    ``x`` (N, 8) EKF states (NaN before the start index), ``pos_std_m`` (N,), ``yaw_std_rad`` (N,),
    ``status`` (N,) :class:`PoseStatus` values, ``model_used`` (N,) bool.
    """

    t_s: np.ndarray
    x: np.ndarray
    pos_std_m: np.ndarray
    yaw_std_rad: np.ndarray
    status: np.ndarray
    model_used: np.ndarray
    guard_fired: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    pos_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))  # (N, 2, 2) [m^2]
    cal: np.ndarray = field(default_factory=lambda: np.zeros((0, CalState.DIM)))  # (N, 3), NaN when off

    @property
    def pose(self) -> np.ndarray:
        """(N, 3) ``[x east, y north, psi ccw from east]`` [m, m, rad] (``psi`` wrapped)."""
        out = self.x[:, :3].copy()
        out[:, 2] = wrap_angle(out[:, 2])
        return out


def omega_var_inflation(model: Model, config: LocalizerConfig, coarse: bool = False) -> float:
    """The factor on the model's omega_z variance next to the raw cues (``coarse``: next to a coarse CAN yaw rate):
    the config's, else the model's metadata (``error_model.var_inflation``), else 1."""
    setting = config.model_omega_var_inflation_coarse if coarse else config.model_omega_var_inflation
    if setting is not None:
        value = float(setting)
    else:
        error_model = getattr(getattr(model, "metadata", None), "error_model", None) or {}
        value = float((error_model.get("var_inflation") or [1.0] * schema.NUM_STATES)[schema.Z.OMEGA_Z])
    if not (math.isfinite(value) and value >= 1.0):
        raise ValueError(f"model omega_z variance inflation must be >= 1, got {value!r}")
    return value


def reads_debiased_cues(model: Model, config: LocalizerConfig) -> bool:
    """Whether the model reads each row less the cue estimator's offsets: the config asks for it
    (``model_inputs_from_cues``), or the model was trained that way (its metadata's ``cue_debiased_inputs``)."""
    meta = getattr(model, "metadata", None)
    return bool(config.model_inputs_from_cues or getattr(meta, "reads_debiased_cues", False))


class StreamingLocalizer:
    """Estimator (window -> model -> physics guard) then filter (EKF, cues, GNSS), one 50 Hz row per :meth:`step`.

    Parameters
    ----------
    model:
        An :class:`~prml2_edge.runtime.inference.OnnxModel` (or anything with its interface).
    config:
        :class:`LocalizerConfig`.
    process_noise:
        EKF ``Q`` (8, 8) for one step; default: the model's metadata ``ekf_process_noise`` when
        present, else :func:`prml2_edge.ekf.numpy_ekf.default_process_noise`.
    initial_pose:
        Where to start; None waits for GNSS (status ``INITIALISING``).

    Each :class:`StepOutput` carries the time its model, guard and filter took; the pipeline records them.
    """

    def __init__(self, model: Model, config: LocalizerConfig | None = None, process_noise: np.ndarray | None = None,
                 initial_pose: InitialPose | None = None, dt_s: float = schema.DT_S) -> None:
        self.model = model
        self.config = config or LocalizerConfig()
        self.dt_s = float(dt_s)
        if process_noise is None:
            process_noise = getattr(getattr(model, "metadata", None), "ekf_process_noise", None)
        if process_noise is None:
            process_noise = default_process_noise(self.dt_s)
        cfg = self.config
        estimator = AsyncEstimator if cfg.async_inference else Estimator
        self.estimator = estimator(model, cfg.stride, cfg.max_invalid_fraction, schema.accel_limit_mps2(cfg.mu))
        self.filter = PoseFilter(cfg, process_noise, initial_pose, self.dt_s)
        self.filter.omega_var_inflation = omega_var_inflation(model, cfg)
        self.filter.omega_var_inflation_coarse = omega_var_inflation(model, cfg, coarse=True)
        self.model_reads_cues = reads_debiased_cues(model, cfg)
        self.reset()

    # the stages' parts that callers read or set (evaluation, the pipeline's summary)
    @property
    def a_max_mps2(self) -> float:
        return self.estimator.a_max_mps2

    @a_max_mps2.setter
    def a_max_mps2(self, value: float) -> None:
        self.estimator.a_max_mps2 = float(value)

    @property
    def ekf(self):
        return self.filter.ekf

    @property
    def initial_pose(self) -> InitialPose | None:
        return self.filter.initial_pose

    @property
    def guard_stats(self):
        return self.estimator.guard_stats

    def reset(self) -> None:
        """Back to the state before the first row (window empty, filter not started)."""
        self.estimator.reset()
        self.filter.reset()
        self.k = -1
        self.n_model_used = 0
        self.status_counts = [0] * len(PoseStatus)

    def restore_calibration(self, cal: np.ndarray, cal_cov: np.ndarray) -> None:
        """Begin every start from this calibration ``(3,)`` / ``(3, 3)`` (a restored state file)."""
        self.filter.calibration0 = (np.asarray(cal, dtype=np.float64), np.asarray(cal_cov, dtype=np.float64))
        if self.filter.ekf is not None and self.filter.calibrated:
            self.filter.ekf.set_calibration(*self.filter.calibration0)

    def calibration(self) -> tuple[np.ndarray, np.ndarray] | None:
        return self.filter.calibration()

    def restore_yaw_gain(self, info: float, info_c: float) -> None:
        """Start the CAN yaw rate's gain from evidence saved by earlier drives (a restored state file)."""
        self.filter.yaw_gain.restore(info, info_c)

    def yaw_gain_state(self) -> dict | None:
        """The gain evidence to save (None with the gain calibration off)."""
        return self.filter.yaw_gain.state() if self.filter.gain_learned else None

    def restore_cue_offsets(self, values, cov) -> bool:
        """Start the cue estimator from the cues' own offsets saved by earlier drives; False (nothing done) when the
        estimator is off or ``cue_offset_restore`` is. ValueError on values of the wrong shape or not finite."""
        cues = self.filter.cue_offset
        if cues is None or not self.config.cue_offset_restore:
            return False
        cues.restore(values, cov)
        return True

    def cue_offset_state(self) -> dict | None:
        """The cues' own offsets to save (None with the estimator off)."""
        cues = self.filter.cue_offset
        if cues is None:
            return None
        values, cov = cues.nuisance()
        return {"names": list(NUISANCE_NAMES), "values": values.tolist(), "cov": cov.tolist()}

    def step(self, values: np.ndarray, valid: np.ndarray, t_s: float, gnss: GnssFix | None = None,
             discontinuity: bool = False, bus_silent: bool = False, substituted: np.ndarray | None = None,
             substitute_std: np.ndarray | None = None) -> StepOutput:
        """Consume one 50 Hz row: ``values`` (9,) SI canonical order, ``valid`` (9,) bool, at ``t_s`` [s].

        ``bus_silent`` (the assembler's flag) is passed through to the output. ``substituted`` (9,) bool marks
        values that :mod:`~prml2_edge.runtime.plausibility` replaced (invalid for the filter, fine for the model).
        """
        self.k += 1
        valid = np.asarray(valid, dtype=bool)
        all_valid = bool(np.all(valid))
        model_ok = all_valid or (substituted is not None and bool(np.all(valid | substituted)))
        est = self.estimator.step(self._model_row(values), model_ok, discontinuity)
        fix = gnss if (gnss is not None and gnss.valid and self.config.fuse_gnss) else None
        t_filter = time.perf_counter_ns()
        res = self.filter.step(values, valid, t_s, est, fix, substituted, substitute_std)
        filter_ns = time.perf_counter_ns() - t_filter
        out = self._output(t_s, res.ekf_status, est, res.model_used, res.gnss_fused, valid, all_valid,
                           res.standstill)
        out.bus_silent = bus_silent
        out.signals, out.gnss = values, gnss
        out.cues_used, out.standstill = res.cues_used, res.standstill
        out.infer_ns, out.guard_ns, out.filter_ns = est.infer_ns, est.guard_ns, filter_ns
        return out

    @property
    def raw_rows_warning(self) -> str | None:
        """Why the model will read raw rows although it wants them less the cues' offsets (calibration or cue_offset
        off: nothing learns them), for a run a user started to say; None when it reads what it wants."""
        if not self.model_reads_cues or self.filter.cue_offset is not None:
            return None
        return ("the model reads a_y and steering less the car's offsets, but with calibration or cue_offset off "
                "nothing learns them: it reads the raw CAN values and will drift more; turn calibration on")

    def _model_row(self, values: np.ndarray) -> np.ndarray:
        """The row the model reads: ``values``, or for a model that reads the cues less their offsets
        (:func:`reads_debiased_cues`) a copy less those the filter's cue estimator has learned so far (the filter
        reads the raw row; without calibration there is no estimator and the model reads the raw row too)."""
        cues = self.filter.cue_offset
        if cues is None or not self.model_reads_cues:
            return values
        return cues.debiased(values)

    def _output(self, t_s: float, ekf_status: StepStatus | None, est: Estimate, model_used: bool,
                gnss_fused: bool, valid: np.ndarray, all_valid: bool, standstill: bool = False) -> StepOutput:
        flt = self.filter
        ekf = flt.ekf
        pos_cov = cal = None
        if ekf is None:
            x = np.full(EkfState.DIM, np.nan)
            pos_std = yaw_std = math.nan
            status = PoseStatus.INITIALISING
            gnss_recent = False
            outage = math.nan
        else:
            x = ekf.x[: EkfState.DIM].copy()
            x[EkfState.YAW] = wrap_angle(x[EkfState.YAW])
            pos_std, yaw_std = ekf.pose_std
            pos_cov = ekf.P[EkfState.POS, EkfState.POS].copy()
            cal = ekf.cal if ekf.calibration else None
            gnss_recent = flt.gnss_recent(t_s)
            outage = flt.outage_s(t_s)
            if not all_valid:
                status = PoseStatus.DEGRADED
            elif gnss_recent:
                status = PoseStatus.GNSS_AIDED
            elif not model_used and not standstill and ekf_status is not None:
                status = PoseStatus.PREDICT_ONLY  # (parked, the zero-velocity update is the measurement)
            else:
                status = PoseStatus.DEAD_RECKONING
        self.status_counts[status] += 1
        self.n_model_used += int(model_used)
        gnss_outage = ekf is not None and flt.had_fix() and not gnss_recent
        z, z_var = (est.z, est.z_var) if model_used else (None, None)
        reasons = {"gnss": flt.gnss_check.reason} if flt.gnss_check.suspect else None
        return StepOutput(self.k, t_s, x, pos_std, yaw_std, status, ekf_status, model_used, est.inferred,
                          est.guard_fired and model_used, gnss_fused, gnss_outage, outage, not all_valid,
                          valid.copy(), z, z_var, pos_cov=pos_cov, cal=cal, reasons=reasons)

    # ---- counters the pipeline reports ------------------------------------------------------------

    @property
    def n_inferences(self) -> int:
        return self.estimator.n_inferences

    @property
    def n_inference_failures(self) -> int:
        return self.estimator.n_inference_failures

    @property
    def n_gnss_rejected(self) -> int:
        return self.filter.n_gnss_rejected

    def close(self) -> None:
        """Release the estimator's worker thread, if it has one."""
        self.estimator.close()

    def summary(self) -> dict:
        """The estimator's and the filter's counters, as plain data."""
        return {**self.estimator.summary(), "model_used_steps": self.n_model_used, **self.filter.summary()}

    def run_arrays(self, onboard: np.ndarray, x0: np.ndarray, P0: np.ndarray | None = None, start_index: int = 0,
                   valid: np.ndarray | None = None, t_s: np.ndarray | None = None,
                   gnss: Mapping[int, GnssFix] | None = None) -> Trajectory:
        """Run a whole drive through the streaming path (what ``prml2 evaluate`` calls).

        Parameters
        ----------
        onboard:
            (N, 9) onboard signals at 50 Hz [SI, canonical order].
        x0, P0:
            EKF state (8,) and covariance (8, 8) at row ``start_index`` (P0 default:
            :func:`prml2_edge.ekf.numpy_ekf.default_initial_covariance`). Rows before it only fill
            the model's window (history), so with ``start_index >= L - 1`` the model is warm.
        valid:
            (N, 9) bool validity (default all valid).
        t_s:
            (N,) timestamps [s] (default ``k * dt_s``).
        gnss:
            GNSS fixes by row index (fused at that row; the deployment protocol), default none.

        Returns
        -------
        :class:`Trajectory` with the state after every row (``x[start_index] == x0``).
        """
        from prml2_edge.ekf.numpy_ekf import default_initial_covariance

        onboard = np.asarray(onboard, dtype=np.float64)
        n = onboard.shape[0]
        if onboard.ndim != 2 or onboard.shape[1] != schema.NUM_SIGNALS:
            raise ValueError(f"onboard must be (N, {schema.NUM_SIGNALS}), got {onboard.shape}")
        if not 0 <= start_index < n:
            raise ValueError(f"start_index {start_index} outside [0, {n})")
        valid_arr = np.ones((n, schema.NUM_SIGNALS), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        times = np.arange(n) * self.dt_s if t_s is None else np.asarray(t_s, dtype=np.float64)
        p0 = default_initial_covariance() if P0 is None else np.asarray(P0, dtype=np.float64)
        fixes = gnss or {}
        saved_pose, self.filter.initial_pose = self.filter.initial_pose, None
        self.reset()
        xs = np.full((n, EkfState.DIM), np.nan)
        pos_std = np.full(n, np.nan)
        yaw_std = np.full(n, np.nan)
        pos_cov = np.full((n, 2, 2), np.nan)
        cal = np.full((n, CalState.DIM), np.nan)
        status = np.zeros(n, dtype=np.int8)
        used = np.zeros(n, dtype=bool)
        fired = np.zeros(n, dtype=bool)
        try:
            for i in range(n):
                if i == start_index:
                    self.filter.start(np.asarray(x0, dtype=np.float64), p0, float(times[i]))
                    # the start row only feeds the window: x[start_index] is x0 itself
                    self.k += 1
                    ok = bool(valid_arr[i].all())
                    est = self.estimator.step(self._model_row(onboard[i]), ok)
                    out = self._output(float(times[i]), None, est, False, False, valid_arr[i], ok)
                else:
                    out = self.step(onboard[i], valid_arr[i], float(times[i]), fixes.get(i))
                xs[i], pos_std[i], yaw_std[i] = out.x, out.pos_std_m, out.yaw_std_rad
                status[i], used[i], fired[i] = out.status, out.model_used, out.guard_fired
                if out.pos_cov is not None:
                    pos_cov[i] = out.pos_cov
                if out.cal is not None:
                    cal[i] = out.cal
        finally:
            self.filter.initial_pose = saved_pose
        return Trajectory(times, xs, pos_std, yaw_std, status, used, fired, pos_cov, cal)
