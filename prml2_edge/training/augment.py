"""Input augmentations for the window batches (issue 26): sensor errors real cars have and the
training cars show too rarely. Each is off by default and seeded by the run's seed and the
optimiser step, so a resumed run draws the same."""

from __future__ import annotations

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.training.presets import TrainConfig

_YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
# The coarse gyros a window may be given (--yaw-quant-aug): steps log-uniform within these [deg/s], from a
# Toyota's 0.244 to ReV-StED's 1.28 and a little beyond; applied only where the step is at least this many
# times the window's own finest change, so a coarse car's reading is not re-rounded onto a finer grid.
QUANT_STEP_RANGE_DPS = (0.2, 1.5)
QUANT_MIN_COARSENING = 2.0


def yaw_offset_augment(onboard: torch.Tensor, cfg: TrainConfig, step: int) -> torch.Tensor:
    """``onboard`` (b, L, 9) with one uniform yaw-rate offset per window within +-``cfg.yaw_offset_aug_dps``;
    unchanged when that is 0."""
    if cfg.yaw_offset_aug_dps <= 0:
        return onboard
    rng = np.random.default_rng([cfg.seed, 26, step])
    offset = rng.uniform(-1.0, 1.0, onboard.shape[0]) * np.radians(cfg.yaw_offset_aug_dps)
    out = onboard.clone()
    out[:, :, _YAW] += torch.as_tensor(offset, dtype=out.dtype)[:, None]
    return out


def finest_change(x: torch.Tensor) -> torch.Tensor:
    """(b,) the smallest non-zero change between consecutive samples of each row of ``x`` (b, L); inf where
    the row never changes. A coarse CAN signal moves by whole steps, a fine one by its noise."""
    d = (x[:, 1:] - x[:, :-1]).abs()
    d = torch.where(d > 1e-12, d, torch.full_like(d, float("inf")))
    return d.min(dim=1).values


def yaw_quant_augment(onboard: torch.Tensor, cfg: TrainConfig, step: int) -> torch.Tensor:
    """``onboard`` (b, L, 9) with the yaw rate of a share ``cfg.yaw_quant_aug`` of the windows rounded to a
    coarse gyro's step (log-uniform in :data:`QUANT_STEP_RANGE_DPS`), as the car's sensor would report it; the
    target stays the truth, so the model learns to tell the rate within the step from steering, a_y and the
    wheels. Windows whose own changes are already within :data:`QUANT_MIN_COARSENING` of the drawn step keep
    their reading. Unchanged when the share is 0."""
    if cfg.yaw_quant_aug <= 0:
        return onboard
    rng = np.random.default_rng([cfg.seed, 2612, step])
    b = onboard.shape[0]
    lo, hi = np.log(np.radians(QUANT_STEP_RANGE_DPS))
    q = torch.as_tensor(np.exp(rng.uniform(lo, hi, b)), dtype=onboard.dtype)
    pick = torch.as_tensor(rng.uniform(size=b) < cfg.yaw_quant_aug)
    yaw = onboard[:, :, _YAW]
    pick &= q >= QUANT_MIN_COARSENING * finest_change(yaw)
    if not bool(pick.any()):
        return onboard
    out = onboard.clone()
    out[pick, :, _YAW] = torch.round(yaw[pick] / q[pick, None]) * q[pick, None]
    return out


def augment(onboard: torch.Tensor, cfg: TrainConfig, step: int) -> torch.Tensor:
    """Every augmentation the config turns on: the offset first, then the rounding, as a real gyro reports
    ``round(rate + offset)``."""
    return yaw_quant_augment(yaw_offset_augment(onboard, cfg, step), cfg, step)
