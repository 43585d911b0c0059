"""The stateful planar EKF (:class:`Ekf`) for the edge runtime and evaluation, and its coverage metrics. No torch.

The equations are :mod:`prml2_edge.ekf.equations`, the tunable noise :mod:`prml2_edge.ekf.noise`; both are
re-exported here, so ``numpy_ekf.NAME`` keeps naming every part of the filter.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from prml2_edge import schema
from prml2_edge.ekf.equations import (
    _AY,
    _B_MODEL,
    _B_YAW,
    _F_COLS,
    _F_ROWS,
    _K_WHEEL,
    _OMEGA,
    _PX,
    _PY,
    _STANDSTILL_IDX,
    _VX,
    _YAW,
    _Z_IDX,
    FULL_DIM,
    JITTER_GROWTH,
    JITTER_MAX_REL,
    JITTER_REL,
    MEAS_DIM,
    STATE_DIM,
    _check_state,
    _update_linear,
    _update_selected,
    cholesky_jittered,
    course_measurement,
    cue_measurement,
    jitter_schedule,
    measurement_matrix,
    model_measurement,
    predict,
    process_jacobian,
    process_model,
    rotation,
    symmetrize,
    update,
    update_linear,
    update_model_calibrated,
    update_pose,
    wrap_angle,
)
from prml2_edge.ekf.noise import (
    CalibrationNoise,
    CalibrationStd,
    InitialStd,
    ProcessNoise,
    default_initial_covariance,
    default_process_noise,
    extend_calibrated,
)
from prml2_edge.schema import CalState


def _valid_z(z: np.ndarray | None, z_var: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``(z, z_var)`` as float64 (5,) arrays if both are given, finite and the variances > 0, else None."""
    if z is None or z_var is None:
        return None
    zz, vv = np.asarray(z, dtype=np.float64), np.asarray(z_var, dtype=np.float64)
    if zz.shape != (MEAS_DIM,) or vv.shape != (MEAS_DIM,):
        return None
    # (on Python floats: five values, once per step; NumPy's reductions cost more than the test)
    if not (all(map(math.isfinite, zz.tolist())) and all(math.isfinite(v) and v > 0.0 for v in vv.tolist())):
        return None
    return zz, vv


def _given_cues(yaw_rate: float | None, yaw_var: float, wheel_speed: float | None,
                wheel_var: float) -> tuple[list[tuple[float, float]], bool]:
    """The raw cues given, as ``(value, variance)`` pairs, and whether they are all usable (finite, variance > 0)."""
    cues = [(c, v) for c, v in ((yaw_rate, yaw_var), (wheel_speed, wheel_var)) if c is not None]
    return cues, all(math.isfinite(c) and math.isfinite(v) and v > 0.0 for c, v in cues)


# Ekf.step: after a non-finite state the filter restarts from the last finite state with its
# covariance diagonal (at least P0's) multiplied by this factor.
RESET_COV_INFLATION = 10.0


class StepStatus(enum.IntEnum):
    """Result of :meth:`Ekf.step` / :meth:`Ekf.fuse_pose` (the hot path never raises)."""

    SUCCESS = 0  # predicted and updated
    PREDICT_ONLY = 1  # no measurement given: predicted only
    INPUT_INVALID = 2  # measurement given but non-finite, wrong shape or variance <= 0: predicted only
    RESET = 3  # state became non-finite: restarted from the last finite state, covariance inflated


