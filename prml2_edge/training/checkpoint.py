"""Self-describing checkpoints, loaded with ``torch.load(weights_only=True)`` (no pickled code).

A checkpoint is a plain dict of tensors and JSON-like data:

* ``model``: the state dict (weights and the normalisation buffers);
* ``model_config`` / ``train_config``: the dataclasses as dicts, ``preset``;
* ``signal_names``, ``signal_units``, ``state_names``, ``schema_hash``: the layout it was trained on;
* ``norm_mean`` / ``norm_std`` (9,) and ``z_mean`` / ``z_std`` (5,): normalisation statistics [SI];
* ``dataset_fingerprint``, ``code_version`` (package version + git commit when available);
* ``epoch`` (epochs completed), ``stage``, ``metrics`` (the epoch's log record), ``counters``;
* optionally ``optimizer`` (for resuming) and ``best_score``.
"""

from __future__ import annotations

import subprocess
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from prml2_edge import __version__, schema
from prml2_edge.errors import ModelError
from prml2_edge.training.model import Prml2Model
from prml2_edge.training.presets import ModelConfig, TrainConfig, model_config_from_dict

CHECKPOINT_FORMAT = "prml2-checkpoint/1"


def code_version() -> str:
    """``prml2-edge <version>`` plus the short git commit of the source tree when it is a checkout."""
    repo = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=False)
        commit = out.stdout.strip() if out.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return f"prml2-edge {__version__}" + (f" ({commit})" if commit else "")


def make_checkpoint(model: Prml2Model, preset: str, train_cfg: TrainConfig, dataset_fingerprint: str, *,
                    epoch: int, stage: str, metrics: dict | None = None, counters: dict | None = None,
                    optimizer: torch.optim.Optimizer | None = None, best_score: float | None = None,
                    version: str | None = None) -> dict[str, Any]:
    """The checkpoint dict for ``model`` (a bare :class:`Prml2Model`, not a DDP wrapper)."""
    ckpt: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "model": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "model_config": asdict(model.cfg),
        "train_config": asdict(train_cfg),
        "preset": preset,
        "signal_names": list(schema.SIGNAL_NAMES),
        "signal_units": [s.unit for s in schema.SIGNALS],
        "state_names": list(schema.STATE_NAMES),
        "schema_hash": schema.SCHEMA_HASH,
        "norm_mean": model.in_mean.tolist(),
        "norm_std": model.in_std.tolist(),
        "z_mean": model.z_mean.tolist(),
        "z_std": model.z_std.tolist(),
        "dataset_fingerprint": dataset_fingerprint,
        "code_version": version or code_version(),
        "epoch": int(epoch),
        "stage": stage,
        "metrics": dict(metrics or {}),
        "counters": dict(counters or {}),
        "best_score": None if best_score is None else float(best_score),
    }
    if optimizer is not None:
        ckpt["optimizer"] = optimizer.state_dict()
    return ckpt


def save_checkpoint(ckpt: dict[str, Any], path: str | Path) -> Path:
    """Write ``ckpt`` atomically (temp file, then rename) to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(ckpt, tmp)
    tmp.replace(path)
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint dict with ``weights_only=True`` and check its format and schema."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"checkpoint {path} not found; train one with 'prml2 train --data DIR --out RUN'")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises many types for corrupt files
        raise ModelError(f"checkpoint {path} cannot be read ({type(exc).__name__}: {str(exc)[:120]})") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        fmt = ckpt.get("format") if isinstance(ckpt, dict) else None
        raise ModelError(f"{path} is not a PRML2 checkpoint (format {fmt!r}, want {CHECKPOINT_FORMAT!r})")
    if ckpt.get("signal_names") != list(schema.SIGNAL_NAMES) or ckpt.get("schema_hash") != schema.SCHEMA_HASH:
        raise ModelError(
            f"{path} was trained for another signal layout (schema hash {ckpt.get('schema_hash')} vs "
            f"{schema.SCHEMA_HASH}); retrain with this version"
        )
    return ckpt


def model_from_checkpoint(ckpt: dict[str, Any]) -> Prml2Model:
    """Rebuild the model (in eval mode) from a checkpoint dict."""
    cfg: ModelConfig = model_config_from_dict(ckpt["model_config"])
    model = Prml2Model(cfg, ckpt["norm_mean"], ckpt["norm_std"], ckpt["z_mean"], ckpt["z_std"])
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        raise ModelError(f"checkpoint weights do not fit its own model config ({str(exc)[:120]})") from exc
    return model.eval()


def load_model(path: str | Path) -> tuple[Prml2Model, dict[str, Any]]:
    """``(model, checkpoint dict)`` from a checkpoint file."""
    ckpt = read_checkpoint(path)
    return model_from_checkpoint(ckpt), ckpt
