"""The one plotting module: matplotlib figures as PNG, a one-line hint without matplotlib, nothing drawn by hand."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import prml2_edge
from prml2_edge.viz import plots

pytest.importorskip("matplotlib")
from matplotlib.image import imread  # noqa: E402


def _png(path: Path) -> np.ndarray:
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return imread(path)


def test_demo_trajectory_draws_truth_and_both_estimate_parts(tmp_path):
    t = np.linspace(0, 2 * np.pi, 400)
    gt = np.column_stack([100 * np.cos(t), 100 * np.sin(t)])
    est = gt + np.column_stack([np.zeros_like(t), np.linspace(0, 8, t.size)])
    img = _png(plots.plot_demo_trajectory(tmp_path / "d" / "trajectory.png", est, gt, t < 1.0, "demo"))
    assert img.shape[:2] == (700, 900)
    rgb = img[..., :3]
    black = np.all(rgb < 0.05, axis=2).sum()
    blue = np.all(np.abs(rgb - np.array([0.122, 0.467, 0.706])) < 0.03, axis=2).sum()  # tab:blue
    green = np.all(np.abs(rgb - np.array([0.173, 0.627, 0.173])) < 0.03, axis=2).sum()  # tab:green
    assert black > 1000 and blue > 500 and green > 50


def test_evaluation_and_training_figures(tmp_path):
    rng = np.random.default_rng(0)
    xy = np.cumsum(rng.normal(size=(100, 2)), axis=0)
    panel = {"title": "w", "truth": xy, "estimates": {"PRML2": xy + 1.0, "OSD": xy - 1.0}}
    curve = {"t_s": np.arange(10) * 0.02, "pos_mean_m": np.arange(10.0), "pos_std_m": np.ones(10),
             "yaw_mean_deg": np.arange(10.0), "yaw_std_deg": np.ones(10)}
    errors = {"PRML2": rng.normal(size=(500, 5)), "OSD": np.full((500, 5), np.nan)}
    history = [{"epoch": e, "stage": "pretrain" if e < 2 else "finetune", "train_nll": -e, "val_nll": -e + 0.5,
                "val_rmse_v_x_mps": 0.1 / (e + 1)} for e in range(4)]
    paths = [plots.plot_trajectories(tmp_path / "t.png", [panel, panel]),
             plots.plot_drift(tmp_path / "d.png", {"PRML2": curve}, "dry"),
             plots.plot_error_histograms(tmp_path / "h.png", errors, ["a", "b", "c", "d", "e"]),
             plots.plot_history(history, tmp_path / "run" / "loss_curve.png")]
    for path in paths:
        img = _png(path)
        assert img.shape[1] > 400 and (img[..., :3] < 0.5).any()


def test_without_matplotlib_figure_is_a_one_line_missing_extra_error():
    code = ("import sys; sys.modules['matplotlib'] = None\n"
            "from prml2_edge.viz import plots\n"
            "assert not plots.available()\n"
            "try:\n    plots.figure(1, 1)\nexcept Exception as exc:\n    print(type(exc).__name__, exc)\n"
            "print(plots.missing_message('x.png'))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0 and len(lines) == 2, proc.stderr
    assert lines[0].startswith("MissingExtraError") and "'.[plot]'" in lines[0]
    assert lines[1].startswith("no x.png: matplotlib is not installed") and "'.[plot]'" in lines[1]


def test_no_module_draws_text_or_encodes_png_by_hand():
    """Issue 19: the hand-written PNG encoder and bitmap font are gone; matplotlib draws everything."""
    root = Path(prml2_edge.__file__).parent
    hand_made = re.compile(r"IHDR|IDAT|IEND|\\x89PNG|zlib\.compress|GLYPH|def glyph|bitmap font")
    offenders = [str(p.relative_to(root)) for p in root.rglob("*.py") if hand_made.search(p.read_text())]
    assert not offenders, offenders
    assert not (root / "viz" / "png.py").exists() and not (root / "viz" / "font.py").exists()
