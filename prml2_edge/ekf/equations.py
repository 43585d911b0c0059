"""The planar EKF's equations in NumPy (float64), as functions; the stateful filter is
:class:`prml2_edge.ekf.numpy_ekf.Ekf`, the noise settings :mod:`prml2_edge.ekf.noise`. No torch.

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

import math

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
