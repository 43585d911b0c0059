"""Streaming localisation: one code path for the live runtime and offline evaluation.

method.md "Streaming inference": a new window every ``stride`` 50 Hz steps; each window's
decoder outputs cover its last L - H steps; at every step the EKF consumes the newest
available output for that step (with stride 1: the last decoder output of the newest
window), after the physics guard. While no valid output is available (the first L - 1 steps,
a failed inference, a window with too many invalid rows, an invalid current row) the EKF
predicts only. GNSS fixes, when given, are fused as pose measurements.

:class:`StreamingLocalizer` works on plain arrays: the CAN pipeline feeds it assembled rows
(:meth:`StreamingLocalizer.step`), ``prml2 evaluate`` feeds it a drive
(:meth:`StreamingLocalizer.run_arrays`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import Ekf, StepStatus, default_process_noise, wrap_angle
from prml2_edge.guard import GuardStats, physics_guard
from prml2_edge.runtime.initial_pose import InitialPose, initial_state
from prml2_edge.runtime.latency import LatencyRecorder
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.status import InferenceStatus, PoseStatus
from prml2_edge.runtime.window import Window
from prml2_edge.schema import EkfState


class Model(Protocol):
    """What the localiser needs from a model (:class:`prml2_edge.runtime.inference.OnnxModel`)."""

    window_len: int
    mean: np.ndarray  # (R, 5) after a successful step, the newest R decoder steps; the last row is used
    var: np.ndarray  # (R, 5)

    def step(self, window: np.ndarray) -> InferenceStatus: ...


@dataclass(frozen=True)
class LocalizerConfig:
    """Tunables of :class:`StreamingLocalizer` (SI units unless named otherwise)."""

    stride: int = 1  # a new window every `stride` 50 Hz steps
    mu: float = 1.0  # road friction for the physics guard (<= 0.5: low-mu limits)
    # Outputs of a window whose rows had an invalid signal in more than this fraction are not used:
    # a dropout of d rows costs the model until at most fraction * L of them are left in the window.
    max_invalid_fraction: float = 0.2
    gnss_pos_std_m: float = 0.5  # one-sigma GNSS position noise per axis
    gnss_heading_std_deg: float = 2.0  # one-sigma GNSS heading noise
    gnss_heading_min_speed_mps: float = 2.0  # below this speed a GNSS heading is not fused
    gnss_timeout_s: float = 0.5  # no fix for longer: GNSS outage (dead reckoning)
    fuse_gnss: bool = True
    # Innovation gate: a fix whose position is further from the prediction than this squared
    # Mahalanobis distance (2 dof; 16 ~ 4 sigma, p ~ 3e-4) is not fused, nor a heading beyond the same
    # bound (1 dof). CAN has no authentication and GNSS_FIX no checksum: one stray frame must not
    # teleport the pose. After this many fixes rejected in a row (2 s at 10 Hz) the next one is fused
    # anyway, so a filter that really is off is pulled back.
    gnss_gate_chi2: float = 16.0
    gnss_gate_max_rejects: int = 20

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")
        if not self.mu > 0:
            raise ValueError(f"mu must be > 0, got {self.mu}")
        if not 0.0 <= self.max_invalid_fraction <= 1.0:
            raise ValueError(f"max_invalid_fraction must be in [0, 1], got {self.max_invalid_fraction}")


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
        rec["valid"] = {n: bool(v) for n, v in zip(schema.SIGNAL_NAMES, self.valid, strict=True)}
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

    @property
    def pose(self) -> np.ndarray:
        """(N, 3) ``[x east, y north, psi ccw from east]`` [m, m, rad] (``psi`` wrapped)."""
        out = self.x[:, :3].copy()
        out[:, 2] = wrap_angle(out[:, 2])
        return out


class StreamingLocalizer:
    """Window -> model -> physics guard -> EKF (+ GNSS fusion), one 50 Hz row per :meth:`step`.

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
        Where to start; None waits for the first valid GNSS fix (status ``INITIALISING``).
    latency:
        Records ``infer``, ``guard`` and ``filter`` durations when given.
    """

    def __init__(self, model: Model, config: LocalizerConfig | None = None, process_noise: np.ndarray | None = None,
                 initial_pose: InitialPose | None = None, latency: LatencyRecorder | None = None,
                 dt_s: float = schema.DT_S) -> None:
        self.model = model
        self.config = config or LocalizerConfig()
        self.dt_s = float(dt_s)
        if process_noise is None:
            meta_q = getattr(getattr(model, "metadata", None), "ekf_process_noise", None)
            process_noise = np.asarray(meta_q, dtype=np.float64) if meta_q is not None else \
                default_process_noise(self.dt_s)
        self.process_noise = np.asarray(process_noise, dtype=np.float64)
        self.initial_pose = initial_pose
        self.latency = latency
        self.a_max_mps2 = schema.accel_limit_mps2(self.config.mu)
        self.guard_stats = GuardStats()
        self.window = Window(model.window_len)
        # the newest window's newest decoder output, guarded: the only one ever consumed (see _feed)
        self._z_mean = np.zeros(schema.NUM_STATES)
        self._z_var = np.ones(schema.NUM_STATES)
        self._fired = False
        self.reset()

    def reset(self) -> None:
        """Back to the state before the first row (window empty, filter not started)."""
        self.window.clear()
        self.ekf: Ekf | None = None
        self.k = -1
        self._inf_count = -1  # window.count at the last inference; -1: none yet
        self._output_ok = False
        self._last_abs_t: float | None = None  # last GNSS fix or the start
        self._last_fix_t: float | None = None
        self._gnss_rejects_in_row = 0
        self.n_gnss_rejected = 0  # fixes refused by the innovation gate
        self.n_inferences = 0
        self.n_model_used = 0
        self.n_inference_failures = 0
        self.status_counts = [0] * len(PoseStatus)

    @property
    def started(self) -> bool:
        return self.ekf is not None

    def start(self, x0: np.ndarray, P0: np.ndarray, t_s: float) -> None:
        """Start (or restart) the EKF at state ``x0`` (8,), covariance ``P0`` (8, 8), at time ``t_s`` [s]."""
        self.ekf = Ekf(x0, P0, Q=self.process_noise, dt_s=self.dt_s)
        self._last_abs_t = t_s

    def _infer(self) -> bool:
        t0 = time.perf_counter_ns()
        status = self.model.step(self.window.view())
        t1 = time.perf_counter_ns()
        self._inf_count = self.window.count
        self.n_inferences += 1
        if status is not InferenceStatus.SUCCESS:
            self._output_ok = False
            self.n_inference_failures += 1
        else:
            # Only the newest decoder step is ever consumed (held until the next window, see _feed), so only
            # it is guarded and counted: the guard statistics are over used predictions.
            mean, var, fired = physics_guard(self.model.mean[-1:], self.model.var[-1:], self.a_max_mps2)
            self._z_mean, self._z_var, self._fired = mean[0], var[0], bool(fired[0])
            self.guard_stats.update(fired)
            self._output_ok = self.window.invalid_fraction <= self.config.max_invalid_fraction
        if self.latency is not None:
            self.latency.add("infer", t1 - t0)
            self.latency.add("guard", time.perf_counter_ns() - t1)
        return True

    def _feed(self, values: np.ndarray, all_valid: bool, discontinuity: bool = False):
        """Window, inference when due, and the output for this step: ``(inferred, z, z_var, guard_fired)``."""
        if discontinuity:
            self.window.clear()
            self._inf_count = -1
            self._output_ok = False
        self.window.step(values, all_valid)
        inferred = False
        if self.window.full and (self._inf_count < 0 or self.window.count - self._inf_count >= self.config.stride):
            inferred = self._infer()
        if self._output_ok and all_valid and self._inf_count >= 0:
            # Causal streaming: between windows (stride > 1) the newest window's newest output, the estimate
            # for step k - offset, is held; older decoder rows describe older steps and are never used.
            offset = self.window.count - self._inf_count
            if offset < self.config.stride:
                return inferred, self._z_mean, self._z_var, self._fired
        return inferred, None, None, False

    def step(self, values: np.ndarray, valid: np.ndarray, t_s: float, gnss: GnssFix | None = None,
             discontinuity: bool = False, bus_silent: bool = False) -> StepOutput:
        """Consume one 50 Hz row: ``values`` (9,) SI canonical order, ``valid`` (9,) bool, at ``t_s`` [s].

        ``bus_silent`` (the assembler's flag) is passed through to the output.
        """
        out = self._step(values, valid, t_s, gnss, discontinuity)
        out.bus_silent = bus_silent
        return out

    def _step(self, values: np.ndarray, valid: np.ndarray, t_s: float, gnss: GnssFix | None,
              discontinuity: bool) -> StepOutput:
        self.k += 1
        cfg = self.config
        all_valid = bool(np.all(valid))
        inferred, z, z_var, guard_fired = self._feed(values, all_valid, discontinuity)
        fix = gnss if (gnss is not None and gnss.valid and cfg.fuse_gnss) else None

        ekf_status = None
        gnss_fused = False
        t_filter = time.perf_counter_ns()
        if self.ekf is None:
            start_pose = self.initial_pose
            if start_pose is None and fix is not None:
                start_pose = InitialPose.from_gnss(fix, cfg.gnss_pos_std_m, cfg.gnss_heading_std_deg)
            if start_pose is None:
                return self._output(t_s, None, inferred, False, False, False, valid, all_valid, z, z_var)
            x0, p0 = initial_state(start_pose, values, valid)
            self.start(x0, p0, t_s)
            gnss_fused = fix is not None and start_pose.source == "gnss"
            if gnss_fused:
                self._last_fix_t = t_s
        else:
            ekf_status = self.ekf.step(z, z_var)
            if fix is not None:
                gnss_fused = self._fuse(fix, t_s)
        model_used = ekf_status is StepStatus.SUCCESS
        if self.latency is not None:
            self.latency.add("filter", time.perf_counter_ns() - t_filter)
        return self._output(t_s, ekf_status, inferred, model_used, guard_fired and model_used, gnss_fused, valid,
                            all_valid, z if model_used else None, z_var if model_used else None)

    def _fuse(self, fix: GnssFix, t_s: float) -> bool:
        cfg = self.config
        x = self.ekf.x  # type: ignore[union-attr]
        # Move the fix from its frame time to this row's time along the current velocity (<= one period).
        lag_s = min(max(t_s - fix.t_s, 0.0), self.dt_s)
        c, s = math.cos(x[EkfState.YAW.start]), math.sin(x[EkfState.YAW.start])
        vx, vy = x[EkfState.VEL]
        pos = np.array([fix.x_m + (c * vx - s * vy) * lag_s, fix.y_m + (s * vx + c * vy) * lag_s])
        psi = fix.psi_rad
        yaw_var = None
        if psi is not None and math.hypot(vx, vy) >= cfg.gnss_heading_min_speed_mps:
            psi += x[EkfState.OMEGA_Z.start] * lag_s
            yaw_var = math.radians(cfg.gnss_heading_std_deg) ** 2
        else:
            psi = None
        if not self._gate(pos, psi, yaw_var):
            return False
        if psi is not None and yaw_var is not None:
            p = self.ekf.P  # type: ignore[union-attr]
            d_psi = float(wrap_angle(psi - x[EkfState.YAW.start]))
            if d_psi * d_psi > cfg.gnss_gate_chi2 * (p[EkfState.YAW.start, EkfState.YAW.start] + yaw_var):
                psi = yaw_var = None  # position fine, heading implausible: fuse the position only
        status = self.ekf.fuse_pose(pos, cfg.gnss_pos_std_m ** 2, psi, yaw_var)  # type: ignore[union-attr]
        if status is StepStatus.SUCCESS:
            self._last_fix_t = t_s
            self._last_abs_t = t_s
            return True
        return False

    def _gate(self, pos: np.ndarray, psi: float | None, yaw_var: float | None) -> bool:
        """Innovation gate of a GNSS position (2,) [m]; False (and counted) when it is refused."""
        cfg = self.config
        p = self.ekf.P  # type: ignore[union-attr]
        d = pos - self.ekf.x[EkfState.POS]  # type: ignore[union-attr]
        s = p[EkfState.POS, EkfState.POS] + np.eye(2) * cfg.gnss_pos_std_m ** 2
        with np.errstate(all="ignore"):
            try:
                m2 = float(d @ np.linalg.solve(s, d))
            except np.linalg.LinAlgError:
                m2 = math.inf
        if math.isfinite(m2) and m2 <= cfg.gnss_gate_chi2:
            self._gnss_rejects_in_row = 0
            return True
        self._gnss_rejects_in_row += 1
        if self._gnss_rejects_in_row > cfg.gnss_gate_max_rejects and math.isfinite(m2):
            self._gnss_rejects_in_row = 0
            return True
        self.n_gnss_rejected += 1
        return False

    def _output(self, t_s: float, ekf_status: StepStatus | None, inferred: bool, model_used: bool,
                guard_fired: bool, gnss_fused: bool, valid: np.ndarray, all_valid: bool, z, z_var) -> StepOutput:
        cfg = self.config
        if self.ekf is None:
            x = np.full(EkfState.DIM, np.nan)
            pos_std = yaw_std = math.nan
            status = PoseStatus.INITIALISING
            gnss_recent = False
            outage = math.nan
        else:
            x = self.ekf.x.copy()
            x[EkfState.YAW] = wrap_angle(x[EkfState.YAW])
            pos_std, yaw_std = self.ekf.pose_std
            gnss_recent = self._last_fix_t is not None and t_s - self._last_fix_t <= cfg.gnss_timeout_s + 1e-9
            outage = t_s - self._last_abs_t if self._last_abs_t is not None else math.nan
            if not all_valid:
                status = PoseStatus.DEGRADED
            elif gnss_recent:
                status = PoseStatus.GNSS_AIDED
            elif not model_used and ekf_status is not None:
                status = PoseStatus.PREDICT_ONLY
            else:
                status = PoseStatus.DEAD_RECKONING
        self.status_counts[status] += 1
        self.n_model_used += int(model_used)
        gnss_outage = self.ekf is not None and self._last_fix_t is not None and not gnss_recent
        return StepOutput(self.k, t_s, x, pos_std, yaw_std, status, ekf_status, model_used, inferred, guard_fired,
                          gnss_fused, gnss_outage, outage, not all_valid, np.array(valid, dtype=bool), z, z_var)

    def run_arrays(self, onboard: np.ndarray, x0: np.ndarray, P0: np.ndarray | None = None, start_index: int = 0,
                   valid: np.ndarray | None = None, t_s: np.ndarray | None = None) -> Trajectory:
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
        saved_pose, self.initial_pose = self.initial_pose, None
        self.reset()
        xs = np.full((n, EkfState.DIM), np.nan)
        pos_std = np.full(n, np.nan)
        yaw_std = np.full(n, np.nan)
        status = np.zeros(n, dtype=np.int8)
        used = np.zeros(n, dtype=bool)
        fired = np.zeros(n, dtype=bool)
        try:
            for i in range(n):
                if i == start_index:
                    self.start(np.asarray(x0, dtype=np.float64), p0, float(times[i]))
                    # the start row only feeds the window: x[start_index] is x0 itself
                    self.k += 1
                    ok = bool(valid_arr[i].all())
                    inferred = self._feed(onboard[i], ok)[0]
                    out = self._output(float(times[i]), None, inferred, False, False, False, valid_arr[i], ok,
                                       None, None)
                else:
                    out = self.step(onboard[i], valid_arr[i], float(times[i]))
                xs[i], pos_std[i], yaw_std[i] = out.x, out.pos_std_m, out.yaw_std_rad
                status[i], used[i], fired[i] = out.status, out.model_used, out.guard_fired
        finally:
            self.initial_pose = saved_pose
        return Trajectory(times, xs, pos_std, yaw_std, status, used, fired)
