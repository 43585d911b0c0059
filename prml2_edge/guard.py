"""Physics guard (NumPy, edge side; no torch): bound the model's predictions to vehicle limits.

Paper Eq. (kamms circle) and the clamp that follows it::

    a_max = mu g,                   a_x^2 + a_y^2 <= a_max^2
    u     = u~ * min(1, u_max / (||u~||_2 + eps))      for u in {(v_x, v_y), (a_x, a_y)}
    omega = clip(omega~, -omega_max, omega_max)

When the guard scales a raw prediction by a factor ``f``, its variance is scaled by ``f^2``.
For the clip of ``omega`` the factor is ``omega / omega~``, written as
``omega_max / max(|omega~|, omega_max)``: exactly 1 inside the limit, so ``omega~ = 0`` is safe.
Limits come from :mod:`prml2_edge.schema` (``V_MAX_MPS``, ``OMEGA_MAX_RADPS``,
``accel_limit_mps2(mu)``, ``GUARD_EPS``). The torch twin is
:class:`prml2_edge.training.guard_torch.PhysicsGuard`; both give the same numbers.
"""

from __future__ import annotations

import math

import numpy as np

from prml2_edge import schema
from prml2_edge.schema import Z


def norm_clamp_factor(u: np.ndarray, u_max: float, eps: float = schema.GUARD_EPS) -> np.ndarray:
    """``min(1, u_max / (||u||_2 + eps))`` over the last axis; ``u`` (..., 2) -> (...,)."""
    norm = np.sqrt(np.sum(np.square(u), axis=-1))
    return u_max / np.maximum(norm + eps, u_max)


def physics_guard(
    mean: np.ndarray, var: np.ndarray, a_max_mps2: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply the physics guard to predicted means and variances of ``z``.

    Parameters
    ----------
    mean : (..., 5) raw predicted ``z = [v_x, v_y, a_x, a_y, omega_z]`` [m/s, m/s^2, rad/s],
        vehicle frame (schema order).
    var : (..., 5) its variances (same units squared).
    a_max_mps2 : acceleration bound [m/s^2] (``schema.accel_limit_mps2(mu)``).

    Returns
    -------
    mean, var : (..., 5) guarded copies.
    fired : (...,) bool, True where any of velocity, acceleration or yaw rate was limited.
    """
    mean = np.asarray(mean, dtype=np.float64)
    var = np.asarray(var, dtype=np.float64)
    if mean.shape[-1:] != (schema.NUM_STATES,) or var.shape != mean.shape:
        raise ValueError(f"mean and var must both have shape (..., {schema.NUM_STATES}), got {mean.shape}, {var.shape}")
    if not (a_max_mps2 > 0.0):
        raise ValueError(f"a_max_mps2 must be > 0, got {a_max_mps2!r}")
    f_vel = norm_clamp_factor(mean[..., Z.VEL], schema.V_MAX_MPS)
    f_acc = norm_clamp_factor(mean[..., Z.ACC], float(a_max_mps2))
    omega = mean[..., Z.OMEGA_Z]
    f_omega = schema.OMEGA_MAX_RADPS / np.maximum(np.abs(omega), schema.OMEGA_MAX_RADPS)

    out_mean = mean.copy()
    out_var = var.copy()
    out_mean[..., Z.VEL] *= f_vel[..., None]
    out_var[..., Z.VEL] *= np.square(f_vel)[..., None]
    out_mean[..., Z.ACC] *= f_acc[..., None]
    out_var[..., Z.ACC] *= np.square(f_acc)[..., None]
    out_mean[..., Z.OMEGA_Z] = np.clip(omega, -schema.OMEGA_MAX_RADPS, schema.OMEGA_MAX_RADPS)
    out_var[..., Z.OMEGA_Z] *= np.square(f_omega)
    fired = (f_vel < 1.0) | (f_acc < 1.0) | (f_omega < 1.0)
    return out_mean, out_var, fired


def physics_guard_row(mean: np.ndarray, var: np.ndarray, a_max_mps2: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`physics_guard` of one ``z`` (5,) and its variances (5,): the same numbers (the same operations on
    Python floats; NaN propagates as there), for the runtime's one guarded prediction per step, where NumPy's
    per-call cost on 5 elements is most of the work. Returns ``(mean (5,), var (5,), fired)``."""
    if not (a_max_mps2 > 0.0):
        raise ValueError(f"a_max_mps2 must be > 0, got {a_max_mps2!r}")
    v_x, v_y, a_x, a_y, omega = (float(u) for u in mean)
    var_vx, var_vy, var_ax, var_ay, var_omega = (float(u) for u in var)
    eps, v_max, w_max, a_max = schema.GUARD_EPS, schema.V_MAX_MPS, schema.OMEGA_MAX_RADPS, float(a_max_mps2)
    # max(candidate, limit) keeps a NaN candidate, as np.maximum does
    f_vel = v_max / max(math.sqrt(v_x * v_x + v_y * v_y) + eps, v_max)
    f_acc = a_max / max(math.sqrt(a_x * a_x + a_y * a_y) + eps, a_max)
    f_omega = w_max / max(abs(omega), w_max)
    omega_c = min(max(omega, -w_max), w_max)  # np.clip (NaN stays NaN)
    f_vel2, f_acc2 = f_vel * f_vel, f_acc * f_acc
    out_mean = np.array([v_x * f_vel, v_y * f_vel, a_x * f_acc, a_y * f_acc, omega_c])
    out_var = np.array([var_vx * f_vel2, var_vy * f_vel2, var_ax * f_acc2, var_ay * f_acc2,
                        var_omega * (f_omega * f_omega)])
    return out_mean, out_var, f_vel < 1.0 or f_acc < 1.0 or f_omega < 1.0


class GuardStats:
    """Counts guarded predictions and how often the guard fired (paper: < 2 % of predictions).

    A prediction is one ``z`` vector (one time step of one window).
    """

    def __init__(self) -> None:
        self.n_predictions = 0
        self.n_fired = 0

    def update(self, fired_mask: np.ndarray) -> None:
        """Add a ``fired`` mask (any shape, bool) from :func:`physics_guard`."""
        fired_mask = np.asarray(fired_mask, dtype=bool)
        self.n_predictions += int(fired_mask.size)
        self.n_fired += int(np.count_nonzero(fired_mask))

    def add(self, fired: bool) -> None:
        """Add one prediction (:func:`physics_guard_row`)."""
        self.n_predictions += 1
        self.n_fired += int(fired)

    def reset(self) -> None:
        """Zero the counters."""
        self.n_predictions = 0
        self.n_fired = 0

    @property
    def fire_rate(self) -> float:
        """Fraction of predictions the guard changed, in [0, 1]; 0.0 before any prediction."""
        return self.n_fired / self.n_predictions if self.n_predictions else 0.0
