"""The car sliding: the odometry misses the motion, and the GNSS fixes that follow must pull the pose back.

A car drives east at 20 m/s with 10 Hz fixes; 15 s in (the GNSS check armed) it slides sideways for one second,
its lateral speed up to 20 m/s and back, while the wheels keep rolling at 20 m/s and the gyro reads 0: 10 m that
the model and the wheels never see. The CAN lateral acceleration shows it (+-40 m/s^2 against v_x omega_z = 0).
"""

from __future__ import annotations

import numpy as np
import pytest
from runtime_models import kinematic_weights, make_kinematic_model

from prml2_edge import schema
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.slide import SlideMonitor
from prml2_edge.schema import SIGNAL_BY_NAME, EkfState

DT = schema.DT_S
SPEED = 20.0
SLIDE_AT_S, SLIDE_S, SLIDE_MPS = 15.0, 1.0, 20.0


def test_gripping_tyres_are_no_slide_and_a_skid_is_one():
    mon = SlideMonitor(3.0, DT)
    rng = np.random.default_rng(0)
    for _ in range(500):  # 10 s of a bend: a_y = v omega, with sensor noise
        assert mon.step(2.0 + rng.normal(0, 0.3), 20.0, 0.1 + rng.normal(0, 0.005)) == 0.0
    assert mon.episodes == 0
    grow = [mon.step(20.0, 20.0, 0.0) for _ in range(50)]  # one second at 20 m/s^2 nobody modelled
    assert mon.episodes == 1 and mon.sliding
    assert sum(grow) == pytest.approx(0.5 * 20.0 * 1.0 ** 2, rel=0.15)  # the lateral distance a bound covers
    for _ in range(int(SlideMonitor.GRIP_S / DT) + 10):
        mon.step(None, 20.0, None)  # a missing signal holds the residual: still sliding
    assert mon.sliding
    for _ in range(int(SlideMonitor.GRIP_S / DT) + 10):
        mon.step(0.0, 20.0, 0.0)
    assert not mon.sliding and mon.step(0.0, 20.0, 0.0) == 0.0
    assert SlideMonitor(None, DT).step(1e3, 20.0, 0.0) == 0.0  # switched off


def _slide_drive(seconds: float = 30.0):
    """Onboard rows, the true position and 10 Hz fixes (0.5 m noise) of the drive in the module docstring."""
    n = int(seconds / DT)
    t = np.arange(n) * DT
    v_y = np.interp(t, [SLIDE_AT_S, SLIDE_AT_S + SLIDE_S / 2, SLIDE_AT_S + SLIDE_S], [0.0, -SLIDE_MPS, 0.0])
    a_y = np.gradient(v_y, DT)
    onboard = np.zeros((n, schema.NUM_SIGNALS))
    for name in schema.WHEEL_SPEED_NAMES + ("speedometer_mps",):
        onboard[:, SIGNAL_BY_NAME[name].index] = SPEED
    onboard[:, SIGNAL_BY_NAME["lat_accel_mps2"].index] = a_y
    truth = np.stack([SPEED * t, np.cumsum(v_y) * DT], axis=1)
    rng = np.random.default_rng(1)
    fixes = {k: GnssFix(float(t[k]), *(truth[k] + rng.normal(0.0, 0.5, 2)).tolist(), heading_deg=90.0, valid=True)
             for k in range(schema.WINDOW_LEN, n, 5)}
    return onboard, truth, fixes


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    """The closed-form model of a car whose tyres grip: its a_y is v_x omega_z (0 here), not the sensor's."""
    w = kinematic_weights()
    w[SIGNAL_BY_NAME["lat_accel_mps2"].index, schema.Z.A_Y] = 0.0
    return make_kinematic_model(tmp_path_factory.mktemp("m") / "gripping.onnx", weights=w)


@pytest.mark.parametrize("monitor", [True, False])
def test_after_a_slide_the_fixes_pull_the_pose_back(model_path, monitor):
    onboard, truth, fixes = _slide_drive()
    cfg = LocalizerConfig(gnss_pos_std_m=0.5, slide_accel_mps2=3.0 if monitor else None)
    loc = StreamingLocalizer(OnnxModel(model_path), cfg)
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.VEL.start] = SPEED
    start = schema.WINDOW_LEN - 1
    x0[EkfState.POS] = truth[start]
    # the car knows its gyro from an earlier stop (its calibration file), so the GNSS check is armed by the slide
    loc.restore_calibration(np.zeros(3), np.diag([1e-6, 0.01 ** 2, 0.005 ** 2]))
    traj = loc.run_arrays(onboard, x0, start_index=start, gnss=fixes)
    err = np.hypot(*(traj.pose[:, :2] - truth).T)
    after = int((SLIDE_AT_S + SLIDE_S + 3.0) / DT)  # 3 s after the slide
    assert err[int(SLIDE_AT_S / DT) - 1] < 1.5  # following the fixes before it
    summary = loc.filter.summary()
    if monitor:
        assert err[after:].max() < 1.5
        assert summary["slides"] == 1 and summary["gnss_suspect"]["restarts"] == 1
        assert summary["gnss_suspect"]["fixes_refused"] == 0
    else:  # the failure the monitor fixes: the gate, then the GNSS check, refuse the genuine fixes for seconds
        assert summary["slides"] == 0
        assert err[after:int(25.0 / DT)].min() > 5.0
        assert summary["gnss_suspect"]["fixes_refused"] > 50
