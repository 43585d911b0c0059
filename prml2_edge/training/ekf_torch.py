"""Differentiable, batched planar EKF in torch (training side).

The twin of :mod:`prml2_edge.ekf.numpy_ekf`: same names, same equations, same default noise
(a float64 parity test runs both over thousands of steps). Shapes: ``B`` batch, ``T`` time.
State ``x = [p_x, p_y, psi, omega_z, v_x, v_y, a_x, a_y]`` (:class:`prml2_edge.schema.EkfState`;
world frame x east, y north, ``psi`` counter-clockwise from east and unwrapped; velocity and
acceleration in the vehicle frame). The dtype and device follow the inputs.

Equations (paper, ``../shared/seed/prml2_paper.tex.txt``):

* Eq. (state_prediction), planar: ``p += R(psi)(v dt + a dt^2/2)``, ``psi += omega dt``,
  ``v += a dt``; ``omega`` and ``a`` constant;
* its analytic Jacobian ``F`` and ``P <- F P F^T + Q`` (the differentiable prediction step);
* Eq. (measurement_vector): ``H`` selects ``z = [v_x, v_y, a_x, a_y, omega_z]``, ``R_t = diag(z_var)``;
* Eq. (kalman stable): ``K = P H^T S^-1`` from ``cholesky_ex`` + ``cholesky_solve`` (no explicit
  inverse), Joseph-form covariance, ``P`` symmetrised after every step.

``H`` is a selection, so ``H P`` and ``H P H^T`` are computed by indexing (exact, cheaper than
matmuls). No in-place operation touches a tensor autograd needs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from prml2_edge import schema
from prml2_edge.ekf import numpy_ekf
from prml2_edge.ekf.numpy_ekf import jitter_schedule
from prml2_edge.schema import CalState, EkfState

STATE_DIM = EkfState.DIM  # 8
FULL_DIM = CalState.FULL_DIM  # 11 with the calibration states (random walks: identity rows of F)
MEAS_DIM = schema.NUM_STATES  # 5
_PX, _PY = EkfState.POS_X.start, EkfState.POS_Y.start
_YAW = EkfState.YAW.start
_OMEGA = EkfState.OMEGA_Z.start
_VX, _VY = EkfState.VEL.start, EkfState.VEL.start + 1
_AX, _AY = EkfState.ACC.start, EkfState.ACC.start + 1
_NPOS = EkfState.POS.stop  # 2
# F = [[I, G(x)], [0, I + dt E]]: only the two position rows depend on the state
assert (_PX, _PY, _NPOS) == (0, 1, 2), "the block form of F assumes the position rows come first"

_Z_IDX_CACHE: dict[torch.device, Tensor] = {}


def _z_index(device: torch.device) -> Tensor:
    """``schema.Z_TO_EKF_INDEX`` as a long tensor on ``device`` (cached)."""
    idx = _Z_IDX_CACHE.get(device)
    if idx is None:
        with torch.inference_mode(False):  # a cached inference tensor would break later autograd use
            idx = torch.tensor(schema.Z_TO_EKF_INDEX, dtype=torch.long, device=device)
        _Z_IDX_CACHE[device] = idx
    return idx


# Rows _NPOS.. of F are constant: identity plus ``state += dt * rate`` for these (state, rate) pairs.
_RATE_PAIRS = ((_YAW, _OMEGA), (_VX, _AX), (_VY, _AY))
_CONST_CACHE: dict[tuple[int, torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}


def _constants(n: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """For a state of ``n`` components (8, or 11 calibrated): the rate row of each row after the position
    (itself where none) and whether it has one, (n - 2,) and (n - 2, 1)."""
    key = (n, dtype, device)
    if key not in _CONST_CACHE:
        src = [next((r for st, r in _RATE_PAIRS if st == i), i) for i in range(_NPOS, n)]
        has = [float(any(st == i for st, _ in _RATE_PAIRS)) for i in range(_NPOS, n)]
        with torch.inference_mode(False):  # first built under inference_mode, the cache must still serve autograd
            _CONST_CACHE[key] = (
                torch.tensor(src, dtype=torch.long, device=device),
                torch.tensor(has, dtype=dtype, device=device).unsqueeze(-1),
            )
    return _CONST_CACHE[key]


def default_process_noise(
    dt_s: float = schema.DT_S, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> Tensor:
    """Default ``Q`` (8, 8): the same numbers as :func:`prml2_edge.ekf.numpy_ekf.default_process_noise`.

    To tune, build ``numpy_ekf.ProcessNoise(...).matrix(dt_s)`` and pass it through ``torch.as_tensor``.
    """
    return torch.as_tensor(numpy_ekf.default_process_noise(dt_s), dtype=dtype, device=device)


def default_initial_covariance(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """Default ``P0`` (8, 8): the same numbers as :func:`prml2_edge.ekf.numpy_ekf.default_initial_covariance`."""
    return torch.as_tensor(numpy_ekf.default_initial_covariance(), dtype=dtype, device=device)


def measurement_matrix(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> Tensor:
    """``H`` (5, 8) selecting ``z`` from the state (Eq. measurement_vector). The filter itself indexes instead."""
    return torch.as_tensor(numpy_ekf.measurement_matrix(), dtype=dtype, device=device)


def symmetrize(P: Tensor) -> Tensor:
    """``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (P + P.transpose(-1, -2))


