"""The learned baselines as torch modules with the PRML2 model interface.

Shared by all: inputs normalised with the dataset's onboard statistics, outputs de-normalised
with the training split's z statistics, a strictly positive variance (softplus + floor), and a
per-step linear skip from the normalised inputs to the normalised mean, fitted by ridge
regression before training (as for PRML2's edge preset: a CPU budget of a few hundred steps would
not reach the linear part from zero, and giving every method the same start keeps the comparison
about the sequence models).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from prml2_edge import schema
from prml2_edge.errors import ConfigError

_SOFTPLUS_ONE = float(np.log(np.expm1(1.0)))
STD_FLOOR = 1e-6


@dataclass(frozen=True)
class BaselineConfig:
    """Hyper-parameters of a baseline (``kind`` one of :data:`BASELINES`)."""

    kind: str = "nn-vdm"
    hidden: int = 64
    n_layers: int = 1
    n_heads: int = 4  # rnn-ekf attention
    kernel: int = 9  # backprop-kf: steps of local context per observation [samples]
    window_len: int = schema.WINDOW_LEN
    encoder_len: int = schema.ENCODER_LEN
    num_signals: int = schema.NUM_SIGNALS
    num_states: int = schema.NUM_STATES
    var_floor: float = 1e-6

    @property
    def decoder_len(self) -> int:
        return self.window_len - self.encoder_len

    def validate(self) -> None:
        if self.kind not in BASELINES:
            raise ConfigError(f"unknown baseline {self.kind!r}; one of {', '.join(BASELINES)}")
        if self.hidden < 1 or self.n_layers < 1 or self.kernel < 1:
            raise ConfigError("hidden, n_layers and kernel must be >= 1")
        if self.kind == "rnn-ekf" and self.hidden % self.n_heads:
            raise ConfigError(f"hidden {self.hidden} must be divisible by n_heads {self.n_heads}")


class _Base(nn.Module):
    """Normalisation, skip, head and de-normalisation around a sequence body ``features``."""

    def __init__(self, cfg: BaselineConfig, norm_mean, norm_std, z_mean, z_std) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        f32 = torch.float32
        self.register_buffer("in_mean", torch.as_tensor(np.asarray(norm_mean), dtype=f32).reshape(cfg.num_signals))
        self.register_buffer("in_std", torch.as_tensor(np.asarray(norm_std), dtype=f32)
                             .reshape(cfg.num_signals).clamp_min(STD_FLOOR))
        self.register_buffer("z_mean", torch.as_tensor(np.asarray(z_mean), dtype=f32).reshape(cfg.num_states))
        self.register_buffer("z_std", torch.as_tensor(np.asarray(z_std), dtype=f32)
                             .reshape(cfg.num_states).clamp_min(STD_FLOOR))
        self.skip = nn.Linear(cfg.num_signals, cfg.num_states)
        self.head = nn.Linear(cfg.hidden, 2 * cfg.num_states)
        with torch.no_grad():
            self.skip.weight.zero_()
            self.skip.bias.zero_()
            self.head.weight.mul_(0.1)
            self.head.bias.zero_()
            self.head.bias[cfg.num_states:] = _SOFTPLUS_ONE

    def features(self, x: torch.Tensor) -> torch.Tensor:  # (B, L, 9) normalised -> (B, L-H, hidden)
        raise NotImplementedError

    def heads(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, T, hidden) -> normalised (mean offset, variance), each (B, T, 5)."""
        out = self.head(feat)
        k = self.cfg.num_states
        return out[..., :k], F.softplus(out[..., k:]) + self.cfg.var_floor

    @torch.no_grad()
    def init_skip(self, onboard_rows: np.ndarray, z_rows: np.ndarray, ridge: float = 1e-3) -> None:
        """Ridge fit of normalised z on normalised inputs (N, 9) -> (N, 5) [SI] for the linear skip."""
        x = (np.asarray(onboard_rows, np.float64) - self.in_mean.double().numpy()) / self.in_std.double().numpy()
        y = (np.asarray(z_rows, np.float64) - self.z_mean.double().numpy()) / self.z_std.double().numpy()
        ok = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(y), axis=1)
        x1 = np.concatenate([x[ok], np.ones((int(ok.sum()), 1))], axis=1)
        gram = x1.T @ x1 + ridge * len(x1) * np.diag([1.0] * x.shape[1] + [0.0])
        coef = np.linalg.solve(gram, x1.T @ y[ok])
        self.skip.weight.copy_(torch.as_tensor(coef[:-1].T, dtype=torch.float32))
        self.skip.bias.copy_(torch.as_tensor(coef[-1], dtype=torch.float32))

    def forward(self, onboard: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``onboard`` (B, L, 9) raw SI -> (mean (B, L-H, 5) SI, var (B, L-H, 5) SI^2)."""
        cfg = self.cfg
        x = (onboard - self.in_mean) / self.in_std  # (B, L, 9)
        mean_n, var_n = self.heads(self.features(x))  # (B, L-H, 5)
        mean_n = mean_n + self.skip(x[:, cfg.encoder_len:])
        return mean_n * self.z_std + self.z_mean, var_n * (self.z_std * self.z_std)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


class NnVdm(_Base):
    """NN-VDM: a GRU over the window; the decoder steps read its hidden states."""

    def __init__(self, cfg: BaselineConfig, *stats) -> None:
        super().__init__(cfg, *stats)
        self.rnn = nn.GRU(cfg.num_signals, cfg.hidden, num_layers=cfg.n_layers, batch_first=True)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.rnn(x)  # (B, L, hidden)
        return h[:, self.cfg.encoder_len:]


class DlAvl(_Base):
    """DL-AVL: an LSTM over the window."""

    def __init__(self, cfg: BaselineConfig, *stats) -> None:
        super().__init__(cfg, *stats)
        self.rnn = nn.LSTM(cfg.num_signals, cfg.hidden, num_layers=cfg.n_layers, batch_first=True)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.rnn(x)
        return h[:, self.cfg.encoder_len:]


class RnnEkf(_Base):
    """RNN-EKF: GRU states, multi-head attention of each decoder step over the whole window, and a
    separate learned adaptive-noise head on the attention context (the EKF's R_t)."""

    def __init__(self, cfg: BaselineConfig, *stats) -> None:
        super().__init__(cfg, *stats)
        self.rnn = nn.GRU(cfg.num_signals, cfg.hidden, num_layers=cfg.n_layers, batch_first=True)
        self.attn = nn.MultiheadAttention(cfg.hidden, cfg.n_heads, batch_first=True)
        self.noise = nn.Sequential(nn.Linear(2 * cfg.hidden, cfg.hidden), nn.Tanh(),
                                   nn.Linear(cfg.hidden, cfg.num_states))
        with torch.no_grad():
            self.noise[-1].weight.mul_(0.1)
            self.noise[-1].bias.fill_(_SOFTPLUS_ONE)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.rnn(x)  # (B, L, hidden)
        q = h[:, self.cfg.encoder_len:]  # (B, L-H, hidden)
        ctx, _ = self.attn(q, h, h, need_weights=False)
        self._noise_in = torch.cat([q, ctx], dim=-1)  # (B, L-H, 2 hidden)
        return q + ctx

    def heads(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean_n, _ = super().heads(feat)
        return mean_n, F.softplus(self.noise(self._noise_in)) + self.cfg.var_floor


class BackpropKf(_Base):
    """Backprop-KF: a feed-forward observation model on each step's last ``kernel`` samples (no
    recurrence: the temporal structure is left to the filter it is trained through)."""

    def __init__(self, cfg: BaselineConfig, *stats) -> None:
        super().__init__(cfg, *stats)
        self.conv = nn.Conv1d(cfg.num_signals, cfg.hidden, cfg.kernel)
        self.mlp = nn.Sequential(nn.Tanh(), nn.Linear(cfg.hidden, cfg.hidden), nn.Tanh())

    def features(self, x: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg
        seg = x[:, cfg.encoder_len - cfg.kernel + 1:].transpose(1, 2)  # (B, 9, L-H+k-1)
        return self.mlp(self.conv(seg).transpose(1, 2))  # (B, L-H, hidden)


BASELINES: dict[str, type[_Base]] = {"nn-vdm": NnVdm, "dl-avl": DlAvl, "rnn-ekf": RnnEkf, "backprop-kf": BackpropKf}
DISPLAY_NAMES = {"nn-vdm": "NN-VDM", "dl-avl": "DL-AVL", "rnn-ekf": "RNN-EKF", "backprop-kf": "Backprop-KF"}


def build_baseline(cfg: BaselineConfig, norm_mean, norm_std, z_mean, z_std) -> _Base:
    """The baseline module of ``cfg.kind`` with the given statistics ((9,), (9,), (5,), (5,) [SI])."""
    cfg.validate()
    return BASELINES[cfg.kind](cfg, norm_mean, norm_std, z_mean, z_std)
