"""The trainer's validation after each epoch: NLL, the fine-tuning position term through the differentiable EKF,
z RMSE and the guard's fire rate over the validation windows, sharded over ranks."""

from __future__ import annotations

import math

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.training import distributed as ddp
from prml2_edge.training.guard_torch import PhysicsGuard
from prml2_edge.training.losses import initial_state, nll_loss, position_loss, to_window_frame
from prml2_edge.training.model import Prml2Model
from prml2_edge.training.train_data import WindowSource

EKF_DTYPE = torch.float64  # the filter runs in float64 (100 recursive steps, Joseph form)


class PositionFilter:
    """Lazy handle on the differentiable EKF (``prml2_edge.training.ekf_torch``)."""

    def __init__(self) -> None:
        from prml2_edge.training import ekf_torch

        self.ekf = ekf_torch
        self.Q = ekf_torch.default_process_noise(schema.DT_S, dtype=EKF_DTYPE, device=torch.device("cpu"))
        self.P0 = ekf_torch.default_initial_covariance(dtype=EKF_DTYPE, device=torch.device("cpu"))

    def positions(self, mean: torch.Tensor, var: torch.Tensor, z_first: torch.Tensor) -> torch.Tensor:
        """A-posteriori positions (B, T, 2) [m, window frame] over the decoder steps.

        ``mean``/``var`` (B, T, 5) guarded model outputs; ``z_first`` (B, 5) ground-truth z at step H.
        """
        b = mean.shape[0]
        x0 = initial_state(z_first.to(EKF_DTYPE))  # (B, 8)
        p0 = self.P0.expand(b, -1, -1)
        x_seq, _ = self.ekf.run_filter(x0, p0, mean.to(EKF_DTYPE), var.to(EKF_DTYPE), Q=self.Q,
                                       dt_s=schema.DT_S, update_first=True)
        return x_seq[..., schema.EkfState.POS]  # (B, T, 2)


def window_batches(indices: np.ndarray, batch_size: int) -> list[np.ndarray]:
    """``indices`` cut into consecutive batches of at most ``batch_size``."""
    return [indices[i : i + batch_size] for i in range(0, len(indices), batch_size)]


def to_tensors(batch: tuple[np.ndarray, np.ndarray, np.ndarray], origin: int):
    """Tensors of a ``(onboard, z, pose)`` batch; ground-truth positions from step ``origin`` on, in the frame
    of that step: the first decoder step H for windows, 0 for segments (:meth:`WindowSet.get_segments`)."""
    onboard, z, pose = batch
    onboard_t = torch.as_tensor(np.ascontiguousarray(onboard), dtype=torch.float32)  # (b, L, 9)
    z_t = torch.as_tensor(np.ascontiguousarray(z), dtype=torch.float32)  # (b, L or T, 5)
    # local positions in float64 (world coordinates can be km: float32 would lose cm)
    d_gt = to_window_frame(torch.as_tensor(np.asarray(pose, dtype=np.float64)), origin)[:, origin:]
    return onboard_t, z_t, d_gt


def evaluate_windows(model: Prml2Model, guard: PhysicsGuard, windows: WindowSource, *, batch_size: int,
                     with_position: bool, filt: PositionFilter | None, beta: float = 8.0,
                     info: ddp.DistInfo | None = None, nll_reduction: str = "sum") -> dict:
    """Validation metrics over all windows of ``windows`` (sharded over ranks, summed).

    Returns ``{"val_nll", "val_pos" (or NaN), "val_rmse_<state>", "val_guard_fire_rate", "val_windows"}``:
    NLL and position term are means per window (the training objective's scale); RMSE over
    every decoder step of every window, guarded means, SI units.
    """
    info = info or ddp.DistInfo()
    H = model.cfg.encoder_len
    idx_all = ddp.shard(np.arange(len(windows)), info) if len(windows) else np.arange(0)
    n_states = schema.NUM_STATES
    # sums: nll, pos, n_windows, sq_err (5), n_steps, fired, predictions
    acc = torch.zeros(5 + n_states, dtype=torch.float64)
    was_training = model.training
    model.eval()
    fired0 = guard.n_fired
    with torch.no_grad():
        for idx in window_batches(idx_all, batch_size):
            onboard, z, d_gt = to_tensors(windows.get(idx), H)
            mean, var = guard(*model(onboard))
            z_dec = z[:, H:]
            acc[0] += nll_loss(mean, var, z_dec, model.z_std, nll_reduction).double().sum()
            if with_position and filt is not None:
                d = filt.positions(mean, var, z[:, H])
                acc[1] += position_loss(d, d_gt, beta).sum()
            acc[2] += len(idx)
            acc[3 : 3 + n_states] += ((mean - z_dec).double() ** 2).sum(dim=(0, 1))
            acc[3 + n_states] += z_dec.shape[0] * z_dec.shape[1]
    acc[4 + n_states] = guard.n_fired - fired0  # fired predictions in this evaluation
    acc = ddp.all_reduce_sum(acc, info)
    model.train(was_training)
    n_win = max(acc[2].item(), 1.0)
    n_steps = max(acc[3 + n_states].item(), 1.0)
    out = {
        "val_nll": acc[0].item() / n_win,
        "val_pos": acc[1].item() / n_win if with_position and filt is not None else float("nan"),
        "val_windows": int(acc[2].item()),
    }
    for i, name in enumerate(schema.STATE_NAMES):
        out[f"val_rmse_{name}"] = math.sqrt(acc[3 + i].item() / n_steps)
    out["val_guard_fire_rate"] = acc[4 + n_states].item() / (n_steps * 1.0)
    return out
