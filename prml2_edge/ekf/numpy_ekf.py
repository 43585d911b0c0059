"""Planar EKF in NumPy (float64) for the edge runtime and evaluation. No torch.

State ``x = [p_x, p_y, psi, omega_z, v_x, v_y, a_x, a_y]`` (:class:`prml2_edge.schema.EkfState`):
position [m] in the world frame (x east, y north), heading ``psi`` [rad] counter-clockwise from
east (kept unwrapped inside the filter), yaw rate [rad/s], velocity [m/s] and acceleration
[m/s^2] in the vehicle frame (x forward, y left). ``R(psi) = [[cos, -sin], [sin, cos]]`` maps
the vehicle frame to the world frame.

Equations, named as in the paper (``../shared/seed/prml2_paper.tex.txt``):

* Eq. (state_prediction), restricted to the plane (method.md)::

      p     <- p + R(psi) v dt + 1/2 R(psi) a dt^2
      psi   <- psi + omega dt
      omega <- omega
      v     <- v + a dt
      a     <- a

* its analytic Jacobian ``F`` (the paper's ``F_t``, planar);
* prediction ``P <- F P F^T + Q``;
* Eq. (measurement_vector): ``z = [v_x, v_y, a_x, a_y, omega_z]`` (schema order), ``H`` selects
  :data:`prml2_edge.schema.Z_TO_EKF_INDEX`, ``R_t = diag(z_var)``;
* Eq. (kalman stable): gain ``K = P H^T S^-1`` from a Cholesky solve, Joseph-form covariance.

The torch twin :mod:`prml2_edge.training.ekf_torch` uses the same names and equations; a float64
parity test runs both over thousands of steps.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.schema import CalState, EkfState

STATE_DIM = EkfState.DIM  # 8
FULL_DIM = CalState.FULL_DIM  # 11: with the calibration states (Ekf(calibration=True))
MEAS_DIM = schema.NUM_STATES  # 5
_Z_IDX = np.asarray(schema.Z_TO_EKF_INDEX, dtype=np.intp)  # H as a selection of state indices
_POS_IDX = np.arange(EkfState.POS.start, EkfState.POS.stop, dtype=np.intp)  # (2,)
_PX, _PY = EkfState.POS_X.start, EkfState.POS_Y.start  # 0, 1
_YAW = EkfState.YAW.start  # 2
_OMEGA = EkfState.OMEGA_Z.start  # 3
_VX, _VY = EkfState.VEL.start, EkfState.VEL.start + 1  # 4, 5
_AX, _AY = EkfState.ACC.start, EkfState.ACC.start + 1  # 6, 7
_VEL = EkfState.VEL
_ACC = EkfState.ACC
_B_YAW = CalState.YAW_RATE_OFFSET.start  # 8
_K_WHEEL = CalState.WHEEL_SCALE.start  # 9
_B_MODEL = CalState.MODEL_OMEGA_BIAS.start  # 10
# process_jacobian's entries that change per step, in the order Ekf._predict fills them:
# dp/dpsi (2), dp/dv (2x2), dp/da (2x2) row by row, then dpsi/domega, dv_x/da_x, dv_y/da_y
_F_ROWS = np.array([_PX, _PX, _PX, _PX, _PX, _PY, _PY, _PY, _PY, _PY, _YAW, _VX, _VY], dtype=np.intp)
_F_COLS = np.array([_YAW, _VX, _VY, _AX, _AY, _YAW, _VX, _VY, _AX, _AY, _OMEGA, _AX, _AY], dtype=np.intp)

# Cholesky of the innovation covariance S: S = H P H^T + R_t is positive definite in exact
# arithmetic (R_t > 0); rounding can break that when variances span many decades. Then a
# diagonal jitter of JITTER_REL * eps * mean|diag S| is added and grown by JITTER_GROWTH until
# the factorisation succeeds, as long as it stays below JITTER_MAX_REL * mean|diag S| (both
# implementations, identically; see cholesky_jittered).
JITTER_REL = 10.0
JITTER_GROWTH = 100.0
JITTER_MAX_REL = 1.0


def jitter_schedule(eps: float) -> list[float]:
    """Relative jitters tried in turn for a dtype with machine epsilon ``eps`` (8 for float64, 3 for float32)."""
    rel, out = JITTER_REL * eps, []
    while rel <= JITTER_MAX_REL:
        out.append(rel)
        rel *= JITTER_GROWTH
    return out

# The hot path calls the LAPACK gufuncs behind np.linalg.cholesky / np.linalg.solve directly: the same
# routines, so the same numbers, without the wrappers' checks and error-state set-up (~5 us a call, most of
# a 5x5 factorisation). They return NaN where the wrappers raise; _cholesky_fast then takes the public path
# (cholesky_jittered), so failures are handled exactly as before. Where NumPy has no such module the public
# functions are used.
try:
    from numpy.linalg import _umath_linalg

    def _cholesky_lo(s: np.ndarray) -> np.ndarray:
        return _umath_linalg.cholesky_lo(s, signature="d->d")

    def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return _umath_linalg.solve(a, b, signature="dd->d")
except (ImportError, AttributeError):  # pragma: no cover - other NumPy layouts
    _cholesky_lo = np.linalg.cholesky
    _solve = np.linalg.solve


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


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time process noise of the planar constant-acceleration model (tunable).

    The model is driven by white noise whose power spectral densities (PSD) are:

    * ``jerk_psd_m2ps5`` [m^2/s^5]: white jerk on ``(a_x, a_y)`` (each axis). Discretised as the
      standard constant-acceleration block ``q_j [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` on ``(v, a)``
      per axis. 2.0 m^2/s^5 lets the acceleration change by ~1.4 m/s^2 within 1 s (1 sigma), a
      brisk but ordinary driver input; the pseudo-measurements arrive every 20 ms and carry the
      fast content.
    * ``yaw_accel_psd_rad2ps3`` [rad^2/s^3]: white yaw acceleration on ``omega_z``, block
      ``q_w [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` on ``(psi, omega_z)``. 0.1 rad^2/s^3 lets the yaw
      rate change by ~0.3 rad/s within 1 s (1 sigma), e.g. entering a roundabout.
    * ``pos_psd_m2ps`` [m^2/s]: white velocity error on each position axis, ``q_p dt``: slip and
      unmodelled motion not in the kinematic model. Position is never measured by the
      pseudo-measurements, so this only sets how fast the reported position uncertainty grows
      (and how much a GNSS fix moves the estimate); 0.01 m^2/s gives a 0.77 m (1 sigma) random
      walk over 60 s on top of the uncertainty propagated from heading and velocity.

    Cross-covariances between the world-frame position and the vehicle-frame velocity depend on
    the heading; they are left out so ``Q`` is a constant, positive semi-definite matrix.
    """

    jerk_psd_m2ps5: float = 2.0
    yaw_accel_psd_rad2ps3: float = 0.1
    pos_psd_m2ps: float = 0.01

    def matrix(self, dt_s: float = schema.DT_S) -> np.ndarray:
        """Discrete process noise ``Q`` (8, 8) [SI units of the state, squared] for step ``dt_s`` [s]."""
        if not (dt_s > 0.0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        for name in ("jerk_psd_m2ps5", "yaw_accel_psd_rad2ps3", "pos_psd_m2ps"):
            if not (getattr(self, name) >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        dt = float(dt_s)
        q = np.zeros((STATE_DIM, STATE_DIM))
        pos = np.arange(EkfState.POS.start, EkfState.POS.stop)
        q[pos, pos] = self.pos_psd_m2ps * dt
        blk = np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
        yaw_omega = np.array([_YAW, _OMEGA])
        q[np.ix_(yaw_omega, yaw_omega)] = self.yaw_accel_psd_rad2ps3 * blk
        for axis in range(2):
            va = np.array([_VEL.start + axis, _ACC.start + axis])
            q[np.ix_(va, va)] = self.jerk_psd_m2ps5 * blk
        return q


@dataclass(frozen=True)
class CalibrationNoise:
    """Random-walk PSDs of the calibration states (:class:`prml2_edge.schema.CalState`), tunable.

    * ``yaw_offset_psd_rad2ps3``: the CAN yaw-rate offset drifts (temperature) by ~0.03 deg/s in
      10 min (1 sigma) at the default 2.2e-11 rad^2/s^3;
    * ``wheel_scale_psd_ps``: the rolling radius changes with tyre temperature and pressure, ~0.1 %
      in 10 min at 1.7e-9 1/s;
    * ``model_bias_std_radps`` / ``model_bias_tau_s``: the model's omega_z error is slow (a per-window
      bias of 0.1-0.3 deg/s that lasts across windows on the validation split): a first-order
      Gauss-Markov process with this stationary sigma and correlation time (0.3 deg/s, 60 s; chosen on the
      validation split, issue 26). With ``model_offset_share`` 0 the gyro-minus-model difference then
      measures the CAN yaw-rate offset less this slow error: a standstill-calibrated offset (0.05 deg/s) is
      left alone and the heading follows the gyro, an unknown one (0.5 deg/s prior, no stop) is learned
      from the model to about this sigma.
    """

    yaw_offset_psd_rad2ps3: float = 2.2e-11
    wheel_scale_psd_ps: float = 1.7e-9
    model_bias_std_radps: float = 0.3 * schema.DEG_TO_RAD
    model_bias_tau_s: float = 60.0
    model_offset_share: float = 0.0  # how much of the CAN yaw-rate offset the model's omega_z carries

    def decay(self, dt_s: float = schema.DT_S) -> float:
        """``exp(-dt / tau)`` of the model bias over ``dt_s`` [s]."""
        if not self.model_bias_tau_s > 0.0:
            raise ValueError(f"model_bias_tau_s must be > 0, got {self.model_bias_tau_s!r}")
        return math.exp(-float(dt_s) / self.model_bias_tau_s)

    def diagonal(self, dt_s: float = schema.DT_S) -> np.ndarray:
        """Process-noise variances (3,) of the calibration states over ``dt_s`` [s]."""
        v = np.array([self.yaw_offset_psd_rad2ps3 * dt_s, self.wheel_scale_psd_ps * dt_s,
                      self.model_bias_std_radps**2 * (1.0 - self.decay(dt_s) ** 2)])
        if not np.all(v >= 0.0):
            raise ValueError("calibration process noise must be >= 0")
        return v


@dataclass(frozen=True)
class CalibrationStd:
    """One-sigma prior of the calibration states with no saved calibration (tunable), SI units.

    0.5 deg/s covers the offsets seen (simulator sigma 0.25 deg/s, a real RAV4 -0.41 deg/s);
    1 % for the rolling radius (tyre wear is ~3 % over a tyre's life: a saved calibration carries it);
    the model's window bias: its Gauss-Markov sigma.
    """

    yaw_offset_radps: float = 0.5 * schema.DEG_TO_RAD
    wheel_scale: float = 0.01
    model_bias_radps: float = 0.3 * schema.DEG_TO_RAD  # CalibrationNoise.model_bias_std_radps

    def diagonal(self) -> np.ndarray:
        std = np.array([self.yaw_offset_radps, self.wheel_scale, self.model_bias_radps])
        if not np.all(std > 0.0):
            raise ValueError("calibration standard deviations must be > 0")
        return std**2


def extend_calibrated(q_or_p: np.ndarray, cal_diag: np.ndarray) -> np.ndarray:
    """An (8, 8) ``Q`` or ``P`` extended to the calibrated layout (11, 11), ``cal_diag`` (3,) on the new diagonal."""
    m = np.asarray(q_or_p, dtype=np.float64)
    if m.shape == (FULL_DIM, FULL_DIM):
        return m.copy()
    if m.shape != (STATE_DIM, STATE_DIM):
        raise ValueError(f"expected a ({STATE_DIM}, {STATE_DIM}) matrix, got {m.shape}")
    out = np.zeros((FULL_DIM, FULL_DIM))
    out[:STATE_DIM, :STATE_DIM] = m
    out[CalState.ALL, CalState.ALL] = np.diag(np.asarray(cal_diag, dtype=np.float64))
    return out


@dataclass(frozen=True)
class InitialStd:
    """One-sigma initial uncertainty of each state component (tunable), SI units.

    The defaults suit a filter started from a known pose (ground truth at a window start, a GNSS
    fix) with dynamics from the first pseudo-measurement.
    """

    pos_m: float = 0.1
    yaw_rad: float = 0.01  # ~0.6 deg
    omega_radps: float = 0.05
    vel_mps: float = 0.5
    acc_mps2: float = 1.0

    def matrix(self) -> np.ndarray:
        """Diagonal ``P0`` (8, 8)."""
        std = np.empty(STATE_DIM)
        std[EkfState.POS] = self.pos_m
        std[EkfState.YAW] = self.yaw_rad
        std[EkfState.OMEGA_Z] = self.omega_radps
        std[EkfState.VEL] = self.vel_mps
        std[EkfState.ACC] = self.acc_mps2
        if not np.all(std > 0.0):
            raise ValueError("initial standard deviations must be > 0")
        return np.diag(std**2)


def default_process_noise(dt_s: float = schema.DT_S) -> np.ndarray:
    """Default ``Q`` (8, 8) for step ``dt_s`` [s]: :class:`ProcessNoise` with its documented PSDs."""
    return ProcessNoise().matrix(dt_s)


def default_initial_covariance() -> np.ndarray:
    """Default ``P0`` (8, 8): :class:`InitialStd` squared on the diagonal."""
    return InitialStd().matrix()


def measurement_matrix() -> np.ndarray:
    """``H`` (5, 8): selects ``z = [v_x, v_y, a_x, a_y, omega_z]`` from the state (Eq. measurement_vector)."""
    h = np.zeros((MEAS_DIM, STATE_DIM))
    h[np.arange(MEAS_DIM), _Z_IDX] = 1.0
    return h


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Wrap an angle [rad] to ``[-pi, pi)``."""
    return (np.asarray(angle_rad) + math.pi) % (2.0 * math.pi) - math.pi


def rotation(psi_rad: float) -> np.ndarray:
    """``R(psi)`` (2, 2): vehicle frame (x forward, y left) to world frame (x east, y north)."""
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    return np.array([[c, -s], [s, c]])


def _check_state(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape not in ((STATE_DIM,), (FULL_DIM,)):
        raise ValueError(f"state must have shape ({STATE_DIM},) or, calibrated, ({FULL_DIM},), got {x.shape}")
    return x


def process_model(x: np.ndarray, dt_s: float, model_bias_decay: float = 1.0) -> np.ndarray:
    """A-priori state ``f(x)`` (Eq. state_prediction, planar).

    Parameters
    ----------
    x : (8,) state, layout :class:`prml2_edge.schema.EkfState`, or (11,) with the calibration
        states (:class:`prml2_edge.schema.CalState`): the sensor errors are random walks (constant
        here), the model's omega_z bias a first-order Gauss-Markov process (``* model_bias_decay``).
    dt_s : step [s].
    model_bias_decay : ``exp(-dt / tau)`` of the model bias (1: a random walk).

    Returns
    -------
    predicted state, same shape; ``psi`` is not wrapped.
    """
    x = _check_state(x)
    dt = float(dt_s)
    rd = rotation(x[_YAW]) @ (x[_VEL] * dt + x[_ACC] * (0.5 * dt * dt))  # world-frame displacement R(psi) d
    out = x.copy()
    out[EkfState.POS] = x[EkfState.POS] + rd
    out[_YAW] = x[_YAW] + x[_OMEGA] * dt
    out[_VEL] = x[_VEL] + x[_ACC] * dt
    if x.shape[0] == FULL_DIM:
        out[_B_MODEL] = x[_B_MODEL] * model_bias_decay
    return out


def process_jacobian(x: np.ndarray, dt_s: float, model_bias_decay: float = 1.0) -> np.ndarray:
    """Analytic Jacobian ``F = df/dx`` (8, 8) of :func:`process_model` (the paper's ``F_t``, planar).

    Non-identity entries: ``dp/dpsi = dR/dpsi (v dt + a dt^2/2)``, ``dp/dv = R dt``,
    ``dp/da = R dt^2/2``, ``dpsi/domega = dt``, ``dv/da = dt I``.
    """
    x = _check_state(x)
    dt = float(dt_s)
    r = rotation(x[_YAW])
    rd = r @ (x[_VEL] * dt + x[_ACC] * (0.5 * dt * dt))  # R d
    f = np.eye(x.shape[0])
    f[_PX, _YAW] = -rd[1]  # dR/dpsi d = (-(R d)_y, (R d)_x)
    f[_PY, _YAW] = rd[0]
    f[EkfState.POS, _VEL] = r * dt
    f[EkfState.POS, _ACC] = r * (0.5 * dt * dt)
    f[_YAW, _OMEGA] = dt
    f[_VX, _AX] = dt
    f[_VY, _AY] = dt
    if x.shape[0] == FULL_DIM:
        f[_B_MODEL, _B_MODEL] = model_bias_decay
    return f


def symmetrize(p: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2``."""
    return 0.5 * (p + p.T)


def predict(x: np.ndarray, P: np.ndarray, Q: np.ndarray, dt_s: float,
            model_bias_decay: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """EKF prediction: ``x <- f(x)``, ``P <- F P F^T + Q`` (the paper's prediction step).

    Parameters
    ----------
    x : (8,) a-posteriori state at t-1.
    P : (8, 8) its covariance.
    Q : (8, 8) process noise for ``dt_s``.
    dt_s : step [s].

    Returns
    -------
    x, P : a-priori state (8,) and covariance (8, 8) at t.
    """
    f = process_jacobian(x, dt_s, model_bias_decay)
    x_new = process_model(x, dt_s, model_bias_decay)
    p_new = f @ P @ f.T + Q
    return x_new, symmetrize(p_new)


def cholesky_jittered(s: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of ``s`` (m, m), adding diagonal jitter if rounding broke definiteness.

    The jitters of :func:`jitter_schedule` (times ``mean|diag s|``) are tried in turn; if none
    succeeds (``s`` far from positive definite) the off-diagonal is dropped (``sqrt(diag s)``), so
    the result is finite for any finite ``s``. The torch twin does the same per batch element.
    """
    try:
        return np.linalg.cholesky(s)
    except np.linalg.LinAlgError:
        pass
    eye = np.eye(s.shape[0])
    diag = np.diag(s)
    tiny = np.finfo(np.float64).tiny
    scale = max(float(np.mean(np.abs(diag))), tiny)
    for rel in jitter_schedule(float(np.finfo(np.float64).eps)):
        try:
            return np.linalg.cholesky(s + (rel * scale) * eye)
        except np.linalg.LinAlgError:
            pass
    return np.diag(np.sqrt(np.maximum(diag, tiny)))


def _cholesky_fast(s: np.ndarray) -> np.ndarray:
    """:func:`cholesky_jittered` with the plain factorisation tried first through the bare gufunc (same
    numbers); a failed one (NaN-filled) takes :func:`cholesky_jittered` itself. Call under ``np.errstate``
    ignoring invalid values."""
    try:
        chol = _cholesky_lo(s)
    except np.linalg.LinAlgError:  # the public fallback of _cholesky_lo raises
        return cholesky_jittered(s)
    if chol[-1, -1] != chol[-1, -1]:  # NaN: the factorisation failed (the gufunc fills all of it)
        return cholesky_jittered(s)
    return chol


def _update_selected(
    x: np.ndarray, P: np.ndarray, idx: np.ndarray, innovation: np.ndarray, meas_var: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update for a measurement that selects state components ``idx`` (Eq. kalman stable).

    ``H`` is a selection, so ``H P = P[idx]`` and ``H P H^T = P[idx][:, idx]`` exactly.
    """
    hp = P[idx, :]  # (m, 8) = H P
    s = hp[:, idx] + np.diag(meas_var)  # (m, m) innovation covariance S = H P H^T + R_t
    with np.errstate(invalid="ignore"):
        chol = _cholesky_fast(s)
        # K^T = S^-1 H P via two triangular solves (no explicit inverse; S and P symmetric).
        k_t = _solve(chol.T, _solve(chol, hp))  # (m, 8)
    k = k_t.T  # (8, m)
    x_new = x + k @ innovation
    # Joseph form P = (I - K H) P (I - K H)^T + K R_t K^T. Unlike (I - K H) P it stays symmetric
    # positive semi-definite under rounding and for a sub-optimal K (jitter, float32), which keeps
    # long sequences and backpropagation through them stable. With H a selection:
    #   A P = P - K (H P);  (A P) A^T = A P - (A P)[:, idx] K^T.
    ap = P - k @ hp
    p_new = ap - ap[:, idx] @ k_t + (k * meas_var) @ k_t
    return x_new, symmetrize(p_new)


def update_linear(
    x: np.ndarray, P: np.ndarray, h: np.ndarray, innovation: np.ndarray, meas_var: np.ndarray,
    eye: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with a dense (linearised) ``H`` (m, n): the raw cues and the calibrated model z.

    Same Cholesky gain and Joseph form as the selection update; ``innovation = y - h(x)`` (m,),
    ``meas_var`` (m,) the diagonal of ``R``; ``eye`` an (n, n) identity to use (the filter keeps one).
    """
    with np.errstate(invalid="ignore"):
        return _update_linear(x, P, h, innovation, meas_var, eye)


def _update_linear(x: np.ndarray, P: np.ndarray, h: np.ndarray, innovation: np.ndarray, meas_var: np.ndarray,
                   eye: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`update_linear` for a caller that already ignores NumPy's invalid-value warnings (the hot path)."""
    hp = h @ P  # (m, n)
    s = hp @ h.T
    s.flat[:: s.shape[0] + 1] += meas_var  # + diag(meas_var), without building it
    chol = _cholesky_fast(s)
    k_t = _solve(chol.T, _solve(chol, hp))  # (m, n) = S^-1 H P
    k = k_t.T
    x_new = x + k @ innovation
    a = (np.eye(P.shape[0]) if eye is None else eye) - k @ h
    p_new = a @ P @ a.T + (k * meas_var) @ k_t
    return x_new, symmetrize(p_new)


def model_measurement(x: np.ndarray, offset_share: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``h(x)`` (5,) and its Jacobian ``H`` (5, 11) of the model's z in the calibrated layout.

    The model reads the same sensors as the raw cues, so it inherits their slow errors (measured on a
    drive it never saw with a -0.4 deg/s yaw offset and wheels 0.8 % fast: its omega_z was 0.24 deg/s
    low and its v_x 0.7 % high): ``v_x`` reads ``(1 + scale) v_x``, ``omega_z`` reads
    ``omega_z + offset_share * offset + model_bias``; ``v_y``, ``a_x``, ``a_y`` as the plain selection.
    ``offset_share`` is how much of the CAN yaw-rate offset the model's omega_z carries (1: all of it, so the
    model can never tell the filter the offset; 0: none, so the gyro-minus-model difference measures the offset
    less the model's own slow error, :class:`CalibrationNoise`). The torch twin
    (``training/ekf_torch.update_model_calibrated``) takes the same argument; the runtime's :class:`Ekf` passes
    :attr:`CalibrationNoise.model_offset_share` (0) and keeps its own H template (:meth:`Ekf._update_model`).
    """
    h = np.zeros((MEAS_DIM, FULL_DIM))
    h[np.arange(MEAS_DIM), _Z_IDX] = 1.0
    hx = x[_Z_IDX].copy()
    vx_row, w_row = schema.Z.V_X, schema.Z.OMEGA_Z
    h[vx_row, _VX] = 1.0 + x[_K_WHEEL]  # the scale is a known correction here (see cue_measurement)
    hx[vx_row] = (1.0 + x[_K_WHEEL]) * x[_VX]
    h[w_row, _B_YAW] = offset_share
    h[w_row, _B_MODEL] = 1.0
    hx[w_row] = x[_OMEGA] + offset_share * x[_B_YAW] + x[_B_MODEL]
    return hx, h


def update_model_calibrated(x: np.ndarray, P: np.ndarray, z: np.ndarray, z_var: np.ndarray,
                            offset_share: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The model's pseudo-measurement ``z`` (5,) in the calibrated layout (:func:`model_measurement`)."""
    hx, h = model_measurement(x, offset_share)
    return update_linear(x, P, h, z - hx, z_var)


def cue_measurement(x: np.ndarray, yaw_rate: float | None, wheel_speed: float | None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Raw-cue model ``h(x)`` and its Jacobian (calibrated layout) for the cues given (None: absent).

    * CAN yaw rate: ``h = omega_z + offset`` (linear);
    * rear-axle wheel speed: ``h = (1 + scale) v_x``, ``dh/dv_x = 1 + scale``; the scale enters as a
      known correction (its Jacobian column is 0): the model's and the wheels' speed pin ``(1 + scale) v_x``
      every step, and any acceleration error would leak into the scale (measured: -1.4 % against a true
      +0.8 % while the car accelerated). The scale is learned from :meth:`Ekf.update_wheel_scale` only.

    Returns ``(innovation (m,), H (m, 11))`` with ``m`` the number of cues given.
    """
    omega, vx, b_yaw, k_wheel = float(x[_OMEGA]), float(x[_VX]), float(x[_B_YAW]), float(x[_K_WHEEL])
    m = (yaw_rate is not None) + (wheel_speed is not None)
    h = np.zeros((m, FULL_DIM))
    innov = []
    if yaw_rate is not None:
        h[0, _OMEGA] = h[0, _B_YAW] = 1.0
        innov.append(yaw_rate - (omega + b_yaw))
    if wheel_speed is not None:
        h[m - 1, _VX] = 1.0 + k_wheel
        innov.append(wheel_speed - (1.0 + k_wheel) * vx)
    return np.array(innov, dtype=np.float64), h


# Standstill: v_x, v_y, a_x, a_y and omega_z are zero (the zero-velocity / zero-rotation update).
_STANDSTILL_IDX = np.array([_VX, _VY, _AX, _AY, _OMEGA], dtype=np.intp)


def update(x: np.ndarray, P: np.ndarray, z: np.ndarray, z_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """EKF update with a pseudo-measurement of the dynamic state (Eqs. measurement_vector, kalman stable).

    Parameters
    ----------
    x : (8,) a-priori state.
    P : (8, 8) a-priori covariance.
    z : (5,) measurement ``[v_x, v_y, a_x, a_y, omega_z]`` [m/s, m/s^2, rad/s], vehicle frame.
    z_var : (5,) its variances (``R_t = diag(z_var)``), each > 0.

    Returns
    -------
    x, P : a-posteriori state (8,) and covariance (8, 8).
    """
    z = np.asarray(z, dtype=np.float64)
    z_var = np.asarray(z_var, dtype=np.float64)
    if z.shape != (MEAS_DIM,) or z_var.shape != (MEAS_DIM,):
        raise ValueError(f"z and z_var must have shape ({MEAS_DIM},), got {z.shape} and {z_var.shape}")
    return _update_selected(x, P, _Z_IDX, z - x[_Z_IDX], z_var)


def update_pose(
    x: np.ndarray,
    P: np.ndarray,
    pos_xy: np.ndarray,
    pos_var: np.ndarray | float,
    yaw_rad: float | None = None,
    yaw_var: float | None = None,
    course: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse a pose fix (GNSS): position, optionally heading; same Cholesky/Joseph update.

    Parameters
    ----------
    x, P : (8,), (8, 8) a-priori state and covariance.
    pos_xy : (2,) position [m], world frame (x east, y north).
    pos_var : scalar or (2,) position variance [m^2], > 0.
    yaw_rad : heading [rad], counter-clockwise from east; any branch (the innovation is wrapped
        to [-pi, pi), so the filter's unwrapped ``psi`` stays continuous).
    yaw_var : heading variance [rad^2], > 0; required with ``yaw_rad``.
    course : ``yaw_rad`` is the course over ground (the direction the car moves: what a single-antenna receiver's
        NMEA RMC course and gpsd's ``track`` are), ``psi + atan2(v_y, v_x)``, not the car's yaw. The sideslip
        angle between them is 2-4 deg rms on the simulated drives and over 10 deg in tight turns.
    """
    pos_xy = np.asarray(pos_xy, dtype=np.float64).reshape(2)
    var = np.broadcast_to(np.asarray(pos_var, dtype=np.float64), (2,)).copy()
    innovation = pos_xy - x[_POS_IDX]
    idx = _POS_IDX
    if yaw_rad is not None:
        if yaw_var is None:
            raise ValueError("yaw_var is required with yaw_rad")
        idx = np.append(_POS_IDX, _YAW)
        var = np.append(var, float(yaw_var))
    if not np.all(var > 0.0):
        raise ValueError("pose variances must be > 0")
    if yaw_rad is not None and course:
        return _update_course(x, P, pos_xy, var, float(yaw_rad))
    if yaw_rad is not None:
        innovation = np.append(innovation, wrap_angle(float(yaw_rad) - x[_YAW]))
    return _update_selected(x, P, idx, innovation, var)


def course_measurement(x: np.ndarray) -> tuple[float, np.ndarray]:
    """``h(x) = psi + atan2(v_y, v_x)``, the course over ground [rad], and its Jacobian row (n,)."""
    vx, vy = float(x[_VX]), float(x[_VY])
    s2 = max(vx * vx + vy * vy, 1e-6)
    h = np.zeros(x.shape[0])
    h[_YAW] = 1.0
    h[_VX] = -vy / s2
    h[_VY] = vx / s2
    return float(x[_YAW]) + math.atan2(vy, vx), h


def _update_course(x: np.ndarray, P: np.ndarray, pos_xy: np.ndarray, var: np.ndarray,
                   course_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`update_pose` with a course over ground (``var``: the two position variances and the course's):
    position rows select, the course row is linearised."""
    pred, row = course_measurement(x)
    h = np.zeros((3, x.shape[0]))
    h[0, _PX] = h[1, _PY] = 1.0
    h[2] = row
    innovation = np.append(pos_xy - x[_POS_IDX], wrap_angle(course_rad - pred))
    with np.errstate(invalid="ignore"):
        return _update_linear(x, P, h, innovation, var)


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
        if not self.calibration:
            raise RuntimeError("no calibration states: Ekf(calibration=True)")
        if not (math.isfinite(scale) and math.isfinite(var) and var > 0.0):
            return StepStatus.INPUT_INVALID
        with np.errstate(all="ignore"):
            idx = np.array([_K_WHEEL], dtype=np.intp)
            x, p = _update_selected(self.x, self.P, idx, np.array([scale - self.x[_K_WHEEL]]), np.array([var]))
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
