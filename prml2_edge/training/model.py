"""The PRML2 transformer encoder-decoder (paper Sec. III-B, "Machine Learning Model").

The model takes a raw onboard window in SI units, canonical signal order
(:data:`prml2_edge.schema.SIGNAL_NAMES`), and returns, for each of the L - H decoder steps,
the mean and a strictly positive variance of z = [v_x, v_y, a_x, a_y, omega_z] in SI units
(vehicle frame), *before* the physics guard (which runs after the model: torch
``PhysicsGuard`` in training, NumPy ``physics_guard`` at runtime).

Inside: input normalisation with the dataset statistics (buffers), a linear input projection
plus a learned positional encoding, a transformer encoder over the first H steps, a transformer
decoder whose queries are the last L - H steps and which attends to the encoder output, and a
linear head giving the normalised mean and a softplus variance with a floor; both are
de-normalised with the training split's z statistics (buffers) so the outputs are SI.

One addition to the paper's description: a linear skip from each decoder step's normalised
inputs to its normalised mean. The final LayerNorm makes the transformer's output depend on
the inputs' scale only non-linearly, so an exact linear relation such as v_x ~ mean wheel
speed takes many steps to learn; with the skip the transformer learns the correction to it
(:meth:`Prml2Model.init_skip` starts it at the least-squares fit on the training split).

The attention is our own small module (no ``nn.MultiheadAttention`` fast path): fused
``scaled_dot_product_attention`` in training, written out as MatMul/Softmax while exporting, so
that the graph exports to ONNX with a fixed shape and the same numbers in onnxruntime.
Layers are pre-norm (LayerNorm before attention / feed-forward): with the few epochs a CPU
budget allows it converges more reliably than the original post-norm layout.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from prml2_edge import schema
from prml2_edge.errors import ModelError
from prml2_edge.training.presets import ModelConfig

_YAW_IN = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index  # the CAN yaw rate among the inputs
_OMEGA_OUT = schema.Z.OMEGA_Z  # omega_z among the outputs
STD_FLOOR = 1e-3  # smallest normalisation std [signal unit]; a constant signal must not divide by ~0
_SOFTPLUS_ONE = math.log(math.e - 1.0)  # softplus(x) = 1 at this x


def _exporting() -> bool:
    """True while tracing for ONNX export: the attention is then written out as MatMul/Softmax."""
    return torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()


class MultiHeadAttention(nn.Module):
    """Scaled dot-product multi-head attention of queries ``x`` over keys/values ``memory``."""

    def __init__(self, d_model: int, n_heads: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.d_head = d_model // n_heads
        self.q_proj = nn.Linear(d_model, d_model)
        self.k_proj = nn.Linear(d_model, d_model)
        self.v_proj = nn.Linear(d_model, d_model)
        self.out_proj = nn.Linear(d_model, d_model)
        self.dropout = nn.Dropout(dropout)
        self.scale = 1.0 / math.sqrt(self.d_head)

    def _split(self, t: torch.Tensor) -> torch.Tensor:
        b, n, _ = t.shape
        return t.reshape(b, n, self.n_heads, self.d_head).transpose(1, 2)  # (B, h, n, d_head)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        """``x`` (B, T, d), ``memory`` (B, S, d) -> (B, T, d)."""
        q = self._split(self.q_proj(x))  # (B, h, T, dh)
        k = self._split(self.k_proj(memory))  # (B, h, S, dh)
        v = self._split(self.v_proj(memory))  # (B, h, S, dh)
        if _exporting() or (self.training and self.dropout.p > 0):
            att = torch.softmax(torch.matmul(q, k.transpose(-2, -1)) * self.scale, dim=-1)  # (B, h, T, S)
            y = torch.matmul(self.dropout(att), v)  # (B, h, T, dh)
        else:  # the same maths, fused: about 2x faster on CPU for training
            y = F.scaled_dot_product_attention(q, k, v)  # (B, h, T, dh)
        b, _, t, _ = y.shape
        return self.out_proj(y.transpose(1, 2).reshape(b, t, self.n_heads * self.d_head))


class FeedForward(nn.Module):
    def __init__(self, d_model: int, d_ff: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.fc1 = nn.Linear(d_model, d_ff)
        self.fc2 = nn.Linear(d_ff, d_model)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.dropout(F.gelu(self.fc1(x))))


def _pre_norm_attention(cfg: ModelConfig) -> tuple[nn.LayerNorm, MultiHeadAttention]:
    """A pre-norm attention sublayer: the LayerNorm before it and the attention (created in that order)."""
    return nn.LayerNorm(cfg.d_model), MultiHeadAttention(cfg.d_model, cfg.n_heads, cfg.dropout)


def _pre_norm_feed_forward(cfg: ModelConfig) -> tuple[nn.LayerNorm, FeedForward]:
    """A pre-norm feed-forward sublayer: the LayerNorm before it and the feed-forward block."""
    return nn.LayerNorm(cfg.d_model), FeedForward(cfg.d_model, cfg.d_ff, cfg.dropout)


class EncoderLayer(nn.Module):
    """Pre-norm self-attention + feed-forward block."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.norm1, self.attn = _pre_norm_attention(cfg)
        self.norm2, self.ff = _pre_norm_feed_forward(cfg)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, H, d)
        h = self.norm1(x)
        x = x + self.drop(self.attn(h, h))
        return x + self.drop(self.ff(self.norm2(x)))


