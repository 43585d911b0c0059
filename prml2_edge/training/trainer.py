"""Two-stage PRML2 training (paper Sec. III-D, IV-A; method.md "Model").

1. **Pretraining** (the first 70 % of the epochs, or all of them with ``finetune=False``,
   which is PRML2*): NLL (Eq. nll_loss) of the guarded predictions.
2. **Fine-tuning** (the last 30 %): NLL + beta * tanh(sum_t ||d_t - d_t^gt||^2 / beta) with d_t
   the a-posteriori positions of the differentiable EKF run over the decoder steps, started from
   the ground-truth state at the first decoder step in the window-local frame. With
   ``ft_horizon_s > 0`` the filter instead runs across consecutive windows over segments of that
   length, fed as streaming inference feeds it (each window's newest ``ft_rows`` steps), started
   from the ground truth at the segment's first sample, with the squared errors averaged over the
   segment: NLL of those steps + beta * tanh(mean_t ||d_t - d_t^gt||^2 / beta).

Adam with one cosine learning-rate schedule over all epochs (``lr_schedule="cosine"``), so
PRML2 and PRML2* (same seed) are identical up to the switch and differ only in the fine-tuning
loss of the last 30 %: a clean ablation. ``"cosine_restart"`` restarts the cosine at the switch
(measured on the benchmark: the jump back to the full rate undoes part of the pretraining, and
PRML2 ended worse than PRML2*). The physics guard (``PhysicsGuard(mu)``) follows the model in
both stages.

Validation every epoch on the validation windows (NLL, position term, z RMSE); the best
checkpoint of the *last stage that ran* is kept as ``best.pt`` (lowest validation NLL for
pretraining, lowest validation NLL + position term for fine-tuning, so the shipped PRML2 model
is always a fine-tuned one). ``last.pt`` (with the optimizer) is written every epoch for
resuming. Steps whose gradient norm is not finite, or exceeds ``explode_ratio`` times its running
(exponential moving, log-domain) average, are skipped and counted. Seeded: the weights depend
only on the seed, the data and the world size; each epoch's shuffle is drawn from
``(seed, epoch)``, so a resumed run equals an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from prml2_edge import schema
from prml2_edge.errors import ConfigError
from prml2_edge.progress import Progress
from prml2_edge.training import distributed as ddp
from prml2_edge.training.augment import augment
from prml2_edge.training.checkpoint import make_checkpoint, save_checkpoint
from prml2_edge.training.epoch_validation import PositionFilter, evaluate_windows, to_tensors, window_batches
from prml2_edge.training.guard_torch import PhysicsGuard
from prml2_edge.training.losses import nll_loss, physics_consistency_loss, position_loss
from prml2_edge.training.model import Prml2Model
from prml2_edge.training.presets import ModelConfig, TrainConfig
from prml2_edge.training.run_dir import keep_last_as_best, resume_run, start_metrics, write_jsonl
from prml2_edge.training.train_data import TrainData, WindowSource, check_data, describe, prepare_data, z_statistics

log = logging.getLogger(__name__)

PRETRAIN = "pretrain"
FINETUNE = "finetune"
INITIAL = "initial"  # a transfer run's epoch 0: the model it started from, validated on the new car


@dataclass
class FitResult:
    """What :func:`fit` produced (paths are under the run directory)."""

    out_dir: Path
    best_path: Path
    last_path: Path
    metrics_path: Path
    history: list[dict] = field(default_factory=list)
    wall_s: float = 0.0
    counters: dict = field(default_factory=dict)
    model: Prml2Model | None = None  # the trained model (last epoch's weights, this rank's copy)


def cosine_lr(lr0: float, step: int, total_steps: int) -> float:
    """Cosine schedule from ``lr0`` at step 0 towards 0 at ``total_steps`` (one stage)."""
    if total_steps <= 1:
        return lr0
    return 0.5 * lr0 * (1.0 + math.cos(math.pi * min(step, total_steps) / total_steps))


def _stage_of(epoch: int, cfg: TrainConfig) -> str:
    return PRETRAIN if epoch < cfg.pretrain_epochs() else FINETUNE


def _windows_per_epoch(n_windows: int, cfg: TrainConfig) -> int:
    return min(n_windows, cfg.max_train_windows) if cfg.max_train_windows > 0 else n_windows


def _steps_per_epoch(n_windows: int, cfg: TrainConfig, world_size: int) -> int:
    n = _windows_per_epoch(n_windows, cfg)
    per_rank = -(-n // world_size)
    per_rank_batch = max(1, cfg.batch_size // world_size)
    return max(1, -(-per_rank // per_rank_batch))


@dataclass
class _Loop:
    """What every epoch and step of :func:`fit` shares (one run, this rank)."""

    model: Prml2Model
    train_model: torch.nn.Module  # ``model``, or its DDP wrapper
    guard: PhysicsGuard
    optimizer: torch.optim.Optimizer
    params: list[torch.nn.Parameter]
    filt: PositionFilter | None
    cfg: TrainConfig
    info: ddp.DistInfo
    counters: dict[str, float]
    H: int  # encoder length
    seq_len: int  # fine-tuning segment length [steps] (0: window fine-tuning)
    seq_rows: int  # newest rows of each window that tile a segment
    steps_per_epoch: int
    per_rank_batch: int


def fit(
    data: TrainData,
    out_dir: str | Path,
    *,
    preset: str,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    resume: str | Path | None = None,
    info: ddp.DistInfo | None = None,
    progress: bool | None = None,
    on_epoch: Callable[[dict], None] | None = None,
    init: Prml2Model | None = None,
) -> FitResult:
    """Train a PRML2 model on ``data``; write checkpoints, ``metrics.jsonl`` and ``loss_curve.png`` to ``out_dir``.

    Parameters
    ----------
    data
        Training and validation windows with statistics (:class:`TrainData`).
    out_dir
        Run directory (created). Only rank 0 writes.
    preset, model_cfg, train_cfg
        The preset name (recorded) and the configs (``train_cfg.finetune=False`` gives PRML2*).
    resume
        A ``last.pt`` to continue from: its model and train configs must equal the given ones,
        and its dataset fingerprint the data's.
    info
        Distributed context (:func:`prml2_edge.training.distributed.init`); default single process.
    progress
        Show a progress bar (default: unless ``PRML2_NO_PROGRESS=1``).
    on_epoch
        Called with each epoch's log record (rank 0).
    init
        Start from this trained model (transfer to a new car, ``prml2 train --init``): its weights, its
        config (``model_cfg`` must equal it) and its own normalisation statistics, which the data's do
        not replace (the inputs keep the scale the model learned).
    """
    t_start = time.monotonic()
    info = info or ddp.DistInfo()
    model_cfg.validate()
    train_cfg.validate()
    out_dir = Path(out_dir)
    metrics_path = out_dir / "metrics.jsonl"
    best_path, last_path = out_dir / "best.pt", out_dir / "last.pt"
    check_data(data)

    torch.manual_seed(train_cfg.seed)
    model = _initial_model(data, model_cfg, init)
    optimizer = torch.optim.Adam(model.parameters(), lr=train_cfg.lr, weight_decay=train_cfg.weight_decay)
    counters: dict[str, float] = {"steps": 0, "skipped_nonfinite": 0, "skipped_exploding": 0,
                                  "grad_log_ema": math.nan}
    start_epoch, best_score, history = 0, math.inf, []
    if resume is not None:
        start_epoch, best_score, history = resume_run(resume, model, optimizer, counters, model_cfg, train_cfg, data,
                                                   metrics_path)
    if info.is_main:
        start_metrics(out_dir, metrics_path, best_path, history if resume is not None else None)
    loop = _make_loop(model, optimizer, counters, model_cfg, train_cfg, info, len(data.train))
    floor = next((h["val_objective"] for h in history if h.get("stage") == INITIAL), math.inf)
    if init is not None and resume is None:
        floor = _validate_initial(loop, data, history, preset, out_dir)
        if info.is_main and on_epoch is not None:
            on_epoch(history[-1])
        if _stage_of(0, train_cfg) == _stage_of(train_cfg.epochs - 1, train_cfg):
            best_score = floor
    _run_epochs(loop, data, range(start_epoch, train_cfg.epochs), best_score, history, preset=preset,
                out_dir=out_dir, progress=progress, on_epoch=on_epoch, floor=floor)
    if info.is_main and not best_path.is_file() and last_path.is_file():
        keep_last_as_best(last_path, best_path)
    if info.enabled:
        torch.distributed.barrier()
    return FitResult(out_dir=out_dir, best_path=best_path, last_path=last_path, metrics_path=metrics_path,
                     history=history, wall_s=time.monotonic() - t_start, counters=dict(counters), model=model)


def _initial_model(data: TrainData, model_cfg: ModelConfig, init: Prml2Model | None) -> Prml2Model:
    """The model training starts from: ``init`` (its config must be ``model_cfg``), or a new one on ``data``."""
    if init is not None:
        if init.cfg != model_cfg:
            raise ConfigError("fit(init=...): model_cfg must be the initial model's config")
        return init.train()
    model = Prml2Model(model_cfg, data.norm_mean, data.norm_std, data.z_mean, data.z_std)
    if data.skip_rows is not None:
        model.init_skip(*data.skip_rows)
    return model


def _run_epochs(loop: _Loop, data: TrainData, epochs: range, best_score: float, history: list[dict], *,
                preset: str, out_dir: Path, progress: bool | None, on_epoch: Callable[[dict], None] | None,
                floor: float = math.inf) -> None:
    """Train and validate each of ``epochs``; append its record to ``history``; rank 0 saves and reports it.

    ``best_score`` is the best validation objective so far in the current stage (a new stage starts its own; the
    last stage starts from ``floor``, a transfer's initial model, so that only a better epoch replaces it).
    """
    train_cfg = loop.cfg
    last_stage = _stage_of(train_cfg.epochs - 1, train_cfg)
    lr = math.nan
    for epoch in epochs:
        stage = _stage_of(epoch, train_cfg)
        if epoch > 0 and stage != _stage_of(epoch - 1, train_cfg):
            best_score = floor if stage == last_stage else math.inf  # a new stage: its own best
        t_epoch = time.monotonic()
        sums, lr = _train_epoch(loop, data, epoch, stage, lr, progress)
        record = _epoch_record(loop, data, epoch, stage, lr, sums, t_epoch)
        improved = math.isfinite(record["val_objective"]) and record["val_objective"] < best_score
        if improved:
            best_score = record["val_objective"]
        record["best"] = improved
        history.append(record)
        if loop.info.is_main:  # a transfer's best.pt is its initial model until the last stage beats it
            keep = improved and (stage == last_stage or not math.isfinite(floor))
            _save_epoch(loop, record, history, keep, best_score, preset, data.fingerprint, out_dir, epoch, stage)
            if on_epoch is not None:
                on_epoch(record)


def _validate_initial(loop: _Loop, data: TrainData, history: list[dict], preset: str, out_dir: Path) -> float:
    """A transfer run's epoch 0: the model it starts from, validated on the new car's windows with the last stage's
    objective, logged and (rank 0) saved as ``best.pt``. Returns that objective: an epoch replaces the initial model
    only when it is better, so 8 minutes of a car cannot hand back a model worse on its validation drive."""
    cfg, info = loop.cfg, loop.info
    val = _validate(loop, data)
    record: dict[str, Any] = {"epoch": 0, "stage": INITIAL, **val,
                              "val_objective": _objective(val, _stage_of(cfg.epochs - 1, cfg))}
    score = record["val_objective"] if math.isfinite(record["val_objective"]) else math.inf
    record["best"] = math.isfinite(score)
    history.append(record)
    if info.is_main:
        _save_epoch(loop, record, history, record["best"], score, preset, data.fingerprint, out_dir, -1, INITIAL)
    return score


def _make_loop(model: Prml2Model, optimizer: torch.optim.Optimizer, counters: dict[str, float],
               model_cfg: ModelConfig, train_cfg: TrainConfig, info: ddp.DistInfo, n_train: int) -> _Loop:
    train_model: torch.nn.Module = model
    if info.enabled:
        train_model = torch.nn.parallel.DistributedDataParallel(model)
    filt = PositionFilter() if train_cfg.finetune else None
    seq_len, seq_rows = train_cfg.ft_horizon_steps(), train_cfg.ft_rows
    if train_cfg.finetune and seq_len and seq_rows > model_cfg.decoder_len:
        raise ConfigError(f"ft_rows = {seq_rows} exceeds the model's {model_cfg.decoder_len} decoder steps")
    return _Loop(model=model, train_model=train_model, guard=PhysicsGuard(mu=train_cfg.mu), optimizer=optimizer,
                 params=[p for p in model.parameters() if p.requires_grad], filt=filt, cfg=train_cfg, info=info,
                 counters=counters, H=model_cfg.encoder_len, seq_len=seq_len, seq_rows=seq_rows,
                 steps_per_epoch=_steps_per_epoch(n_train, train_cfg, info.world_size),
                 per_rank_batch=max(1, train_cfg.batch_size // info.world_size))


def _schedule(loop: _Loop, stage: str) -> tuple[int, int]:
    """``(first epoch, number of steps)`` of the cosine schedule the epochs of ``stage`` follow."""
    cfg = loop.cfg
    if cfg.lr_schedule == "cosine":  # one schedule over the whole run
        return 0, cfg.epochs * loop.steps_per_epoch
    # "cosine_restart": one schedule per stage
    stage_first = 0 if stage == PRETRAIN else cfg.pretrain_epochs()
    stage_epochs = cfg.pretrain_epochs() if stage == PRETRAIN else cfg.epochs - stage_first
    return stage_first, stage_epochs * loop.steps_per_epoch


def _epoch_batches(loop: _Loop, data: TrainData, epoch: int, seq: bool) -> list[np.ndarray]:
    """This rank's batches of one epoch: window indices, or segment starts when ``seq``."""
    cfg = loop.cfg
    n_train = len(data.train)
    rng = np.random.default_rng([cfg.seed, epoch])
    if seq:  # as many windows per epoch as the window epochs (each segment takes seq_len / seq_rows)
        candidates = data.train.segment_starts(loop.seq_len, cfg.window_stride)
        if len(candidates) == 0:
            raise ConfigError(f"no training segment of {cfg.ft_horizon_s:g} s (+ one window of history) "
                              "fits in a drive's training split; lower ft_horizon_s")
        n_seg = max(1, round(_windows_per_epoch(n_train, cfg) * loop.seq_rows / loop.seq_len))
        order = candidates[rng.permutation(len(candidates))[:n_seg]]
        batch_size = max(1, cfg.ft_segments // loop.info.world_size)
    else:
        order = rng.permutation(n_train)
        if cfg.max_train_windows > 0:
            order = order[: cfg.max_train_windows]
        batch_size = loop.per_rank_batch
    return window_batches(ddp.shard(order, loop.info), batch_size)


def _train_epoch(loop: _Loop, data: TrainData, epoch: int, stage: str, lr: float,
                 progress: bool | None) -> tuple[torch.Tensor, float]:
    """One epoch of steps: the summed ``(loss, nll, pos, windows)`` over applied steps (all ranks) and the last lr."""
    cfg = loop.cfg
    stage_first, stage_steps = _schedule(loop, stage)
    seq = stage == FINETUNE and loop.seq_len > 0  # fine-tuning over segments, the EKF across windows
    batches = _epoch_batches(loop, data, epoch, seq)
    sums = torch.zeros(4, dtype=torch.float64)  # loss, nll, pos, windows
    loop.guard.reset_stats()
    loop.train_model.train()
    bar = Progress(len(batches), desc=f"epoch {epoch + 1}/{cfg.epochs} {stage}", unit="batch",
                   enabled=(progress if loop.info.is_main else False))
    for step_in_epoch, idx in enumerate(batches):
        step = (epoch - stage_first) * loop.steps_per_epoch + step_in_epoch
        if seq:  # the schedule advances by window epochs, whatever the number of segment steps in one
            step = (epoch - stage_first + step_in_epoch / len(batches)) * loop.steps_per_epoch
        lr = cosine_lr(cfg.lr, step, stage_steps)
        for group in loop.optimizer.param_groups:
            group["lr"] = lr
        loss, nll, pos, n_items = _losses(loop, data, idx, stage, seq)
        if _optimizer_step(loop, loss):
            sums += torch.tensor([loss.item() * n_items, nll.mean().item() * n_items,
                                  float(pos.item()) * n_items, n_items], dtype=torch.float64)
        loop.counters["steps"] += 1
        bar.update()
        if step_in_epoch % 5 == 0:
            bar.set_postfix(f"loss {loss.item():.3g}")
    bar.close()
    return ddp.all_reduce_sum(sums, loop.info), lr


def _losses(loop: _Loop, data: TrainData, idx: np.ndarray, stage: str,
            seq: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """``(loss, per-item NLL, position term, items)`` of one batch (items: windows)."""
    cfg, guard = loop.cfg, loop.guard
    if seq:  # the newest seq_rows steps of each window tile its segment
        seq_len, seq_rows = loop.seq_len, loop.seq_rows
        onboard, z_gt, d_gt = to_tensors(data.train.get_segments(idx, seq_len, seq_rows), 0)
        mean, var = guard(*loop.train_model(onboard, rows=seq_rows))  # (b * seq_len / rows, rows, 5) each
        mean = mean.reshape(len(idx), seq_len, -1)  # windows are segment-major, in time order
        var = var.reshape(len(idx), seq_len, -1)
        pos_reduction, n_items = "mean", len(idx) * seq_len // seq_rows  # n_items: windows
    else:
        onboard, z, d_gt = to_tensors(data.train.get(idx), loop.H)
        onboard = augment(onboard, cfg, int(loop.counters["steps"]))
        mean, var = guard(*loop.train_model(onboard))  # (b, L-H, 5) each
        z_gt = z[:, loop.H:]
        pos_reduction, n_items = "sum", len(idx)
    nll = nll_loss(mean, var, z_gt, loop.model.z_std, cfg.nll_reduction)  # (b,)
    loss = nll.mean()
    if stage == PRETRAIN and cfg.pretrain_physics > 0:
        loss = loss + cfg.pretrain_physics * physics_consistency_loss(mean, schema.DT_S).mean().to(loss.dtype)
    pos = torch.zeros(())
    if stage == FINETUNE:  # the EKF from the ground truth at the first step of mean/var
        d = loop.filt.positions(mean, var, z_gt[:, 0])  # (b, L-H or seq_len, 2)
        pos = position_loss(d, d_gt, cfg.beta, pos_reduction).mean()
        loss = loss + pos.to(loss.dtype)
    return loss, nll, pos, n_items


def _optimizer_step(loop: _Loop, loss: torch.Tensor) -> bool:
    """Backpropagate ``loss`` and step, unless the gradient norm is not finite or explodes; True when stepped."""
    counters = loop.counters
    loop.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(loop.params, loop.cfg.grad_clip).item()  # after all-reduce
    # the decision uses the gradient norm only: after DDP's all-reduce it is the same on every
    # rank (a NaN loss on one rank makes the shared gradients NaN), so all ranks agree.
    ema = counters["grad_log_ema"]
    if not math.isfinite(grad_norm):
        counters["skipped_nonfinite"] += 1
        return False
    if math.isfinite(ema) and grad_norm > loop.cfg.explode_ratio * math.exp(ema):
        counters["skipped_exploding"] += 1
        return False
    log_g = math.log(max(grad_norm, 1e-30))
    counters["grad_log_ema"] = log_g if not math.isfinite(ema) else 0.9 * ema + 0.1 * log_g
    loop.optimizer.step()
    return True


def _epoch_record(loop: _Loop, data: TrainData, epoch: int, stage: str, lr: float, sums: torch.Tensor,
                  t_epoch: float) -> dict[str, Any]:
    """Validate and build the epoch's log record (``best`` is added by the caller)."""
    guard, info = loop.guard, loop.info
    train_fire = ddp.all_reduce_sum(torch.tensor([guard.n_fired, guard.n_predictions], dtype=torch.float64), info)
    train_time = time.monotonic() - t_epoch
    val = _validate(loop, data)
    n_used = max(sums[3].item(), 1.0)
    record: dict[str, Any] = {
        "epoch": epoch + 1,
        "stage": stage,
        "lr_end": lr,
        "train_loss": sums[0].item() / n_used,
        "train_nll": sums[1].item() / n_used,
        "train_pos": sums[2].item() / n_used if stage == FINETUNE else float("nan"),
        "train_windows": int(sums[3].item()),
        "train_guard_fire_rate": train_fire[0].item() / max(train_fire[1].item(), 1.0),
        **val,
        "train_time_s": train_time,
        "epoch_time_s": time.monotonic() - t_epoch,
        "train_windows_per_s": sums[3].item() / max(train_time, 1e-9),
        **{k: int(v) for k, v in loop.counters.items() if k != "grad_log_ema"},
    }
    record["val_objective"] = _objective(val, stage)
    return record


def _validate(loop: _Loop, data: TrainData) -> dict:
    """The model's validation metrics now (:func:`evaluate_windows` with the loop's guard, filter and batch)."""
    cfg = loop.cfg
    return evaluate_windows(loop.model, loop.guard, data.val, batch_size=max(loop.per_rank_batch, 64),
                            with_position=loop.filt is not None, filt=loop.filt, beta=cfg.beta, info=loop.info,
                            nll_reduction=cfg.nll_reduction)


def _objective(val: dict, stage: str) -> float:
    """What ``best.pt`` is chosen by in ``stage``: validation NLL, plus the position term when fine-tuning."""
    return val["val_nll"] + (val["val_pos"] if stage == FINETUNE else 0.0)


def _save_epoch(loop: _Loop, record: dict, history: list[dict], improved: bool, best_score: float, preset: str,
                fingerprint: str, out_dir: Path, epoch: int, stage: str) -> None:
    """Rank 0 after an epoch: the metrics line, ``last.pt``, ``best.pt`` when improved, the loss curve."""
    write_jsonl(out_dir / "metrics.jsonl", record)
    ckpt = make_checkpoint(loop.model, preset, loop.cfg, fingerprint, epoch=epoch + 1, stage=stage,
                           metrics=record, counters=loop.counters, optimizer=loop.optimizer, best_score=best_score)
    save_checkpoint(ckpt, out_dir / "last.pt")
    if improved:
        ckpt.pop("optimizer")
        save_checkpoint(ckpt, out_dir / "best.pt")
    from prml2_edge.viz import plots

    if plots.available():
        plots.plot_history(history, out_dir / "loss_curve.png")
    elif epoch == 0:  # matplotlib is part of the train extra; a missing plot is not fatal
        log.warning(plots.missing_message(str(out_dir / "loss_curve.png")))


__all__ = ["FitResult", "TrainData", "WindowSource", "describe", "evaluate_windows", "fit", "prepare_data",
           "z_statistics"]