class Ekf:
    """Stateful planar EKF for the runtime and evaluation (one 50 Hz step per call).

    Parameters
    ----------
    x0 : (8,) initial state (default zeros: at the origin, heading east, at rest); with
        ``calibration`` also (11,) (an (8,) state starts the calibration states at zero).
    P0 : (8, 8) initial covariance (default :func:`default_initial_covariance`); with
        ``calibration`` also (11, 11) (an (8, 8) one is extended with :class:`CalibrationStd`).
    Q : (8, 8) process noise for ``dt_s`` (default :func:`default_process_noise`); with
        ``calibration`` extended with :class:`CalibrationNoise` unless it is (11, 11).
    dt_s : step [s].
    calibration : carry the calibration states (:class:`prml2_edge.schema.CalState`) and accept the
        raw cues (:meth:`update_cues`) and standstill updates (:meth:`update_standstill`).
    """

    # Diagnostics (benchmarks/innovation_check.py): a list here gets, per step_with_cues update, ``((model z, yaw
    # cue, wheel cue given), innovation (m,), diag(H P H^T + R) (m,))``; None (the default): nothing is kept.
    innovation_log: list | None = None

    def __init__(
        self,
        x0: np.ndarray | None = None,
        P0: np.ndarray | None = None,
        Q: np.ndarray | None = None,
        dt_s: float = schema.DT_S,
        calibration: bool = False,
        cal_noise: CalibrationNoise | None = None,
        cal_std: CalibrationStd | None = None,
    ) -> None:
        if not (dt_s > 0.0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        self.dt_s = float(dt_s)
        self.calibration = bool(calibration)
        self.dim = FULL_DIM if self.calibration else STATE_DIM
        self.cal_std = cal_std or CalibrationStd()
        cal_noise = cal_noise or CalibrationNoise()
        self.model_bias_decay = cal_noise.decay(self.dt_s) if self.calibration else 1.0
        self.model_offset_share = float(cal_noise.model_offset_share)
        q = default_process_noise(self.dt_s) if Q is None else np.array(Q, dtype=np.float64)
        if self.calibration:
            q = extend_calibrated(q, cal_noise.diagonal(self.dt_s))
        if q.shape != (self.dim, self.dim):
            raise ValueError(f"Q must have shape ({self.dim}, {self.dim}), got {q.shape}")
        self.Q = q
        # per-step templates (the hot path fills the entries that change instead of building them)
        self._eye = np.eye(self.dim)
        self._F = np.eye(self.dim)  # process_jacobian: the entries _F_ROWS, _F_COLS change per step
        self._F_flat = np.ravel_multi_index((_F_ROWS, _F_COLS), self._F.shape)  # those entries, flat
        if self.calibration:
            self._F[_B_MODEL, _B_MODEL] = self.model_bias_decay
            # only H[v_x, v_x] = 1 + scale changes
            self._H_model = model_measurement(np.zeros(FULL_DIM), self.model_offset_share)[1]
            self._H_stack: dict[tuple[bool, bool, bool], np.ndarray] = {}  # model z and cues stacked (_stacked)
        self.x: np.ndarray = np.zeros(self.dim)
        self.P: np.ndarray = np.eye(self.dim)
        self.n_resets = 0
        self.reset(x0, P0)

    def reset(self, x0: np.ndarray | None = None, P0: np.ndarray | None = None) -> None:
        """Restart from ``x0`` / ``P0`` (defaults: zeros / :func:`default_initial_covariance`; see the class)."""
        x = np.zeros(self.dim)
        if x0 is not None:
            x0 = _check_state(x0)
            if x0.shape[0] > self.dim:
                raise ValueError(f"state must have shape ({self.dim},), got {x0.shape}")
            x[: x0.shape[0]] = x0
        p = default_initial_covariance() if P0 is None else np.array(P0, dtype=np.float64)
        if self.calibration and p.shape == (STATE_DIM, STATE_DIM):
            p = extend_calibrated(p, self.cal_std.diagonal())
        if p.shape != (self.dim, self.dim):
            raise ValueError(f"P0 must have shape ({self.dim}, {self.dim}), got {p.shape}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(p))):
            raise ValueError("x0 and P0 must be finite")
        self.x, self.P = x, symmetrize(p)
        self._P0 = self.P.copy()
        self._last_good = (self.x.copy(), self.P.copy())

    def _predict(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`predict` of this filter's state: the same numbers (same operations, in the same order),
        with the Jacobian filled into a kept template and the state arithmetic on Python floats."""
        dt = self.dt_s
        half_dt2 = 0.5 * dt * dt
        xs = self.x.tolist()
        p_x, p_y, psi, omega, v_x, v_y, a_x, a_y = xs[:STATE_DIM]
        c, s = math.cos(psi), math.sin(psi)
        r = np.array([[c, -s], [s, c]])
        rd_x, rd_y = (r @ np.array([v_x * dt + a_x * half_dt2, v_y * dt + a_y * half_dt2])).tolist()
        xs[:STATE_DIM] = [p_x + rd_x, p_y + rd_y, psi + omega * dt, omega, v_x + a_x * dt, v_y + a_y * dt, a_x, a_y]
        if self.calibration:
            xs[_B_MODEL] *= self.model_bias_decay
        c_dt, s_dt, c_h, s_h = c * dt, s * dt, c * half_dt2, s * half_dt2
        f = self._F
        f.flat[self._F_flat] = (-rd_y, c_dt, -s_dt, c_h, -s_h, rd_x, s_dt, c_dt, s_h, c_h, dt, dt, dt)
        p_new = f @ self.P @ f.T + self.Q
        return np.array(xs), 0.5 * (p_new + p_new.T)

    def _update_model(self, x: np.ndarray, p: np.ndarray, z: np.ndarray,
                      z_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model's z: :func:`update_model_calibrated` (with the kept H template) or :func:`update`."""
        if not self.calibration:
            return _update_selected(x, p, _Z_IDX, z - x[_Z_IDX], z_var)
        return update_linear(x, p, *self._stacked(x, (z, z_var), None, None, []), self._eye)

    def _stacked(self, x: np.ndarray, zv: tuple[np.ndarray, np.ndarray] | None, yaw_rate: float | None,
                 wheel_speed: float | None, cue_var: list[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(H, innovation, variance)`` of the model's z (``zv``, when valid; :func:`model_measurement`) stacked
        over the raw cues given (:func:`cue_measurement`), in that order, with the same numbers, filled into a kept
        H template per combination instead of built and joined."""
        omega, v_x, v_y, a_x, a_y = x[_OMEGA:_AY + 1].tolist()
        b_yaw, k_wheel, b_model = x[_B_YAW:].tolist()
        key = (zv is not None, yaw_rate is not None, wheel_speed is not None)
        h = self._H_stack.get(key)
        if h is None:
            rows = ([self._H_model] if key[0] else []) + [cue_measurement(x, yaw_rate, wheel_speed)[1]]
            h = self._H_stack[key] = np.concatenate(rows)
        innov: list[float] = []
        var: list[float] = []
        if zv is not None:
            z, z_var = zv
            h[schema.Z.V_X, _VX] = 1.0 + k_wheel
            hx = [0.0] * MEAS_DIM
            hx[schema.Z.V_X], hx[schema.Z.V_Y], hx[schema.Z.A_X], hx[schema.Z.A_Y] = \
                (1.0 + k_wheel) * v_x, v_y, a_x, a_y
            hx[schema.Z.OMEGA_Z] = omega + self.model_offset_share * b_yaw + b_model
            innov = [zi - hi for zi, hi in zip(z.tolist(), hx, strict=True)]
            var = z_var.tolist()
        if yaw_rate is not None:
            innov.append(yaw_rate - (omega + b_yaw))
        if wheel_speed is not None:
            h[len(innov), _VX] = 1.0 + k_wheel
            innov.append(wheel_speed - (1.0 + k_wheel) * v_x)
        return h, np.array(innov), np.array(var + cue_var)

    def _commit(self, x: np.ndarray, p: np.ndarray, status: StepStatus) -> StepStatus:
        if all(map(math.isfinite, x.tolist())) and np.isfinite(p).all():  # (x: 11 values, cheaper as floats)
            self.x, self.P = x, p
            self._last_good = (x.copy(), p.copy())
            return status
        x_good, p_good = self._last_good
        self.x = x_good.copy()
        self.P = np.diag(np.maximum(np.diag(p_good), np.diag(self._P0)) * RESET_COV_INFLATION)
        self.n_resets += 1
        return StepStatus.RESET

    def step(self, z: np.ndarray | None = None, z_var: np.ndarray | None = None) -> StepStatus:
        """Advance one step ``dt_s``: predict, then update with ``z`` (5,) / ``z_var`` (5,) if valid.

        ``z = [v_x, v_y, a_x, a_y, omega_z]`` (schema order, vehicle frame), ``z_var`` its
        variances. Never raises on bad data: see :class:`StepStatus`.
        """
        with np.errstate(all="ignore"):
            x, p = self._predict()
            if z is None and z_var is None:
                return self._commit(x, p, StepStatus.PREDICT_ONLY)
            zv = _valid_z(z, z_var)
            if zv is None:
                return self._commit(x, p, StepStatus.INPUT_INVALID)
            try:
                x, p = self._update_model(x, p, *zv)
            except np.linalg.LinAlgError:
                x = np.full(self.dim, np.nan)  # cannot happen for finite P; handled as a reset
            return self._commit(x, p, StepStatus.SUCCESS)

    def step_with_cues(self, z: np.ndarray | None, z_var: np.ndarray | None, yaw_rate: float | None = None,
                       yaw_var: float = 1.0, wheel_speed: float | None = None,
                       wheel_var: float = 1.0) -> tuple[StepStatus, bool]:
        """:meth:`step` and :meth:`update_cues` in one Kalman update (the runtime's hot path).

        Predict, then the model's z (when valid) and the raw cues given stacked into one measurement. R is
        diagonal, so this is the estimate of the two updates in turn except that the cue rows are linearised
        at the prediction instead of at the model-updated state (they depend on it only through the wheel
        scale, which the model's z does not measure: the same state within 1e-9 in the tests). One Cholesky
        of 7 x 7 instead of 5 x 5 and 2 x 2, one Joseph form and one commit instead of two.

        Returns ``(status, cues_fused)``: ``status`` as :meth:`step` would return it, ``cues_fused`` whether
        the cues entered (all of them finite with variance > 0, as :meth:`update_cues` requires).
        """
        if not self.calibration:
            raise RuntimeError("raw cues need the calibration states: Ekf(calibration=True)")
        cues, usable = _given_cues(yaw_rate, yaw_var, wheel_speed, wheel_var)
        cues_ok = bool(cues) and usable
        with np.errstate(all="ignore"):
            x, p = self._predict()
            zv = _valid_z(z, z_var)
            status = StepStatus.PREDICT_ONLY if z is None and z_var is None else \
                StepStatus.INPUT_INVALID if zv is None else StepStatus.SUCCESS
            if zv is None and not cues_ok:
                return self._commit(x, p, status), False
            h, innovation, var = self._stacked(x, zv, yaw_rate if cues_ok else None, wheel_speed if cues_ok else None,
                                               [v for _, v in cues] if cues_ok else [])
            if self.innovation_log is not None:
                self.innovation_log.append(((zv is not None, cues_ok and yaw_rate is not None,
                                             cues_ok and wheel_speed is not None), innovation.copy(),
                                            np.einsum("ij,jk,ik->i", h, p, h) + var))
            try:
                x, p = _update_linear(x, p, h, innovation, var, self._eye)  # (inside errstate already)
            except np.linalg.LinAlgError:
                x = np.full(self.dim, np.nan)
            committed = self._commit(x, p, status)
            return committed, cues_ok and committed is not StepStatus.RESET

    def fuse_pose(
        self,
        pos_xy: np.ndarray,
        pos_var: np.ndarray | float,
        yaw_rad: float | None = None,
        yaw_var: float | None = None,
        course: bool = False,
    ) -> StepStatus:
        """Fuse a pose fix at the current time (no prediction); see :func:`update_pose` (``course``: the angle is
        the course over ground, not the yaw)."""
        with np.errstate(all="ignore"):
            try:
                pos = np.asarray(pos_xy, dtype=np.float64).reshape(2)
                var = np.broadcast_to(np.asarray(pos_var, dtype=np.float64), (2,))
            except ValueError:
                return StepStatus.INPUT_INVALID
            if yaw_rad is not None:
                if yaw_var is None or not (math.isfinite(yaw_rad) and math.isfinite(yaw_var) and yaw_var > 0.0):
                    return StepStatus.INPUT_INVALID
            if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(var)) and np.all(var > 0.0)):
                return StepStatus.INPUT_INVALID
            try:
                x, p = update_pose(self.x, self.P, pos, var, yaw_rad, yaw_var, course)
            except np.linalg.LinAlgError:
                x, p = np.full(self.dim, np.nan), self.P
            return self._commit(x, p, StepStatus.SUCCESS)

    def update_cues(self, yaw_rate: float | None = None, yaw_var: float = 1.0, wheel_speed: float | None = None,
                    wheel_var: float = 1.0) -> StepStatus:
        """Fuse the raw cues at the current time (no prediction): CAN yaw rate [rad/s] and rear-axle
        wheel speed [m/s] through the calibration states (:func:`cue_measurement`), variances > 0.

        Only with ``calibration``; ``PREDICT_ONLY`` when neither cue is given.
        """
        if not self.calibration:
            raise RuntimeError("raw cues need the calibration states: Ekf(calibration=True)")
        cues, usable = _given_cues(yaw_rate, yaw_var, wheel_speed, wheel_var)
        if not cues:
            return StepStatus.PREDICT_ONLY
        if not usable:
            return StepStatus.INPUT_INVALID
        with np.errstate(all="ignore"):
            innovation, h = cue_measurement(self.x, yaw_rate, wheel_speed)
            var = np.array([v for _, v in cues])
            try:
                x, p = update_linear(self.x, self.P, h, innovation, var, self._eye)
            except np.linalg.LinAlgError:
                x, p = np.full(self.dim, np.nan), self.P
            return self._commit(x, p, StepStatus.SUCCESS)

    def update_standstill(self, var: float, omega_var: float | None = None) -> StepStatus:
        """Zero-velocity and zero-rotation update: ``v = a = 0`` with variance ``var`` [SI^2] each and
        ``omega_z = 0`` with ``omega_var`` [rad^2/s^2] (default ``var``).

        With the raw yaw-rate cue at the same step this makes the yaw-rate offset observable without GNSS.
        """
        omega_var = var if omega_var is None else omega_var
        if not (math.isfinite(var) and var > 0.0 and math.isfinite(omega_var) and omega_var > 0.0):
            return StepStatus.INPUT_INVALID
        with np.errstate(all="ignore"):
            idx = _STANDSTILL_IDX
            meas_var = np.array([var, var, var, var, omega_var])
            try:
                x, p = _update_selected(self.x, self.P, idx, -self.x[idx], meas_var)
            except np.linalg.LinAlgError:
                x, p = np.full(self.dim, np.nan), self.P
            return self._commit(x, p, StepStatus.SUCCESS)

    def update_wheel_scale(self, scale: float, var: float) -> StepStatus:
        """A direct measurement of the wheel scale (GNSS distance against wheel distance, runtime/filter.py)."""
        return self._update_cal_state(_K_WHEEL, scale, var)

    def update_yaw_offset(self, offset: float, var: float) -> StepStatus:
        """A direct measurement of the CAN yaw-rate offset [rad/s] (the other cues' opinion, runtime/cue_offset.py)."""
        return self._update_cal_state(_B_YAW, offset, var)

    def _update_cal_state(self, index: int, value: float, var: float) -> StepStatus:
        if not self.calibration:
            raise RuntimeError("no calibration states: Ekf(calibration=True)")
        if not (math.isfinite(value) and math.isfinite(var) and var > 0.0):
            return StepStatus.INPUT_INVALID
        with np.errstate(all="ignore"):
            idx = np.array([index], dtype=np.intp)
            x, p = _update_selected(self.x, self.P, idx, np.array([value - self.x[index]]), np.array([var]))
            return self._commit(x, p, StepStatus.SUCCESS)

    @property
    def cal(self) -> np.ndarray:
        """The calibration states (3,) (:class:`prml2_edge.schema.CalState`; empty without ``calibration``)."""
        return self.x[STATE_DIM:].copy()

    @property
    def cal_cov(self) -> np.ndarray:
        """Their covariance (3, 3) (empty without ``calibration``)."""
        return self.P[STATE_DIM:, STATE_DIM:].copy()

    def set_calibration(self, cal: np.ndarray, cal_cov: np.ndarray) -> None:
        """Start the calibration states at ``cal`` (3,) with covariance ``cal_cov`` (3, 3) (a restored file)."""
        cal = np.asarray(cal, dtype=np.float64).reshape(CalState.DIM)
        cov = np.asarray(cal_cov, dtype=np.float64).reshape(CalState.DIM, CalState.DIM)
        if not self.calibration:
            raise RuntimeError("no calibration states: Ekf(calibration=True)")
        self.x[CalState.ALL] = cal
        self.P[CalState.ALL, :] = 0.0
        self.P[:, CalState.ALL] = 0.0
        self.P[CalState.ALL, CalState.ALL] = symmetrize(cov)
        self._last_good = (self.x.copy(), self.P.copy())

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(p_x [m], p_y [m], psi [rad])``, world frame; ``psi`` unwrapped (see :func:`wrap_angle`)."""
        return float(self.x[_PX]), float(self.x[_PY]), float(self.x[_YAW])

    @property
    def pose_std(self) -> tuple[float, float]:
        """``(pos_std_m, yaw_std_rad)``: ``sqrt(var p_x + var p_y)`` (radial RMS) and ``sqrt(var psi)``."""
        return float(math.sqrt(self.P[_PX, _PX] + self.P[_PY, _PY])), float(math.sqrt(self.P[_YAW, _YAW]))


# Share of a 2D Gaussian inside its k-sigma ellipse, 1 - exp(-k^2 / 2): 39.3, 86.5, 98.9 %.
COVERAGE_IDEAL_PCT = {k: 100.0 * (1.0 - math.exp(-k * k / 2.0)) for k in (1, 2, 3)}


def checked_gaussian(values, cov, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(values (n,), cov (n, n))`` as float arrays, the covariance made symmetric; ValueError on a wrong shape, a
    non-finite value, or a covariance that is not positive (semi-)definite (what a calibration file may hold)."""
    values = np.asarray(values, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    if values.shape != (n,) or cov.shape != (n, n):
        raise ValueError(f"want {n} values and a {n}x{n} covariance")
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0.0)
            and np.linalg.eigvalsh(cov)[0] >= -1e-9 * float(np.max(np.diag(cov)))):
        raise ValueError("non-finite values or a covariance that is not positive")
    return values, cov


def mahalanobis2(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances (n,) of 2D errors (n, 2) under covariances (n, 2, 2) (NaN where singular)."""
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = a * c - b * b
    with np.errstate(all="ignore"):
        m2 = (c * err[:, 0] ** 2 - 2 * b * err[:, 0] * err[:, 1] + a * err[:, 1] ** 2) / det
    return np.where(det > 0, m2, np.where(np.hypot(err[:, 0], err[:, 1]) == 0, 0.0, np.nan))


def coverage_pct(m2: np.ndarray) -> dict[str, float]:
    """Share of steps [%] inside the 1/2/3-sigma ellipses from squared Mahalanobis distances (NaN ignored).

    A consistent filter gives :data:`COVERAGE_IDEAL_PCT`; less means the reported uncertainty is too small.
    """
    m2 = np.asarray(m2, dtype=np.float64)
    m2 = m2[np.isfinite(m2)]
    if not m2.size:
        return {}
    return {f"coverage_{k}sigma_pct": float(100.0 * np.mean(m2 <= k * k)) for k in (1, 2, 3)}


__all__ = [
    "COVERAGE_IDEAL_PCT",
    "CalibrationNoise",
    "CalibrationStd",
    "Ekf",
    "FULL_DIM",
    "InitialStd",
    "JITTER_GROWTH",
    "JITTER_MAX_REL",
    "JITTER_REL",
    "MEAS_DIM",
    "ProcessNoise",
    "RESET_COV_INFLATION",
    "STATE_DIM",
    "StepStatus",
    "cholesky_jittered",
    "course_measurement",
    "coverage_pct",
    "cue_measurement",
    "default_initial_covariance",
    "default_process_noise",
    "extend_calibrated",
    "jitter_schedule",
    "mahalanobis2",
    "measurement_matrix",
    "model_measurement",
    "predict",
    "process_jacobian",
    "process_model",
    "rotation",
    "symmetrize",
    "update",
    "update_linear",
    "update_model_calibrated",
    "update_pose",
    "wrap_angle",
]
