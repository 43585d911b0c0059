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

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    ax = axes[0]
    ax.plot(epochs, series("train_nll"), "o-", label="train NLL")
    ax.plot(epochs, series("val_nll"), "s-", label="val NLL")
    ax.set_xlabel("epoch")
    ax.set_ylabel("NLL per window")
    ax.set_title("NLL (Eq. nll_loss)")
    ax.legend()
    ax = axes[1]
    ax.plot(epochs, series("train_pos"), "o-", label="train")
    ax.plot(epochs, series("val_pos"), "s-", label="val")
    ax.set_xlabel("epoch")
    ax.set_ylabel("beta tanh(sum |d - d_gt|^2 / beta)")
    ax.set_title("position term (fine-tuning)")
    ax.legend()
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
