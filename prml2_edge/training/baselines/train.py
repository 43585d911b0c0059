"""Training and export of the learned baselines (same data, NLL and guard as PRML2's trainer).

NN-VDM, DL-AVL and RNN-EKF are trained with the Gaussian NLL (Eq. nll_loss) after the physics
guard; Backprop-KF with NLL plus the EKF position term (Eq. total_loss_single) from the first
epoch on, its observation model learning through the differentiable filter. Adam, cosine
learning rate, gradient clipping; the checkpoint with the lowest validation objective is kept.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.errors import ConfigError, ModelError
from prml2_edge.progress import Progress
from prml2_edge.training.baselines.models import BaselineConfig, build_baseline
from prml2_edge.training.guard_torch import PhysicsGuard
from prml2_edge.training.losses import initial_state, nll_loss, position_loss, to_window_frame

log = logging.getLogger(__name__)
FORMAT = "prml2-baseline/1"
EKF_DTYPE = torch.float64


@dataclass(frozen=True)
class BaselineTrainConfig:
    """Training options of a baseline (sized for a few CPU minutes)."""

    epochs: int = 3
    batch_size: int = 32
    lr: float = 1e-3
    max_train_windows: int = 2048  # random training windows per epoch (0: all)
    max_val_windows: int = 256
    grad_clip: float = 10.0
    beta: float = 8.0  # position-loss scale (Backprop-KF)
    mu: float = 1.0
    seed: int = 0
    num_threads: int = 2

    def validate(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or not self.lr > 0:
            raise ConfigError("epochs and batch_size must be >= 1 and lr > 0")


def _cosine(lr0: float, step: int, total: int) -> float:
    return 0.5 * lr0 * (1.0 + math.cos(math.pi * min(step, total) / max(total, 1)))


class _Objective:
    """NLL (+ EKF position term for Backprop-KF) of a batch, per window averaged."""

    def __init__(self, model, cfg: BaselineConfig, tcfg: BaselineTrainConfig) -> None:
        from prml2_edge.training import ekf_torch

        self.model = model
        self.guard = PhysicsGuard(mu=tcfg.mu)
        self.through_filter = cfg.kind == "backprop-kf"
        self.beta = tcfg.beta
        self.H = cfg.encoder_len
        self.ekf = ekf_torch
        self.Q = ekf_torch.default_process_noise(schema.DT_S, dtype=EKF_DTYPE, device=torch.device("cpu"))
        self.P0 = ekf_torch.default_initial_covariance(dtype=EKF_DTYPE, device=torch.device("cpu"))

    def __call__(self, batch) -> torch.Tensor:
        onboard, z, pose = batch
        onboard_t = torch.as_tensor(np.ascontiguousarray(onboard), dtype=torch.float32)  # (b, L, 9)
        z_t = torch.as_tensor(np.ascontiguousarray(z), dtype=torch.float32)[:, self.H:]  # (b, L-H, 5)
        mean, var = self.guard(*self.model(onboard_t))
        loss = nll_loss(mean, var, z_t, self.model.z_std)
        if self.through_filter:
            d_gt = to_window_frame(torch.as_tensor(np.asarray(pose, dtype=np.float64)), self.H)[:, self.H:]
            x0 = initial_state(z_t[:, 0].to(EKF_DTYPE))
            x_seq, _ = self.ekf.run_filter(x0, self.P0.expand(len(x0), -1, -1), mean.to(EKF_DTYPE),
                                           var.to(EKF_DTYPE), Q=self.Q, dt_s=schema.DT_S, update_first=True)
            loss = loss + position_loss(x_seq[..., schema.EkfState.POS], d_gt, self.beta).to(loss.dtype)
        return loss.mean()


def fit_baseline(data, out_dir: str | Path, cfg: BaselineConfig, tcfg: BaselineTrainConfig,
                 progress: bool | None = None) -> Path:
    """Train baseline ``cfg.kind`` on ``data`` (:class:`prml2_edge.training.trainer.TrainData`).

    Writes ``best.pt`` (lowest validation objective) and ``metrics.jsonl`` to ``out_dir``;
    returns the path of ``best.pt``.
    """
    cfg.validate()
    tcfg.validate()
    if len(data.train) == 0 or len(data.val) == 0:
        raise ConfigError("need training and validation windows")
    torch.manual_seed(tcfg.seed)
    torch.set_num_threads(tcfg.num_threads)
    rng = np.random.default_rng(tcfg.seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model = build_baseline(cfg, data.norm_mean, data.norm_std, data.z_mean, data.z_std)
    if data.skip_rows is not None:
        model.init_skip(*data.skip_rows)
    objective = _Objective(model, cfg, tcfg)
    opt = torch.optim.Adam(model.parameters(), lr=tcfg.lr)
    n_train = len(data.train) if tcfg.max_train_windows <= 0 else min(len(data.train), tcfg.max_train_windows)
    steps_per_epoch = -(-n_train // tcfg.batch_size)
    total = steps_per_epoch * tcfg.epochs
    val_idx = np.linspace(0, len(data.val) - 1, min(len(data.val), tcfg.max_val_windows)).astype(int)
    best = math.inf
    best_path = out / "best.pt"
    metrics_path = out / "metrics.jsonl"
    metrics_path.write_text("")
    t0 = time.monotonic()
    step = 0
    for epoch in range(1, tcfg.epochs + 1):
        model.train()
        idx = rng.permutation(len(data.train))[:n_train]
        bar = Progress(steps_per_epoch, desc=f"{cfg.kind} epoch {epoch}/{tcfg.epochs}", unit="step", enabled=progress)
        losses = []
        for i in range(0, n_train, tcfg.batch_size):
            for g in opt.param_groups:
                g["lr"] = _cosine(tcfg.lr, step, total)
            loss = objective(data.train.get(np.sort(idx[i:i + tcfg.batch_size])))
            opt.zero_grad(set_to_none=True)
            if torch.isfinite(loss):
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), tcfg.grad_clip)
                opt.step()
                losses.append(float(loss.detach()))
            step += 1
            bar.update(1)
        bar.close()
        model.eval()
        with torch.no_grad():
            val = float(np.mean([float(objective(data.val.get(val_idx[j:j + 64])))
                                 for j in range(0, len(val_idx), 64)]))
        record = {"epoch": epoch, "train": float(np.mean(losses)) if losses else None, "val_objective": val,
                  "wall_s": round(time.monotonic() - t0, 1)}
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        log.info("%s epoch %d: train %.2f, val %.2f (%.0f s)", cfg.kind, epoch, record["train"] or math.nan, val,
                 record["wall_s"])
        if val < best:
            best = val
            torch.save(make_checkpoint(model, cfg, tcfg, data.fingerprint, epoch, val), best_path)
    return best_path


def make_checkpoint(model, cfg: BaselineConfig, tcfg: BaselineTrainConfig, fingerprint: str, epoch: int,
                    val_objective: float) -> dict[str, Any]:
    """A self-describing checkpoint (plain data + the state dict)."""
    from prml2_edge.training.checkpoint import code_version

    return {"format": FORMAT, "preset": f"baseline:{cfg.kind}", "model_config": asdict(cfg),
            "train_config": asdict(tcfg), "model": model.state_dict(), "epoch": epoch, "stage": "baseline",
            "metrics": {"val_objective": val_objective}, "dataset_fingerprint": fingerprint,
            "code_version": code_version()}


def load_baseline(path: str | Path):
    """``(model, checkpoint)`` from a baseline ``best.pt``."""
    ckpt = torch.load(str(path), map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ModelError(f"{path}: not a baseline checkpoint (format {FORMAT})")
    cfg = BaselineConfig(**ckpt["model_config"])
    model = build_baseline(cfg, np.zeros(cfg.num_signals), np.ones(cfg.num_signals), np.zeros(cfg.num_states),
                           np.ones(cfg.num_states))
    model.load_state_dict(ckpt["model"])
    return model.eval(), ckpt


def export_baseline(checkpoint: str | Path, out_path: str | Path, parity_windows: np.ndarray | None = None) -> dict:
    """Export a baseline checkpoint to ONNX with PRML2 metadata; returns ``{"path", "max_abs_diff"}``.

    ``parity_windows`` (N, L, 9) [SI]: when given, the ONNX outputs are compared with torch's.
    """
    from prml2_edge.training.export_onnx import export_onnx, metadata_for, ort_session, run_ort

    model, ckpt = load_baseline(checkpoint)
    path = export_onnx(model, metadata_for(model, ckpt), out_path)
    diff = None
    if parity_windows is not None and len(parity_windows):
        sess = ort_session(path)
        mean_o, var_o = run_ort(sess, np.asarray(parity_windows, dtype=np.float32))
        with torch.no_grad():
            mean_t, var_t = model(torch.as_tensor(np.asarray(parity_windows, dtype=np.float32)))
        diff = float(max(np.abs(mean_o - mean_t.numpy()).max(), np.abs(var_o - var_t.numpy()).max()))
    return {"path": str(path), "max_abs_diff": diff}


def is_baseline_checkpoint(path: str | Path) -> bool:
    """True when ``path`` is a checkpoint written by :func:`fit_baseline`."""
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=False)
    except Exception:  # noqa: BLE001 - unreadable here: let the PRML2 loader report it
        return False
    return isinstance(ckpt, dict) and ckpt.get("format") == FORMAT
