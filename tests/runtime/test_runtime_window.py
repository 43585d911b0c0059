"""Window, latency recorder and initial pose helpers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from prml2_edge.errors import ConfigError
from prml2_edge.runtime.initial_pose import InitialPose, initial_state
from prml2_edge.runtime.latency import LatencyRecorder
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.window import Window
from prml2_edge.schema import psi_rad_to_heading_deg


def test_window_is_the_last_rows_in_order_and_contiguous(rng):
    win = Window(length=7, n_signals=3)
    rows = rng.normal(size=(30, 3)).astype(np.float32)
    for k, row in enumerate(rows):
        win.step(row, all_valid=(k % 5 != 0))
        view = win.view()
        assert view.flags["C_CONTIGUOUS"] and view.shape == (1, 7, 3)
        if k >= 6:
            np.testing.assert_array_equal(view[0], rows[k - 6:k + 1])
            assert win.n_invalid == sum(1 for j in range(k - 6, k + 1) if j % 5 == 0)
    assert win.full
    win.clear()
    assert not win.full and win.invalid_fraction == 1.0


def test_latency_percentiles_and_deadline_misses():
    lat = LatencyRecorder(max_samples=1000)
    for ms in range(1, 101):
        lat.add("end_to_end", ms * 1_000_000)
    s = lat.summary()["end_to_end"]
    assert s["count"] == 100 and s["max_ms"] == 100.0 and s["p50_ms"] == pytest.approx(50.5)
    assert s["deadline_misses"] == 80  # > 20 ms
    assert any("25-32 ms" in line for line in lat.report_lines())
    for _ in range(2000):
        lat.add("decode", 1)
    assert lat.count("decode") <= 1000 and lat.dropped > 0


def test_initial_pose_from_text_file_and_gnss(tmp_path):
    p = InitialPose.parse("12.5,-3,90")
    assert (p.x_m, p.y_m) == (12.5, -3.0) and p.psi_rad == pytest.approx(0.0)
    with pytest.raises(ConfigError, match="X,Y,HEADING_DEG"):
        InitialPose.parse("1,2")
    f = tmp_path / "pose.json"
    f.write_text(json.dumps({"x_m": 1.0, "y_m": 2.0, "heading_deg": 0.0}))
    assert InitialPose.from_file(f).psi_rad == pytest.approx(math.pi / 2)  # north
    f.write_text(json.dumps({"x_m": 1.0, "y_m": 2.0, "heading": 0.0}))
    with pytest.raises(ConfigError, match="unknown key 'heading'"):
        InitialPose.from_file(f)
    g = InitialPose.from_gnss(GnssFix(0.0, 5.0, 6.0, 180.0, True))
    assert g.psi_rad == pytest.approx(-math.pi / 2) and g.source == "gnss"
    assert psi_rad_to_heading_deg(g.psi_rad) == pytest.approx(180.0)


def test_initial_state_takes_dynamics_from_the_row():
    values = np.array([10.5, 0.1, 0.2, 1.5, 0.0, 10.0, 10.2, 9.8, 10.0])
    x0, p0 = initial_state(InitialPose(1.0, 2.0, 90.0, pos_std_m=2.0), values)
    assert x0[:3] == pytest.approx([1.0, 2.0, 0.0]) and x0[4] == pytest.approx(10.0)
    assert x0[3] == pytest.approx(0.2) and x0[7] == pytest.approx(1.5)
    assert p0[0, 0] == pytest.approx(4.0)
    valid = np.ones(9, dtype=bool)
    valid[5:] = False
    x0, _ = initial_state(InitialPose(0, 0, 0), values, valid)
    assert x0[4] == pytest.approx(10.5)  # speedometer when no wheel speed is valid
