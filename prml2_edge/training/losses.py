"""Training losses (paper Eq. nll_loss and Eq. total_loss_single) and the window-local frame.

Per window (sample) the paper sums over the decoder steps D_t:

* NLL: sum_t (z_gt - mu)^T Sigma^-1 (z_gt - mu) + log|Sigma|, with Sigma = diag(var).
  Computed in normalised z units (z divided by the training split's std), which changes the
  value only by a constant and keeps float32 well conditioned; the gradient is the same.
* position: beta * tanh(sum_t ||d_t - d_t^gt||^2 / beta), beta = 8, with d_t the EKF's
  a-posteriori positions [m] in the window-local frame (method.md).

Both return one value per window, shape (B,); the trainer averages over the batch.
"""

from __future__ import annotations

import torch

from prml2_edge import schema
from prml2_edge.schema import EkfState


def nll_loss(mean: torch.Tensor, var: torch.Tensor, z_gt: torch.Tensor, z_std: torch.Tensor,
             reduction: str = "sum") -> torch.Tensor:
    """Gaussian NLL of Eq. nll_loss per window, without the constant.

    Parameters
    ----------
    mean, var
        (B, T, 5) predicted z mean [SI] and variance [SI^2] (after the physics guard).
    z_gt
        (B, T, 5) ground-truth z [SI].
    z_std
        (5,) z normalisation std [SI].
    reduction
        ``"sum"`` (the paper's Eq. nll_loss) or ``"mean"`` over the T x 5 terms: the same gradient
        direction, 1 / (5 T) the size, so that next to it the position term of fine-tuning
        (bounded by beta) is not swamped (see :class:`~prml2_edge.training.presets.TrainConfig`).

    Returns
    -------
    torch.Tensor
        (B,) sum (or mean) over steps and components of r^2 / v + log v, r and v in normalised units.
    """
    r = (z_gt - mean) / z_std  # (B, T, 5)
    v = var / (z_std * z_std)  # (B, T, 5)
    terms = r * r / v + torch.log(v)
    if reduction == "sum":
        return terms.sum(dim=(1, 2))
    if reduction == "mean":
        return terms.mean(dim=(1, 2))
    raise ValueError(f"reduction must be 'sum' or 'mean', got {reduction!r}")


def physics_consistency_loss(mean: torch.Tensor, dt_s: float) -> torch.Tensor:
    """The authors' pretraining regulariser: acceleration consistency + jerk, per window (B,) [SI].

    ``mean`` (B, T, 5) guarded z [SI]. Consistency: the central difference of v_x, v_y against a_x,
    a_y, squared, averaged over steps and times dt^2; jerk: squared step-to-step changes of a_x, a_y,
    averaged. (They compare dv/dt with a directly, not with a + r v: a weak smoothness prior.)
    """
    v, a = mean[..., 0:2], mean[..., 2:4]
    dv = (v[:, 2:] - v[:, :-2]) / (2.0 * dt_s)
    consistency = ((dv - a[:, 1:-1]) ** 2).sum(-1).mean(-1) * dt_s * dt_s
    jerk = ((a[:, 1:] - a[:, :-1]) ** 2).sum(-1).mean(-1)
    return consistency + jerk


def position_loss(d: torch.Tensor, d_gt: torch.Tensor, beta: float = 8.0, reduction: str = "sum") -> torch.Tensor:
    """beta * tanh(sum_t ||d_t - d_t^gt||^2 / beta) per window: ``d``, ``d_gt`` (B, T, 2) [m] -> (B,).

    ``reduction="mean"`` averages the squared errors over the T steps instead of summing them (long
    segments: summed over 1000 steps of metre-size errors the tanh would be saturated, gradient ~0).
    """
    sq = ((d - d_gt) ** 2).sum(dim=2)  # (B, T) [m^2]
    if reduction == "sum":
        sq = sq.sum(dim=1)
    elif reduction == "mean":
        sq = sq.mean(dim=1)
    else:
        raise ValueError(f"reduction must be 'sum' or 'mean', got {reduction!r}")
    return beta * torch.tanh(sq / beta)


def to_window_frame(pose: torch.Tensor, origin_index: int) -> torch.Tensor:
    """Positions in the frame local to a window.

    Parameters
    ----------
    pose
        (B, T, 3) world poses [x east m, y north m, psi ccw from east rad].
    origin_index
        Step whose pose becomes the origin with heading 0 (the first decoder step, H).

    Returns
    -------
    torch.Tensor
        (B, T, 2) positions [m] translated and rotated so that step ``origin_index`` is at (0, 0)
        facing +x.
    """
    origin = pose[:, origin_index]  # (B, 3)
    dx = pose[..., 0] - origin[:, 0:1]  # (B, T)
    dy = pose[..., 1] - origin[:, 1:2]
    c = torch.cos(origin[:, 2:3])
    s = torch.sin(origin[:, 2:3])
    return torch.stack((c * dx + s * dy, -s * dx + c * dy), dim=-1)


def initial_state(z_first: torch.Tensor) -> torch.Tensor:
    """EKF state at the first decoder step in the window-local frame from ground truth.

    ``z_first`` (B, 5) ground-truth z [SI] -> x0 (B, 8) = [0, 0, 0, omega_z, v_x, v_y, a_x, a_y].
    """
    x0 = torch.zeros(z_first.shape[0], EkfState.DIM, dtype=z_first.dtype, device=z_first.device)
    x0[:, list(schema.Z_TO_EKF_INDEX)] = z_first
    return x0
