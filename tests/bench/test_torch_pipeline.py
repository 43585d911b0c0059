"""The latency benchmark's torch-eager reference runs through the runtime's Pipeline as the runtime's localiser does."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from prml2_edge import schema  # noqa: E402
from prml2_edge.bench.latency import measure_steps  # noqa: E402
from prml2_edge.bench.replay_input import simulated_frames  # noqa: E402
from prml2_edge.training.model import Prml2Model  # noqa: E402
from prml2_edge.training.presets import ModelConfig  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from torch_pipeline import torch_pipeline  # noqa: E402


def test_the_torch_reference_steps_every_row_and_times_its_stages():
    cfg = ModelConfig(d_model=16, n_heads=2, n_layers=1, d_ff=16)
    model = Prml2Model(cfg, np.zeros(9), np.ones(9), np.zeros(5), np.ones(5))
    replay = simulated_frames(6.0, seed=3)
    pipe = torch_pipeline(model, replay.initial_pose)
    samples = measure_steps(pipe, replay.frames)
    rows = pipe.rows
    assert rows >= int(5.9 / schema.DT_S)
    # stride 1: an inference at every row once the window is full, each timed end to end
    assert len(samples.e2e_ms) == rows - cfg.window_len + 1
    assert np.isfinite(pipe.last.x).all()
    lat = pipe.latency.summary()
    assert lat["infer"]["count"] == rows - cfg.window_len + 1 and lat["filter"]["count"] == rows
