"""Benchmark honesty: a loaded machine is never labelled idle; the per-row cost outside the model adds up."""

from __future__ import annotations

import pytest

from prml2_edge.bench.latency import OUTSIDE_STAGES, StepSamples, _outside_rows
from prml2_edge.bench.machine import load_label
from prml2_edge.runtime.latency import LatencyRecorder


def test_load_label_says_loaded_above_a_third_of_a_core_per_core():
    assert load_label([0.2, 0.1, 0.1], [0.5, 0.2, 0.1], cores=2).startswith("idle (load 0.20 -> 0.50)")
    assert load_label([0.7, 0.1, 0.1], [0.1, 0.1, 0.1], cores=2) == "loaded (load 0.70 -> 0.10)"
    assert load_label([0.1, 0.1, 0.1], [2.4, 1.0, 0.5], cores=2).startswith("loaded")
    assert load_label(None, [0.0, 0.0, 0.0]) == "load unknown"


def test_outside_rows_sums_each_rows_frames_and_stages():
    lat = LatencyRecorder()
    for ns in (1000, 2000, 3000):  # three frames: two for the first row, one for the second
        lat.add("decode", ns)
        lat.add("assemble", 500)
    for ns in (10_000, 20_000):
        for stage in ("plausibility", "guard", "filter", "sinks"):
            lat.add(stage, ns)
    zero = tuple(0 for _ in OUTSIDE_STAGES)
    bounds = [(zero, (2, 2, 1, 1, 1, 1)), ((2, 2, 1, 1, 1, 1), (3, 3, 2, 2, 2, 2))]
    s = StepSamples()
    _outside_rows(lat, bounds, s)
    assert s.outside_stage_ms["decode"] == pytest.approx([0.003, 0.003])
    assert s.outside_ms == pytest.approx([0.003 + 0.001 + 0.04, 0.003 + 0.0005 + 0.08])


def test_every_row_counts_the_rows_without_an_inference_too(tmp_path):
    from prml2_edge.bench.latency import measure_steps
    from prml2_edge.bench.replay_input import read_frames, simulate_log
    from prml2_edge.runtime.pipeline import Pipeline

    path, pose, _ = simulate_log(8.0, tmp_path / "drive.log", seed=3)
    frames = read_frames(path)
    inferred = measure_steps(Pipeline.build(initial_pose=pose), frames)
    every = measure_steps(Pipeline.build(initial_pose=pose), frames, every_row=True)
    assert every.rows == inferred.rows > 0
    assert 0 < len(inferred.outside_ms) < len(every.outside_ms) <= every.rows
    assert len(every.outside_ms) >= every.rows - 5  # (two rows completed by one frame count as one step)
    assert every.model_ms.count(0.0) >= len(every.model_ms) - len(inferred.model_ms)
