"""Every figure the project draws, with matplotlib: the demo's trajectory, the evaluation's figures, the loss curve.

matplotlib comes with the ``plot`` extra (``pip install -c constraints.txt '.[plot]'``; the ``train``
extra has it too). Figures are built on :class:`matplotlib.figure.Figure` and saved as PNG through
the Agg canvas, so no display and no global pyplot state are involved. Without matplotlib,
:func:`figure` raises :class:`~prml2_edge.errors.MissingExtraError`: callers print its one line
and carry on without the plot.

The functions take plain arrays (positions [m], times [s], SI errors), not the evaluation's or the
runtime's types, so every layer can draw through this one module.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from prml2_edge.errors import MissingExtraError, install_hint

PLOT_EXTRA = "plot"


def available() -> bool:
    """True when matplotlib can be imported."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def missing_message(what: str) -> str:
    """The one line a command prints when it skips ``what`` (a figure) for want of matplotlib."""
    return f"no {what}: matplotlib is not installed; to get it: {install_hint(PLOT_EXTRA)}"


def figure(width_in: float, height_in: float):
    """A new :class:`matplotlib.figure.Figure` (Agg canvas); :class:`MissingExtraError` without matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingExtraError("matplotlib", PLOT_EXTRA) from exc
    fig = Figure(figsize=(width_in, height_in))
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: str | Path, dpi: int) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi, format="png")
    return path


# ---- prml2 demo ----------------------------------------------------------------------------------------------------

def plot_demo_trajectory(path: str | Path, est_xy: np.ndarray, gt_xy: np.ndarray, gnss_mask: np.ndarray,
                         title: str) -> Path:
    """Ground truth and the estimate, its GNSS-aided part and its dead-reckoning part in their own colours.

    ``est_xy``, ``gt_xy`` (N, 2) east/north [m]; ``gnss_mask`` (N,) True while GNSS fixes came in.
    """
    last_fix = int(np.flatnonzero(gnss_mask)[-1]) if np.any(gnss_mask) else 0
    fig = figure(9.0, 7.0)
    ax = fig.add_subplot()
    ax.plot(gt_xy[:, 0], gt_xy[:, 1], "k-", lw=2.0, label="ground truth")
    ax.plot(est_xy[: last_fix + 1, 0], est_xy[: last_fix + 1, 1], "-", color="tab:green", lw=2.5,
            label="estimate, GNSS aided")
    ax.plot(est_xy[last_fix:, 0], est_xy[last_fix:, 1], "-", color="tab:blue", lw=1.8,
            label="estimate, dead reckoning")
    if len(gt_xy):
        ax.plot(gt_xy[0, 0], gt_xy[0, 1], "o", color="tab:orange", ms=8, label="start")
    if len(est_xy):
        ax.plot(est_xy[last_fix, 0], est_xy[last_fix, 1], "o", color="tab:red", ms=8, label="GNSS lost")
    ax.set_title(title)
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path, dpi=100)


# ---- prml2 evaluate ------------------------------------------------------------------------------------------------

def plot_trajectories(path: str | Path, panels: Sequence[dict]) -> Path:
    """One panel per example window: ``{"title", "truth" (N, 2), "estimates" {name: (M, 2)}}``, positions [m]
    relative to the window's start."""
    fig = figure(4.2 * max(len(panels), 1), 4.2)
    axes = fig.subplots(1, max(len(panels), 1), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=False):
        ax.plot(*np.asarray(panel["truth"]).T, "k-", lw=2.0, label="ground truth")
        for name, xy in panel["estimates"].items():
            ax.plot(*np.asarray(xy).T, lw=1.1, label=name)
        ax.plot(0, 0, "ko", ms=4)
        ax.set_title(panel["title"], fontsize=8)
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    return _save(fig, path, dpi=110)


def plot_drift(path: str | Path, curves: Mapping[str, Mapping[str, np.ndarray]], split: str,
               band_sigma: float = 0.25) -> Path:
    """Mean position and heading error versus time (paper Fig. 4) with a +-``band_sigma`` std band.

    ``curves[name]`` holds ``t_s``, ``pos_mean_m``, ``pos_std_m``, ``yaw_mean_deg``, ``yaw_std_deg``.
    """
    fig = figure(11.0, 4.0)
    ax_p, ax_y = fig.subplots(1, 2)
    for name, c in curves.items():
        line = ax_p.plot(c["t_s"], c["pos_mean_m"], label=name)[0]
        colour = line.get_color()
        ax_p.fill_between(c["t_s"], c["pos_mean_m"] - band_sigma * c["pos_std_m"],
                          c["pos_mean_m"] + band_sigma * c["pos_std_m"], color=colour, alpha=0.2)
        ax_y.plot(c["t_s"], c["yaw_mean_deg"], color=colour, label=name)
        ax_y.fill_between(c["t_s"], c["yaw_mean_deg"] - band_sigma * c["yaw_std_deg"],
                          c["yaw_mean_deg"] + band_sigma * c["yaw_std_deg"], color=colour, alpha=0.2)
    ax_p.set_ylabel("position error [m]")
    ax_y.set_ylabel("|heading error| [deg]")
    for ax in (ax_p, ax_y):
        ax.set_xlabel("time since start [s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"dead-reckoning drift ({split}; mean, band +-{band_sigma} std)")
    return _save(fig, path, dpi=110)


def plot_error_histograms(path: str | Path, errors: Mapping[str, np.ndarray], state_names: Sequence[str]) -> Path:
    """Per-component histograms of z errors; ``errors[name]`` (M, len(state_names)) [SI], NaN where missing."""
    fig = figure(3.4 * len(state_names), 3.2)
    axes = fig.subplots(1, len(state_names), squeeze=False)[0]
    for i, (ax, state) in enumerate(zip(axes, state_names, strict=True)):
        vals = {name: e[:, i][np.isfinite(e[:, i])] for name, e in errors.items()}
        nonempty = [v for v in vals.values() if len(v)]
        if not nonempty:
            continue
        lim = float(np.percentile(np.abs(np.concatenate(nonempty)), 99.5)) or 1.0
        bins = np.linspace(-lim, lim, 61)
        for name, v in vals.items():
            if len(v):
                ax.hist(v, bins=bins, histtype="step", density=True, label=name)
        ax.set_title(state, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    return _save(fig, path, dpi=110)


# ---- prml2 train ---------------------------------------------------------------------------------------------------

def plot_history(history: list[dict], path: str | Path) -> Path:
    """Train/validation NLL, the fine-tuning position term and the validation z RMSE per epoch.

    ``history`` is the list of per-epoch records of ``metrics.jsonl``.
    """
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

    fig = figure(13.0, 3.6)
    axes = fig.subplots(1, 3)
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
    return _save(fig, path, dpi=100)
