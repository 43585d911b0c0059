"""A training run's folder: its metrics.jsonl, last.pt and best.pt, and resuming from them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from prml2_edge.errors import ConfigError, ModelError
from prml2_edge.training.checkpoint import read_checkpoint, save_checkpoint
from prml2_edge.training.model import Prml2Model
from prml2_edge.training.presets import ModelConfig, TrainConfig, model_config_from_dict, train_config_from_dict
from prml2_edge.training.train_data import TrainData


def write_jsonl(path: Path, record: dict) -> None:
    with path.open("a") as fh:
        fh.write(json.dumps(record, sort_keys=True) + "\n")


def keep_last_as_best(last_path: Path, best_path: Path) -> None:
    """Every epoch had a non-finite validation objective: keep the last weights as "best"."""
    ckpt = read_checkpoint(last_path)
    ckpt.pop("optimizer", None)
    save_checkpoint(ckpt, best_path)


def resume_run(resume: str | Path, model: Prml2Model, optimizer: torch.optim.Optimizer, counters: dict[str, float],
            model_cfg: ModelConfig, train_cfg: TrainConfig, data: TrainData,
            metrics_path: Path) -> tuple[int, float, list[dict]]:
    """Load a ``last.pt`` into ``model``/``optimizer``/``counters``: ``(start epoch, best score, history so far)``."""
    ckpt = read_checkpoint(resume)
    if ckpt.get("optimizer") is None:
        raise ModelError(f"{resume} has no optimizer state; resume from a run's last.pt")
    if model_config_from_dict(ckpt["model_config"]) != model_cfg:
        raise ConfigError(f"{resume} was trained with another model config; use the same --preset")
    if train_config_from_dict(ckpt["train_config"]) != train_cfg:
        raise ConfigError(f"{resume} was trained with other training options; repeat the original ones")
    if ckpt["dataset_fingerprint"] != data.fingerprint:
        raise ConfigError(f"{resume} was trained on another dataset (fingerprint {ckpt['dataset_fingerprint']})")
    model.load_state_dict(ckpt["model"])
    optimizer.load_state_dict(ckpt["optimizer"])
    start_epoch = int(ckpt["epoch"])
    best_score = math.inf if ckpt.get("best_score") is None else float(ckpt["best_score"])
    counters.update(ckpt.get("counters", {}))
    history: list[dict] = []
    if metrics_path.is_file():
        history = [json.loads(line) for line in metrics_path.read_text().splitlines() if line.strip()]
        history = [h for h in history if h.get("epoch", 0) <= start_epoch]
    return start_epoch, best_score, history


def start_metrics(out_dir: Path, metrics_path: Path, best_path: Path, resumed_history: list[dict] | None) -> None:
    """Create the run directory; a new run starts an empty ``metrics.jsonl``, a resumed one keeps its epochs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if resumed_history is None:
        metrics_path.write_text("")
        best_path.unlink(missing_ok=True)
    else:  # drop records of epochs after the checkpoint
        metrics_path.write_text("".join(json.dumps(h, sort_keys=True) + "\n" for h in resumed_history))