def _rotation_terms(x: Tensor, dt: float) -> tuple[Tensor, Tensor]:
    """``R(psi)`` (..., 2, 2) and the world-frame displacement ``R(psi)(v dt + a dt^2/2)`` (..., 2)."""
    psi = x[..., _YAW]
    c, s = torch.cos(psi), torch.sin(psi)
    rot = torch.stack([c, -s, s, c], dim=-1).unflatten(-1, (2, 2))  # (..., 2, 2)
    d = x[..., EkfState.VEL] * dt + x[..., EkfState.ACC] * (0.5 * dt * dt)  # (..., 2) vehicle frame
    rd = (rot * d.unsqueeze(-2)).sum(-1)  # (..., 2) = R d, without a tiny batched matmul
    return rot, rd


def _linear_part(x: Tensor, dt: float) -> Tensor:
    """Components after the position of ``f(x)``: ``psi += omega dt``, ``v += a dt``, the rest constant; (..., 6)."""
    src, has_rate = _constants(x.shape[-1], x.dtype, x.device)
    return x[..., _NPOS:] + (dt * has_rate.squeeze(-1)) * x.index_select(-1, src)


def _bias_decay(x: Tensor, out: Tensor, model_bias_decay: float) -> Tensor:
    """The model's omega_z bias decays (Gauss-Markov) in the calibrated layout; ``out`` (..., n - 2)."""
    if x.shape[-1] != FULL_DIM or model_bias_decay == 1.0:
        return out
    scale = torch.ones(FULL_DIM - _NPOS, dtype=x.dtype, device=x.device)
    scale[CalState.MODEL_OMEGA_BIAS.start - _NPOS] = model_bias_decay
    return out * scale


def process_model(x: Tensor, dt_s: float, model_bias_decay: float = 1.0) -> Tensor:
    """A-priori state ``f(x)`` (Eq. state_prediction, planar); ``x`` (..., 8) -> (..., 8).

    ``p += R(psi)(v dt + a dt^2/2)``, ``psi += omega dt``, ``v += a dt``; ``psi`` is not wrapped.
    """
    dt = float(dt_s)
    _, rd = _rotation_terms(x, dt)
    return torch.cat([x[..., EkfState.POS] + rd, _bias_decay(x, _linear_part(x, dt), model_bias_decay)], dim=-1)


def _jacobian_top(rot: Tensor, rd: Tensor, dt: float, n: int = STATE_DIM) -> Tensor:
    """The state-dependent block ``G = dp / d(psi, omega, v, a)`` (..., 2, 6) of ``F``.

    ``dR/dpsi d = (-(R d)_y, (R d)_x)``, ``dp/domega = 0``, ``dp/dv = R dt``, ``dp/da = R dt^2/2``.
    """
    d_psi = torch.stack([-rd[..., 1], rd[..., 0]], dim=-1).unsqueeze(-1)  # (..., 2, 1)
    parts = [d_psi, torch.zeros_like(d_psi), rot * dt, rot * (0.5 * dt * dt)]
    if n > STATE_DIM:  # the calibration states do not move the position
        parts.append(d_psi.new_zeros(*d_psi.shape[:-1], n - STATE_DIM))
    return torch.cat(parts, dim=-1)


