"""Offset jumps: measured at their step, taken off the signal, and told apart from the driver's own steps.

The plausibility stage runs alone on simulator rows (no CAN): a fault is an exact step added to one signal,
so the offset it measures can be compared with the one added. The simulated driver steps the steering wheel
by up to 25 deg within one row at manoeuvre changes (the car follows); those must not read as offsets.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.localizer import StreamingLocalizer
from prml2_edge.runtime.plausibility import AY, SW, YAW, Plausibility
from prml2_edge.runtime.rows import AssembledRow, GnssFix
from prml2_edge.schema import EkfState

_DEG = schema.DEG_TO_RAD
RATES = [s.rate_hz for s in schema.SIGNALS]
T0 = 125.0


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(2.6, 1.0, 8, family="mixed", vehicle="compact_fwd")  # the fine-gyro car


def run(d, signal=None, offset=0.0, t_end=math.inf):
    x = d.onboard.astype(np.float64).copy()
    if signal is not None:
        on = (d.t_s >= T0) & (d.t_s < t_end)
        x[on, signal] += offset
    mon = Plausibility(RATES)
    ones, zeros = np.ones(schema.NUM_SIGNALS, dtype=bool), np.zeros(schema.NUM_SIGNALS)
    rows = [mon.check(AssembledRow(k, float(d.t_s[k]), x[k], ones, zeros)) for k in range(len(d))]
    return mon, rows


@pytest.mark.parametrize("signal, offset, within_s", [
    (YAW, 2.0 * _DEG, 0.5), (AY, 1.0, 0.7), (SW, 10.0 * _DEG, 0.9)], ids=["yaw-2dps", "ay-1mps2", "steer-10deg"])
def test_an_offset_jump_is_measured_at_its_step_and_taken_off(drive, signal, offset, within_s):
    mon, rows = run(drive, signal, offset)
    first = mon.summary()["first_flag"]
    name = schema.SIGNAL_NAMES[signal]
    assert set(first) == {name}, first  # that signal and no other
    assert T0 <= first[name]["t_s"] <= T0 + within_s and "jumped by" in first[name]["reason"]
    found = [j for r in rows for j in r.offset_jumps]
    assert len(found) == 1 and found[0][0] == signal
    _, measured, std, t_step = found[0]
    assert abs(t_step - T0) < 0.021
    assert abs(measured - offset) < 0.05 * abs(offset) and 0.0 < std < 0.05 * abs(offset)
    # from then on the value less the offset replaces it: close to what the sensor should have read
    after = [r for r in rows if r.t_s > first[name]["t_s"]]
    assert all(r.substituted[signal] and not r.valid[signal] for r in after)
    k = np.array([r.k for r in after])
    sub = np.array([r.values[signal] for r in after])
    assert np.max(np.abs(sub - drive.onboard[k, signal])) <= abs(measured - offset) + 1e-9
    assert all(abs(r.substitute_std[signal] - std) < 1e-12 for r in after)


def test_the_correction_ends_when_the_signal_steps_back(drive):
    mon, rows = run(drive, YAW, 2.0 * _DEG, t_end=140.0)
    name = schema.SIGNAL_NAMES[YAW]
    assert "jumped by" in mon.summary()["first_flag"][name]["reason"]
    # back at 140 s: the step back is confirmed like the jump (0.4 s), the correction stops, the flag clears after
    assert not any(r.substituted is not None and r.substituted[YAW]
                   and abs(r.values[YAW] - (drive.onboard[r.k, YAW] - 2.0 * _DEG)) < 0.2 * _DEG
                   for r in rows if r.t_s >= 140.45)
    assert not mon.checks[YAW].flagged
    assert mon.summary()["flag_episodes"] == {name: 1}


def test_the_drivers_steering_steps_are_not_offset_jumps():
    d = simulate_drive(6.0, 1.0, 1008, family="lateral", vehicle="reference")
    moving = d.z_gt[:, 0] > 5.0
    step = np.abs(np.diff(d.onboard[:, SW], prepend=d.onboard[0, SW]))
    assert np.count_nonzero(moving & (step > 7.0 * _DEG)) >= 2  # the drive has them: the test can fail
    mon, rows = run(d)
    assert mon.summary()["first_flag"] == {}
    assert not any(r.offset_jumps for r in rows)


def test_a_found_offset_takes_back_the_heading_it_cost(tmp_path):
    loc = StreamingLocalizer(OnnxModel(make_kinematic_model(tmp_path / "k.onnx")))
    flt = loc.filter
    flt.correct_yaw_cue(0.03, 0.001, 10.0, 10.4)  # no filter yet: nothing to correct, no error
    d = simulate_drive(0.5, 1.0, 3)
    ones = np.ones(schema.NUM_SIGNALS, dtype=bool)
    for k in range(len(d)):
        fix = GnssFix(float(d.t_s[k]), float(d.pose_gt[k, 0]), float(d.pose_gt[k, 1]), None, True) \
            if k % 5 == 0 else None
        loc.step(d.onboard[k].astype(np.float64), ones, float(d.t_s[k]), fix)
    psi, omega = flt.ekf.x[EkfState.YAW][0], flt.ekf.x[EkfState.OMEGA_Z][0]
    var = flt.ekf.P[EkfState.YAW, EkfState.YAW][0, 0]
    flt.correct_yaw_cue(0.03, 0.001, 10.0, 10.4)
    g = loc.config.offset_retro_gain
    assert flt.ekf.x[EkfState.YAW][0] == pytest.approx(psi - g * 0.03 * 0.4)
    assert flt.ekf.x[EkfState.OMEGA_Z][0] == pytest.approx(omega - g * 0.03)
    assert flt.ekf.P[EkfState.YAW, EkfState.YAW][0, 0] == pytest.approx(var + (0.001 * 0.4) ** 2)
