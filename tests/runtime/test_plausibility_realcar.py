"""A real car's highway drive through the plausibility stage (issue 28): a coarse gyro with an offset nobody
calibrated must not make the wheel pairs, which learned from it, outvote the truth.

The ReV-StED-like car's yaw rate comes in 1.28 deg/s steps; +0.4 deg/s of offset, gentle curves and
no stop leave its wheel pairs' learned track and radius difference poorly known for the first
minute. Their RLS uncertainty widens the checks they are the reference for; without it the gyro
is flagged as a dropout at 38.5 s of a clean drive.
"""

from __future__ import annotations

import math

import numpy as np

from prml2_edge import schema
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.plausibility import Plausibility, PlausibilityConfig
from prml2_edge.runtime.rows import AssembledRow


def _first_flags(drive, cfg: PlausibilityConfig, seconds: float) -> dict:
    mon = Plausibility([s.rate_hz for s in schema.SIGNALS], cfg)
    ones, zeros = np.ones(schema.NUM_SIGNALS, dtype=bool), np.zeros(schema.NUM_SIGNALS)
    for k in range(int(seconds * schema.SAMPLE_RATE_HZ)):
        mon.check(AssembledRow(k, float(drive.t_s[k]), drive.onboard[k].astype(np.float64), ones, zeros))
    return mon.summary()["first_flag"]


def test_a_coarse_uncalibrated_gyro_on_the_highway_raises_no_flag():
    d = simulate_drive(10.0, 1.0, 1008, family="highway", vehicle="reference",
                       sensor_errors={"yaw_offset_radps": math.radians(0.4)})
    assert _first_flags(d, PlausibilityConfig(), 60.0) == {}
    # and it matters: with the wheel pairs' learned relations taken as certain, the clean gyro is taken out
    flagged = _first_flags(d, PlausibilityConfig(learned_sd=False), 60.0)
    assert "yaw_rate_radps" in flagged