def process_jacobian(x: Tensor, dt_s: float) -> Tensor:
    """Analytic Jacobian ``F = df/dx`` (..., 8, 8) of :func:`process_model` (the paper's ``F_t``, planar).

    Non-identity entries: ``dp/dpsi = dR/dpsi (v dt + a dt^2/2)``, ``dp/dv = R dt``,
    ``dp/da = R dt^2/2``, ``dpsi/domega = dt``, ``dv/da = dt I``.
    """
    dt = float(dt_s)
    n = x.shape[-1]
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    for st, rate in _RATE_PAIRS:
        eye[st, rate] = dt
    eye = eye.expand(*x.shape[:-1], n, n)
    rot, rd = _rotation_terms(x, dt)
    top = torch.cat([eye[..., :_NPOS, :_NPOS], _jacobian_top(rot, rd, dt, n)], dim=-1)  # (..., 2, n)
    return torch.cat([top, eye[..., _NPOS:, :]], dim=-2)


def _apply_jacobian(g: Tensor, m: Tensor, dt: float, model_bias_decay: float = 1.0) -> Tensor:
    """``F @ m`` for ``F`` = [[I, G], [0, I + dt E]] without the dense 8x8 product; ``m`` (..., 8, n)."""
    src, has_rate = _constants(m.shape[-2], m.dtype, m.device)
    top = m[..., :_NPOS, :] + g @ m[..., _NPOS:, :]  # (..., 2, n)
    bottom = m[..., _NPOS:, :] + (dt * has_rate) * m.index_select(-2, src)  # (..., n - 2, n)
    if m.shape[-2] == FULL_DIM and model_bias_decay != 1.0:
        bottom = _bias_decay(m[..., 0, :], bottom.transpose(-1, -2), model_bias_decay).transpose(-1, -2)
    return torch.cat([top, bottom], dim=-2)


def predict(x: Tensor, P: Tensor, Q: Tensor, dt_s: float, model_bias_decay: float = 1.0) -> tuple[Tensor, Tensor]:
    """Prediction ``x <- f(x)``, ``P <- F P F^T + Q``; ``x`` (B, 8), ``P`` (B, 8, 8), ``Q`` (8, 8) or (B, 8, 8).

    ``F P F^T`` is evaluated as ``F (F P)^T`` (``P`` symmetric) with the block structure of ``F``.
    """
    dt = float(dt_s)
    rot, rd = _rotation_terms(x, dt)
    g = _jacobian_top(rot, rd, dt, x.shape[-1])
    fp = _apply_jacobian(g, P, dt, model_bias_decay)
    p_new = _apply_jacobian(g, fp.transpose(-1, -2), dt, model_bias_decay) + Q
    x_new = torch.cat([x[..., EkfState.POS] + rd, _bias_decay(x, _linear_part(x, dt), model_bias_decay)], dim=-1)
    return x_new, symmetrize(p_new)


def cholesky_jittered(S: Tensor) -> Tensor:
    """Lower Cholesky factor of ``S`` (..., m, m), adding diagonal jitter where rounding broke definiteness.

    Per batch element that fails, the jitters of :func:`prml2_edge.ekf.numpy_ekf.jitter_schedule`
    (times ``mean|diag S|``) are tried in turn, as in the NumPy twin; if none succeeds the
    off-diagonal is dropped (``sqrt(diag S)``), so the result is always finite for finite ``S``.
    """
    L, info = torch.linalg.cholesky_ex(S)
    bad = info != 0
    if not bool(bad.any()):  # the common case: one host sync per call
        return L
    eye = torch.eye(S.shape[-1], dtype=S.dtype, device=S.device)
    diag = S.diagonal(dim1=-2, dim2=-1)
    scale = diag.abs().mean(-1).clamp_min(torch.finfo(S.dtype).tiny)
    for rel in jitter_schedule(torch.finfo(S.dtype).eps):
        L_j, info_j = torch.linalg.cholesky_ex(S + (rel * scale * bad)[..., None, None] * eye)
        L = torch.where(bad[..., None, None], L_j, L)
        bad = bad & (info_j != 0)
        if not bool(bad.any()):
            return L
    L_diag = torch.diag_embed(torch.sqrt(diag.clamp_min(torch.finfo(S.dtype).tiny)))
    return torch.where(bad[..., None, None], L_diag, L)


