"""Loss-curve plot of a training run (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import math
from pathlib import Path


def plot_history(history: list[dict], path: str | Path) -> Path:
    """Write a PNG with train/validation NLL, the fine-tuning position term and z RMSE per epoch.

    ``history`` is the list of per-epoch records of ``metrics.jsonl``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    epochs = [h["epoch"] for h in history]

    def series(key: str) -> list[float]:
        return [h.get(key, math.nan) for h in history]

    def train_val(ax, key: str, labels: tuple[str, str], ylabel: str, title: str) -> None:
        ax.plot(epochs, series(f"train_{key}"), "o-", label=labels[0])
        ax.plot(epochs, series(f"val_{key}"), "s-", label=labels[1])
        ax.set_xlabel("epoch")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.legend()

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    train_val(axes[0], "nll", ("train NLL", "val NLL"), "NLL per window", "NLL (Eq. nll_loss)")
    train_val(axes[1], "pos", ("train", "val"), "beta tanh(sum |d - d_gt|^2 / beta)", "position term (fine-tuning)")
    ax = axes[2]
    for key, label in (("val_rmse_v_x_mps", "v_x [m/s]"), ("val_rmse_v_y_mps", "v_y [m/s]"),
                       ("val_rmse_a_x_mps2", "a_x [m/s²]"), ("val_rmse_a_y_mps2", "a_y [m/s²]"),
                       ("val_rmse_omega_z_radps", "ω_z [rad/s]")):
        ax.plot(epochs, series(key), "o-", label=label)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_title("validation z RMSE")
    ax.legend(fontsize=7)
    for h in history:
        if h.get("stage") == "finetune":
            for a in axes:
                a.axvline(h["epoch"] - 0.5, color="grey", lw=0.8, ls="--")
            break
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
