"""What the trainer reads: the window sets, the normalisation and z statistics, and a run's description
(:func:`prepare_data` builds them from a loaded dataset; :mod:`prml2_edge.training.trainer` re-exports them)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from prml2_edge import schema
from prml2_edge.errors import ConfigError
from prml2_edge.training.presets import ModelConfig, TrainConfig


class WindowSource(Protocol):
    """What the trainer needs from a window set (``prml2_edge.data.windows.WindowSet``)."""

    def __len__(self) -> int: ...

    def get(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(onboard (b, L, 9) float32, z (b, L, 5) float32, pose (b, L, 3) float64)``."""
        ...

    # fine-tuning over segments (``TrainConfig.ft_horizon_s > 0``) also needs
    # ``segment_starts(length, stride)`` and ``get_segments(starts, length, rows)``.


@dataclass
class TrainData:
    """Everything :func:`fit` reads: windows, normalisation statistics and provenance.

    ``norm_mean``/``norm_std`` (9,) are the dataset's onboard statistics [SI]; ``z_mean``/``z_std``
    (5,) those of z on the training split [SI].
    """

    train: WindowSource
    val: WindowSource
    norm_mean: np.ndarray
    norm_std: np.ndarray
    z_mean: np.ndarray
    z_std: np.ndarray
    fingerprint: str
    skip_rows: tuple[np.ndarray, np.ndarray] | None = None  # (onboard (N, 9), z (N, 5)) to fit the skip on


def z_statistics(z_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std (5,) of ground-truth z rows (N, 5) [SI] (std floored at 1e-3)."""
    z_rows = np.asarray(z_rows, dtype=np.float64)
    if z_rows.ndim != 2 or z_rows.shape[1] != schema.NUM_STATES or len(z_rows) < 2:
        raise ConfigError(f"need at least two ground-truth z rows (N, {schema.NUM_STATES}) for statistics")
    return z_rows.mean(axis=0), np.maximum(z_rows.std(axis=0), 1e-3)


def check_data(data: TrainData) -> None:
    if len(data.train) == 0:
        raise ConfigError("no training windows: the training split is shorter than one window (L samples)")
    if len(data.val) == 0:
        raise ConfigError("no validation windows: the validation split is shorter than one window (L samples)")


def describe(model_cfg: ModelConfig, train_cfg: TrainConfig) -> dict:
    """Plain-data description of a run's configuration (for logs and recipes)."""
    return {"model": asdict(model_cfg), "train": asdict(train_cfg),
            "pretrain_epochs": train_cfg.pretrain_epochs(),
            "finetune_epochs": train_cfg.epochs - train_cfg.pretrain_epochs()}


def prepare_data(dataset, model_cfg: ModelConfig, train_cfg: TrainConfig) -> TrainData:
    """Windows and statistics of a loaded dataset (``prml2_edge.data.datasets.Dataset``) for :func:`fit`.

    Training windows every ``train_cfg.window_stride`` samples of the training split, validation
    windows every ``train_cfg.val_stride`` samples of the validation split; z statistics and the
    rows the model's linear skip is fitted on from the training split's samples. A model with
    ``cue_debiased_inputs`` reads every drive's a_y and steering less the car's offsets (``data.cue_debias``).
    """
    from prml2_edge.data.windows import build_windows

    if model_cfg.cue_debiased_inputs:
        from prml2_edge.data.cue_debias import debiased_dataset

        dataset = debiased_dataset(dataset, train_cfg.seed)

    train_drives = [d for d in dataset.split("train") if d.has_ground_truth]
    val_drives = [d for d in dataset.split("val") if d.has_ground_truth]
    if not train_drives:
        raise ConfigError(f"{dataset.root}: no training drives with ground truth (need z and pose columns)")
    z_rows = np.concatenate([d.z_gt for d in train_drives])
    z_mean, z_std = z_statistics(z_rows)
    L, H = model_cfg.window_len, model_cfg.encoder_len
    return TrainData(
        train=build_windows(train_drives, L=L, H=H, stride=train_cfg.window_stride),
        val=build_windows(val_drives, L=L, H=H, stride=train_cfg.val_stride),
        norm_mean=np.asarray(dataset.norm_mean, dtype=np.float64),
        norm_std=np.asarray(dataset.norm_std, dtype=np.float64),
        z_mean=z_mean,
        z_std=z_std,
        fingerprint=str(dataset.fingerprint),
        skip_rows=(np.concatenate([d.onboard for d in train_drives]), z_rows),
    )