def update(x: Tensor, P: Tensor, z: Tensor, z_var: Tensor) -> tuple[Tensor, Tensor]:
    """Kalman update with pseudo-measurements (Eqs. measurement_vector, kalman stable).

    Parameters
    ----------
    x : (B, 8) a-priori state; P : (B, 8, 8) its covariance.
    z : (B, 5) ``[v_x, v_y, a_x, a_y, omega_z]`` [m/s, m/s^2, rad/s], vehicle frame.
    z_var : (B, 5) variances, > 0 (``R_t = diag(z_var)``).

    Returns
    -------
    x (B, 8), P (B, 8, 8): a-posteriori state and covariance.
    """
    idx = _z_index(x.device)
    hp = P.index_select(-2, idx)  # (B, 5, 8) = H P
    s = hp.index_select(-1, idx) + torch.diag_embed(z_var)  # (B, 5, 5) = H P H^T + R_t
    chol = cholesky_jittered(s)
    k_t = torch.cholesky_solve(hp, chol)  # (B, 5, 8) = S^-1 H P = K^T
    k = k_t.transpose(-1, -2)  # (B, 8, 5)
    innovation = z - x.index_select(-1, idx)  # (B, 5)
    x_new = x + (k * innovation.unsqueeze(-2)).sum(-1)
    # Joseph form P = (I - K H) P (I - K H)^T + K R_t K^T. Unlike the short form (I - K H) P it is
    # first-order insensitive to errors in K and keeps P symmetric positive semi-definite under
    # rounding and for a perturbed gain (jitter, float32): long sequences and their gradients stay
    # finite. With H a selection, A P = P - K (H P) and (A P) A^T + K R K^T = A P - ((A P) H^T - K R) K^T.
    ap = P - k @ hp
    p_new = ap - (ap.index_select(-1, idx) - k * z_var.unsqueeze(-2)) @ k_t
    return x_new, symmetrize(p_new)


def update_linear(x: Tensor, P: Tensor, h: Tensor, innovation: Tensor, meas_var: Tensor) -> tuple[Tensor, Tensor]:
    """Kalman update with a dense ``H`` (B, m, n) (the twin of :func:`numpy_ekf.update_linear`), Joseph form."""
    hp = h @ P  # (B, m, n)
    s = hp @ h.transpose(-1, -2) + torch.diag_embed(meas_var)
    chol = cholesky_jittered(s)
    k_t = torch.cholesky_solve(hp, chol)  # (B, m, n)
    k = k_t.transpose(-1, -2)
    x_new = x + (k * innovation.unsqueeze(-2)).sum(-1)
    a = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device) - k @ h
    p_new = a @ P @ a.transpose(-1, -2) + (k * meas_var.unsqueeze(-2)) @ k_t
    return x_new, symmetrize(p_new)


def update_model_calibrated(x: Tensor, P: Tensor, z: Tensor, z_var: Tensor,
                            offset_share: float = 1.0) -> tuple[Tensor, Tensor]:
    """The model's z (B, 5) in the calibrated layout, as :func:`numpy_ekf.model_measurement` with the same
    ``offset_share`` (the runtime's is :attr:`numpy_ekf.CalibrationNoise.model_offset_share`); x (B, 11)."""
    b = x.shape[0]
    idx = _z_index(x.device)
    k_idx, by_idx, bm_idx = CalState.WHEEL_SCALE.start, CalState.YAW_RATE_OFFSET.start, CalState.MODEL_OMEGA_BIAS.start
    vx_row, w_row = schema.Z.V_X, schema.Z.OMEGA_Z
    h = torch.zeros(b, MEAS_DIM, FULL_DIM, dtype=x.dtype, device=x.device)
    h[:, torch.arange(MEAS_DIM), idx] = 1.0
    k = x[:, k_idx]
    h[:, vx_row, _VX] = 1.0 + k
    h[:, w_row, by_idx] = offset_share
    h[:, w_row, bm_idx] = 1.0
    hx = x.index_select(-1, idx).clone()
    hx[:, vx_row] = (1.0 + k) * x[:, _VX]
    hx[:, w_row] = x[:, _OMEGA] + offset_share * x[:, by_idx] + x[:, bm_idx]
    return update_linear(x, P, h, z - hx, z_var)


