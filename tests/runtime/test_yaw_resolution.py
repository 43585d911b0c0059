"""The CAN yaw rate's resolution from the steps between its readings: one rule for the filter and the replays."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from prml2_edge.runtime.localizer_config import LocalizerConfig
from prml2_edge.runtime.yaw_resolution import YawResolution


def test_a_replay_of_readings_measures_the_step_as_the_filter_would() -> None:
    step = math.radians(1.28)
    cfg = LocalizerConfig()
    few = np.where((np.arange(500) // 50) % 2 == 1, math.radians(0.5), 0.0)  # 9 steps of 0.5 deg/s
    assert YawResolution.of(few, cfg) == pytest.approx(math.radians(0.5))
    assert YawResolution.of(few, replace(cfg, resolution_from_steps=False)) == step  # the configured until measured
    assert YawResolution.of(np.zeros(100), cfg) == step  # never changed: the configured one
    many = np.round(np.random.default_rng(0).normal(0.0, 2 * step, 1000) / step) * step
    many[::7] = np.nan  # missing readings are skipped
    coarse = YawResolution.from_config(replace(cfg, yaw_cue_resolution_radps=math.radians(5.0)))
    coarse.readings(many)
    assert coarse.measured and coarse.coarse and coarse.radps == pytest.approx(step)
