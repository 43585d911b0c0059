"""PNG figures of the evaluation (matplotlib, Agg backend): example trajectories, drift over time
(paper Fig. 4, mean with a +-0.25 sigma band), per-component z error histograms."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.evaluation.metrics import drift_curves, z_errors
from prml2_edge.evaluation.protocol import WindowResult, WindowTask


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_trajectories(path: Path, tasks: Sequence[WindowTask], results: Mapping[str, Sequence[WindowResult]]) -> Path:
    """Ground truth and every model for the example ``tasks`` (one panel each), positions relative to the start."""
    plt = _plt()
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.2 * len(tasks), 4.2), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        origin = task.pose_gt[0, :2]
        ax.plot(*(task.pose_gt[:, :2] - origin).T, "k-", lw=2.0, label="ground truth")
        for name, res in results.items():
            match = [r for r in res if r.task_key == task.key]
            if match:
                ax.plot(*(match[0].pose[:, :2] - origin).T, lw=1.1, label=name)
        ax.plot(0, 0, "ko", ms=4)
        ax.set_title(f"{task.drive} ({task.split}) t0={task.t_s[0]:.0f} s", fontsize=8)
        ax.set_xlabel("east [m]")
        ax.set_ylabel("north [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_drift(path: Path, results: Mapping[str, Sequence[WindowResult]], split: str, band_sigma: float = 0.25) -> Path:
    """Mean position and heading error versus time over 60 s windows, with a +-``band_sigma`` std band."""
    plt = _plt()
    fig, (ax_p, ax_y) = plt.subplots(1, 2, figsize=(11, 4))
    for name, res in results.items():
        if not res:
            continue
        c = drift_curves(res)
        line = ax_p.plot(c["t_s"], c["pos_mean_m"], label=name)[0]
        ax_p.fill_between(c["t_s"], c["pos_mean_m"] - band_sigma * c["pos_std_m"],
                          c["pos_mean_m"] + band_sigma * c["pos_std_m"], color=line.get_color(), alpha=0.2)
        ax_y.plot(c["t_s"], c["yaw_mean_deg"], color=line.get_color(), label=name)
        ax_y.fill_between(c["t_s"], c["yaw_mean_deg"] - band_sigma * c["yaw_std_deg"],
                          c["yaw_mean_deg"] + band_sigma * c["yaw_std_deg"], color=line.get_color(), alpha=0.2)
    ax_p.set_xlabel("time since start [s]")
    ax_p.set_ylabel("position error [m]")
    ax_y.set_xlabel("time since start [s]")
    ax_y.set_ylabel("|heading error| [deg]")
    for ax in (ax_p, ax_y):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"dead-reckoning drift ({split}; mean, band +-{band_sigma} std)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_error_histograms(path: Path, results: Mapping[str, Sequence[WindowResult]],
                          tasks: Sequence[WindowTask]) -> Path:
    """Per-component histograms of z errors (model minus ground truth) [SI] for every model."""
    plt = _plt()
    fig, axes = plt.subplots(1, schema.NUM_STATES, figsize=(3.4 * schema.NUM_STATES, 3.2))
    errs = {name: z_errors(res, tasks) for name, res in results.items() if res}
    for i, (ax, state) in enumerate(zip(axes, schema.STATE_NAMES, strict=True)):
        vals = [e[:, i][np.isfinite(e[:, i])] for e in errs.values()]
        nonempty = [v for v in vals if len(v)]
        if not nonempty:
            continue
        lim = float(np.percentile(np.abs(np.concatenate(nonempty)), 99.5)) or 1.0
        bins = np.linspace(-lim, lim, 61)
        for name, v in zip(errs, vals, strict=True):
            if len(v):
                ax.hist(v, bins=bins, histtype="step", density=True, label=name)
        ax.set_title(state, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