def cue_measurement(x: Tensor, yaw_rate: Tensor, wheel_speed: Tensor) -> tuple[Tensor, Tensor]:
    """Both raw cues (B,) each: innovation (B, 2) and Jacobian (B, 2, 11), as :func:`numpy_ekf.cue_measurement`."""
    b = x.shape[0]
    h = x.new_zeros(b, 2, FULL_DIM)
    k = x[:, CalState.WHEEL_SCALE.start]
    vx = x[:, _VX]
    h[:, 0, _OMEGA] = 1.0
    h[:, 0, CalState.YAW_RATE_OFFSET.start] = 1.0
    h[:, 1, _VX] = 1.0 + k
    innovation = torch.stack([yaw_rate - (x[:, _OMEGA] + x[:, CalState.YAW_RATE_OFFSET.start]),
                              wheel_speed - (1.0 + k) * vx], dim=-1)
    return innovation, h


def run_filter_calibrated(x0: Tensor, P0: Tensor, z: Tensor, z_var: Tensor, cues: Tensor, cue_var: Tensor,
                          Q: Tensor, dt_s: float = schema.DT_S, model_bias_decay: float = 1.0,
                          offset_share: float = 1.0) -> tuple[Tensor, Tensor]:
    """The calibrated filter over a batch: each step predict, model z update, raw-cue update.

    ``x0`` (B, 11), ``P0`` (B, 11, 11), ``z``/``z_var`` (B, T, 5), ``cues``/``cue_var`` (B, T, 2)
    ``[CAN yaw rate rad/s, rear-axle wheel speed m/s]``, ``Q`` (11, 11). The first step updates
    without predicting. ``offset_share``: of the CAN yaw-rate offset in the model's omega_z
    (:func:`update_model_calibrated`). Returns ``x`` (B, T, 11) and ``P`` (B, T, 11, 11).
    """
    x, P = x0, P0
    xs, ps = [], []
    for t in range(z.shape[1]):
        if t > 0:
            x, P = predict(x, P, Q, dt_s, model_bias_decay)
        x, P = update_model_calibrated(x, P, z[:, t], z_var[:, t], offset_share)
        innovation, h = cue_measurement(x, cues[:, t, 0], cues[:, t, 1])
        x, P = update_linear(x, P, h, innovation, cue_var[:, t])
        xs.append(x)
        ps.append(P)
    return torch.stack(xs, dim=1), torch.stack(ps, dim=1)


def run_filter(
    x0: Tensor,
    P0: Tensor,
    z: Tensor,
    z_var: Tensor,
    Q: Tensor | None = None,
    dt_s: float = schema.DT_S,
    update_first: bool = True,
) -> tuple[Tensor, Tensor]:
    """Run the EKF over a batch of pseudo-measurement sequences, differentiably.

    Step ``t``: predict (except at ``t = 0`` when ``update_first``), then update with ``z[:, t]``.

    Parameters
    ----------
    x0 : (B, 8) or (8,) initial state; P0 : (B, 8, 8) or (8, 8) initial covariance.
    z : (B, T, 5) pseudo-measurements ``[v_x, v_y, a_x, a_y, omega_z]``, vehicle frame, SI.
    z_var : (B, T, 5) their variances, > 0.
    Q : (8, 8) or (B, 8, 8) process noise (default :func:`default_process_noise` for ``dt_s``).
    dt_s : step [s].
    update_first : skip the prediction at ``t = 0`` (``x0`` is the prior at the first measurement).

    Returns
    -------
    x : (B, T, 8) a-posteriori states; P : (B, T, 8, 8) a-posteriori covariances.
    """
    if z.dim() != 3 or z.shape[-1] != MEAS_DIM or z_var.shape != z.shape:
        raise ValueError(f"z and z_var must both be (B, T, {MEAS_DIM}), got {tuple(z.shape)}, {tuple(z_var.shape)}")
    b, t_len, _ = z.shape
    x = x0.expand(b, STATE_DIM)
    P = P0.expand(b, STATE_DIM, STATE_DIM)
    if Q is None:
        Q = default_process_noise(dt_s, dtype=z.dtype, device=z.device)
    xs: list[Tensor] = []
    ps: list[Tensor] = []
    for t in range(t_len):
        if t > 0 or not update_first:
            x, P = predict(x, P, Q, dt_s)
        x, P = update(x, P, z[:, t], z_var[:, t])
        xs.append(x)
        ps.append(P)
    return torch.stack(xs, dim=1), torch.stack(ps, dim=1)
