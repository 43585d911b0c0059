"""Physics guard as a differentiable torch layer (training side).

Same equations and numbers as the edge twin :func:`prml2_edge.guard.physics_guard` (paper
Eq. kamms circle and the norm clamp / clip that follows it); see that module for the maths.
"""

from __future__ import annotations

import torch
from torch import Tensor

from prml2_edge import schema
from prml2_edge.schema import Z


def norm_clamp_factor(u: Tensor, u_max: float, eps: float = schema.GUARD_EPS) -> Tensor:
    """``min(1, u_max / (||u||_2 + eps))`` over the last axis; ``u`` (..., 2) -> (...,).

    Written as ``u_max / max(||u|| + eps, u_max)``: identical values, and the gradient flows
    through the norm only where the clamp is active.
    """
    sq = torch.sum(u * u, dim=-1)
    # sqrt has an infinite derivative at 0, and 0 * inf = NaN even where the clamp blocks the
    # gradient; the double where keeps it finite (same values as sqrt).
    nonzero = sq > 0
    norm = torch.where(nonzero, torch.sqrt(torch.where(nonzero, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    return u_max / torch.clamp(norm + eps, min=u_max)


class PhysicsGuard(torch.nn.Module):
    """Bound predicted ``z = [v_x, v_y, a_x, a_y, omega_z]`` to vehicle limits; scale variances by factor^2.

    Parameters
    ----------
    mu : tyre-road friction coefficient; the acceleration bound is ``schema.accel_limit_mps2(mu)``
        (10 m/s^2 dry, 5 m/s^2 for mu <= 0.5).

    Attributes
    ----------
    n_predictions, n_fired : running counts of guarded ``z`` vectors and of those the guard changed
        (plain attributes, not in the state dict); see :meth:`fire_rate`, :meth:`reset_stats`.
    """

    def __init__(self, mu: float = 1.0) -> None:
        super().__init__()
        self.mu = float(mu)
        self.a_max_mps2 = schema.accel_limit_mps2(self.mu)
        self.v_max_mps = schema.V_MAX_MPS
        self.omega_max_radps = schema.OMEGA_MAX_RADPS
        self.n_predictions = 0
        self.n_fired = 0

    def extra_repr(self) -> str:
        return (f"mu={self.mu}, a_max_mps2={self.a_max_mps2}, v_max_mps={self.v_max_mps}, "
                f"omega_max_radps={self.omega_max_radps}")

    def forward(self, mean: Tensor, var: Tensor) -> tuple[Tensor, Tensor]:
        """Guard ``mean`` (..., 5) and ``var`` (..., 5) (schema z order, SI units); returns new tensors."""
        if mean.shape[-1] != schema.NUM_STATES or var.shape != mean.shape:
            raise ValueError(f"mean and var must both have shape (..., {schema.NUM_STATES}), "
                             f"got {tuple(mean.shape)}, {tuple(var.shape)}")
        f_vel = norm_clamp_factor(mean[..., Z.VEL], self.v_max_mps)  # (...,)
        f_acc = norm_clamp_factor(mean[..., Z.ACC], self.a_max_mps2)  # (...,)
        omega_raw = mean[..., Z.OMEGA_Z]
        omega = torch.clamp(omega_raw, -self.omega_max_radps, self.omega_max_radps)
        # factor omega / omega~ written so that omega~ = 0 is safe (exactly 1 inside the limit)
        f_omega = self.omega_max_radps / torch.clamp(omega_raw.abs(), min=self.omega_max_radps)

        factor = torch.stack([f_vel, f_vel, f_acc, f_acc], dim=-1)  # (..., 4) in z order v_x, v_y, a_x, a_y
        out_mean = torch.cat([mean[..., : Z.OMEGA_Z] * factor, omega.unsqueeze(-1)], dim=-1)
        var_factor = torch.cat([factor * factor, (f_omega * f_omega).unsqueeze(-1)], dim=-1)
        out_var = var * var_factor
        with torch.no_grad():
            fired = (f_vel < 1.0) | (f_acc < 1.0) | (f_omega < 1.0)
            self.n_predictions += fired.numel()
            self.n_fired += int(fired.sum())
        return out_mean, out_var

    def fire_rate(self) -> float:
        """Fraction of guarded predictions the guard changed, in [0, 1]; 0.0 before any."""
        return self.n_fired / self.n_predictions if self.n_predictions else 0.0

    def reset_stats(self) -> None:
        """Zero the running counters."""
        self.n_predictions = 0
        self.n_fired = 0
