"""Real-car GNSS (issue 28): an uncalibrated gyro, no standstill and consumer fixes must not look like a spoof.

A highway drive that starts at speed, a CAN yaw-rate offset of -0.4 deg/s nobody calibrated, and
20 s of 1.5 m fixes from t = 0 in a TUM file (``prml2 replay --gnss``'s input): every fix is fused.
The units show each part of the mechanism on its own: the fix stream's noise from its second
differences, a tolerance that grows with the yaw-rate offset the filter does not know yet, and a
check that does not arm before the filter knows it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from runtime_models import ListSink, make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.gnss_check import FixNoise, GnssCheck
from prml2_edge.runtime.gnss_input import FixFeed, load_fixes
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.pipeline import Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.tum import tum_line

OFFSET_DPS = -0.4


def test_fix_noise_reads_the_receivers_noise_from_its_second_differences():
    rng = np.random.default_rng(3)
    t = np.arange(200) * 0.1
    x, y = 20.0 * t, 30.0 * np.sin(t / 10.0)  # 20 m/s along a gentle bend
    noisy, clean = FixNoise(), FixNoise()
    for k in range(len(t)):
        noisy.add(t[k], x[k] + rng.normal(0, 1.5), y[k] + rng.normal(0, 1.5))
        clean.add(t[k], x[k], y[k])
        if k == 3:
            assert noisy.std_m is None  # four fixes: not known yet
    assert noisy.std_m == pytest.approx(1.5, rel=0.2)
    assert clean.std_m < 0.05  # the car's motion itself adds centimetres at 10 Hz
    noisy.add(t[-1], 1e6, 1e6)  # the same fix time again is not a new fix
    assert noisy.std_m == pytest.approx(1.5, rel=0.2)


def _run_check(rate_std: float, converged: bool = True) -> GnssCheck:
    """20 m/s straight, fixes on the truth; the filter's heading turns at the uncalibrated gyro's 0.4 deg/s
    between fixes, and each fix takes back only 2 % of its heading error (a filter that trusts its gyro):
    the heading error settles near 2 deg, which over an 8 s baseline puts the odometry metres off the fixes."""
    check = GnssCheck()
    check.fix_std_m = 0.5
    b, psi = math.radians(0.4), 0.0
    for k in range(400):  # 40 s of 10 Hz fixes
        t = k * 0.1
        psi = (psi + b * 0.1) * 0.98
        check.step(check.odo[0] + 2.0 * math.cos(psi), check.odo[1] + 2.0 * math.sin(psi))
        check.settle(check.odo[0], check.odo[1])
        check.check(t, (20.0 * t, 0.0), (check.odo[0], check.odo[1]), True, psi_std=0.0, rate_std=rate_std,
                    converged=converged)
    return check


def test_the_tolerance_covers_the_yaw_rate_offset_the_filter_does_not_know_yet():
    assert _run_check(rate_std=0.0).episodes >= 1  # a certain filter would blame the satellites
    assert _run_check(rate_std=math.radians(0.25)).fixes_refused == 0  # 2 sigma cover the 0.4 deg/s
    assert _run_check(rate_std=0.0, converged=False).fixes_refused == 0  # not armed while learning the gyro


def _noisy_stream(walk_mps: float) -> GnssCheck:
    """60 s at 20 m/s straight with exact odometry and 1.5 m fixes at 10 Hz (a consumer receiver), the fixes
    walking sideways at ``walk_mps`` from 30 s on; the filter knows its gyro (the check arms after 10 s)."""
    rng = np.random.default_rng(11)
    check = GnssCheck()
    check.fix_std_m = 1.5
    for k in range(600):
        t = k * 0.1
        check.step(check.odo[0] + 2.0, 0.0)
        check.settle(check.odo[0], 0.0)
        walk = walk_mps * max(t - 30.0, 0.0)
        fix = (20.0 * t + rng.normal(0, 1.5), walk + rng.normal(0, 1.5))
        check.check(t, fix, (check.odo[0], 0.0), True, psi_std=0.0, rate_std=0.0)
    return check


def test_a_noisy_receiver_is_not_a_spoofer_and_a_walk_still_is():
    # one 1.5 m fix against another would pass 2 sqrt(2) sigma 14 % of the time; the baseline's ends are 1 s means
    assert _noisy_stream(0.0).fixes_refused == 0
    walked = _noisy_stream(50.0 / 60.0)  # reliability.py's spoof: 50 m over 60 s
    assert walked.episodes >= 1 and walked.fixes_refused > 0


@pytest.fixture(scope="module")
def highway(tmp_path_factory):
    root = tmp_path_factory.mktemp("realcar")
    drive = simulate_drive(40.0 / 60.0, 1.0, 9105, "highway", vehicle="compact_fwd",
                           sensor_errors={"yaw_offset_radps": math.radians(OFFSET_DPS)})
    log, fixes = root / "hw.log", root / "fixes.tum"
    encode_drive_to_log(drive, log)
    rng = np.random.default_rng(5)
    with open(fixes, "w") as f:
        for k in range(0, 1000, 5):  # 20 s at 10 Hz from t = 0
            x, y, psi = drive.pose_gt[k]
            f.write(tum_line(float(drive.t_s[k]), x + rng.normal(0, 1.5), y + rng.normal(0, 1.5),
                             psi + math.radians(rng.normal(0, 1.0))))
    return root, drive, log, fixes, OnnxModel(make_kinematic_model(root / "kinematic.onnx"))


def test_consumer_fixes_with_an_uncalibrated_gyro_and_no_stop_are_all_fused(highway):
    _, drive, log, fixes, model = highway
    pipeline = Pipeline.build(model=model, sinks=[ListSink()], external_gnss=True)
    pipeline.add_gnss_source(FixFeed(load_fixes(fixes), str(fixes)))
    with LogReplay(log) as source:
        run_source(pipeline, source)
    pipeline.close()
    s = pipeline.summary()
    assert s["gnss_suspect"]["fixes_refused"] == 0, s["gnss_suspect"]["first_reason"]
    assert s["gnss_rejected"] == 0 and s["gnss_init_rejected"] == 0
    flt = pipeline.localizer.filter
    assert flt.gnss_std_m == pytest.approx(1.5, rel=0.25)  # the receiver's noise, not the configured 0.5 m
    cal = s["calibration"]
    assert cal["standstill_updates"] == 0
    # learned while driving, and honest about it: the truth lies within 3 of its reported sigmas
    assert abs(cal["yaw_rate_offset_dps"] - OFFSET_DPS) < max(0.15, 3.0 * cal["yaw_rate_offset_std_dps"])