class DecoderLayer(nn.Module):
    """Pre-norm self-attention, cross-attention to the encoder output, feed-forward."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.norm1, self.self_attn = _pre_norm_attention(cfg)
        self.norm2, self.cross_attn = _pre_norm_attention(cfg)
        self.norm3, self.ff = _pre_norm_feed_forward(cfg)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, rows: int | None = None) -> torch.Tensor:
        """``x`` (B, L-H, d), ``memory`` (B, H, d) -> (B, L-H, d); with ``rows`` only the last ``rows``
        query rows are computed, (B, rows, d): the same numbers as the full layer's last rows (the self
        attention still reads keys and values from every row), for a fraction of the work."""
        h = self.norm1(x)
        if rows is not None:
            x, q = x[:, -rows:], h[:, -rows:]
        else:
            q = h
        x = x + self.drop(self.self_attn(q, h))
        x = x + self.drop(self.cross_attn(self.norm2(x), memory))
        return x + self.drop(self.ff(self.norm3(x)))


def _as_tensor(values, n: int, what: str) -> torch.Tensor:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ModelError(f"{what} must be {n} finite numbers, got shape {arr.shape}")
    return torch.tensor(arr, dtype=torch.float32)


class Prml2Model(nn.Module):
    """PRML2 measurement model g_ml(z | O_t; Theta).

    Parameters
    ----------
    cfg
        Model hyper-parameters.
    norm_mean, norm_std
        (9,) onboard normalisation statistics [SI, canonical order] (the dataset's).
    z_mean, z_std
        (5,) statistics of z on the training split [SI, z order]; outputs are de-normalised with them.

    ``forward(onboard)`` with ``onboard`` (B, L, 9) float32 raw SI returns ``(mean, var)``, each
    (B, L - H, 5) in SI units (m/s, m/s^2, rad/s and their squares), ``var > 0``.
    """

    def __init__(self, cfg: ModelConfig, norm_mean, norm_std, z_mean, z_std) -> None:
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.register_buffer("in_mean", _as_tensor(norm_mean, cfg.num_signals, "norm_mean"))
        self.register_buffer("in_std", _as_tensor(norm_std, cfg.num_signals, "norm_std").clamp_min(STD_FLOOR))
        self.register_buffer("z_mean", _as_tensor(z_mean, cfg.num_states, "z_mean"))
        self.register_buffer("z_std", _as_tensor(z_std, cfg.num_states, "z_std").clamp_min(STD_FLOOR))
        d = cfg.d_model
        self.input_proj = nn.Linear(cfg.num_signals, d)
        self.pos_embedding = nn.Parameter(torch.randn(cfg.window_len, d) * 0.02)  # learned, (L, d)
        self.encoder = nn.ModuleList([EncoderLayer(cfg) for _ in range(cfg.n_layers)])
        self.decoder = nn.ModuleList([DecoderLayer(cfg) for _ in range(cfg.n_layers)])
        self.enc_norm = nn.LayerNorm(d)
        self.dec_norm = nn.LayerNorm(d)
        self.head = nn.Linear(d, 2 * cfg.num_states)
        # linear skip from each decoder step's normalised inputs to its normalised mean (zero at start)
        self.skip = nn.Linear(cfg.num_signals, cfg.num_states)
        with torch.no_grad():
            self.skip.weight.zero_()
            self.skip.bias.zero_()
            self.head.weight.mul_(0.1)
            if cfg.omega_residual:  # the transformer's part of omega_z's correction starts at zero
                self.head.weight[_OMEGA_OUT].zero_()
            self.head.bias.zero_()
            self.head.bias[cfg.num_states:] = _SOFTPLUS_ONE  # start at unit normalised variance

    @torch.no_grad()
    def init_skip(self, onboard_rows: np.ndarray, z_rows: np.ndarray, ridge: float = 1e-3) -> None:
        """Set the linear skip to the ridge-regression fit of normalised z on normalised inputs.

        ``onboard_rows`` (N, 9) [SI] and ``z_rows`` (N, 5) [SI] are training samples. The
        transformer then starts from (and learns the correction to) the best per-step linear map,
        which the few hundred optimizer steps of a CPU budget would not reach from zero.
        """
        x = (np.asarray(onboard_rows, np.float64) - self.in_mean.double().numpy()) / self.in_std.double().numpy()
        x = self.features(torch.as_tensor(x)).numpy()
        y = (np.asarray(z_rows, np.float64) - self.z_mean.double().numpy()) / self.z_std.double().numpy()
        if self.cfg.omega_residual:  # fit the correction to the CAN yaw rate, not omega_z itself
            y[:, _OMEGA_OUT] -= self.omega_cue(torch.as_tensor(np.asarray(onboard_rows, np.float64))).numpy()
        ok = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(y), axis=1)
        x1 = np.concatenate([x[ok], np.ones((int(ok.sum()), 1))], axis=1)  # (N, 10)
        gram = x1.T @ x1 + ridge * len(x1) * np.diag([1.0] * x.shape[1] + [0.0])
        coef = np.linalg.solve(gram, x1.T @ y[ok])  # (10, 5)
        self.skip.weight.copy_(torch.as_tensor(coef[:-1].T, dtype=torch.float32))
        self.skip.bias.copy_(torch.as_tensor(coef[-1], dtype=torch.float32))

    def omega_cue(self, onboard: torch.Tensor) -> torch.Tensor:
        """The CAN yaw rate of raw SI ``onboard`` (..., 9) in normalised omega_z units (...): the residual
        form's starting point (``cfg.omega_residual``)."""
        w = _OMEGA_OUT
        return (onboard[..., _YAW_IN] - self.z_mean[w].to(onboard.dtype)) / self.z_std[w].to(onboard.dtype)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The model's input features from normalised signals ``x`` (..., 9): ``x`` itself, or with
        ``cfg.wheel_diff_gain > 0`` the wheel channels replaced by [front mean, rear mean,
        gain * (fr - fl), gain * (rr - rl)] (element-wise ops only, so int8 export leaves them in fp32)."""
        g = self.cfg.wheel_diff_gain
        if g <= 0:
            return x
        fl, fr, rl, rr = (x[..., i : i + 1] for i in schema.WHEEL_SPEED_INDICES)
        first = schema.WHEEL_SPEED_INDICES[0]
        return torch.cat([x[..., :first], 0.5 * (fl + fr), 0.5 * (rl + rr), g * (fr - fl), g * (rr - rl),
                          x[..., first + 4 :]], dim=-1)

    def forward_normalised(self, onboard: torch.Tensor, rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and variance in normalised z units: each (B, L - H, 5), or (B, rows, 5) for the newest
        ``rows`` decoder steps only (the last decoder layer then computes just those query rows)."""
        cfg = self.cfg
        if rows is not None and not 1 <= rows <= cfg.decoder_len:
            raise ModelError(f"rows must be in [1, {cfg.decoder_len}], got {rows}")
        x = self.features((onboard - self.in_mean) / self.in_std)  # (B, L, 9)
        h = self.input_proj(x) + self.pos_embedding  # (B, L, d)
        enc = h[:, : cfg.encoder_len]  # (B, H, d)
        dec = h[:, cfg.encoder_len :]  # (B, L-H, d)
        for layer in self.encoder:
            enc = layer(enc)
        memory = self.enc_norm(enc)
        last = len(self.decoder) - 1
        for i, layer in enumerate(self.decoder):
            dec = layer(dec, memory, rows if i == last else None)
        out = self.head(self.dec_norm(dec))  # (B, L-H or rows, 10)
        n = dec.shape[1]
        mean_n = out[..., : cfg.num_states] + self.skip(x[:, cfg.window_len - n :])  # (B, n, 5)
        if cfg.omega_residual:  # omega_z = the CAN yaw rate + the correction
            w = _OMEGA_OUT
            cue = self.omega_cue(onboard[:, cfg.window_len - n :]).unsqueeze(-1)  # (B, n, 1)
            mean_n = torch.cat([mean_n[..., :w], mean_n[..., w : w + 1] + cue, mean_n[..., w + 1 :]], dim=-1)
        var_n = F.softplus(out[..., cfg.num_states :]) + cfg.var_floor
        return mean_n, var_n

    def forward(self, onboard: torch.Tensor, rows: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``onboard`` (B, L, 9) raw SI -> (mean (B, L-H, 5) SI, var (B, L-H, 5) SI^2); with ``rows``,
        the newest ``rows`` decoder steps only, (B, rows, 5) each."""
        mean_n, var_n = self.forward_normalised(onboard, rows)
        return mean_n * self.z_std + self.z_mean, var_n * (self.z_std * self.z_std)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())


def check_window(onboard: torch.Tensor, cfg: ModelConfig) -> None:
    """Shape assert for entry points: ``onboard`` must be (B, L, 9)."""
    if onboard.ndim != 3 or onboard.shape[1:] != (cfg.window_len, schema.NUM_SIGNALS):
        raise ModelError(
            f"onboard window must be (B, {cfg.window_len}, {schema.NUM_SIGNALS}), got {tuple(onboard.shape)}"
        )
