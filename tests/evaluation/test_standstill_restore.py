"""The benchmark's calibrated filter starts from the standstill's yaw-rate offset as the runtime would know it."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.evaluation.models import OsdModel
from prml2_edge.evaluation.osd import StandstillBias, drive_bias, standstill_bias
from prml2_edge.evaluation.protocol import ModelSpec
from prml2_edge.evaluation.standstill_restore import restore_standstill_calibration, standstill_offset
from prml2_edge.runtime.calibration import RESTORE_STD_FLOOR
from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer
from prml2_edge.schema import EkfState

YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
WHEELS = list(schema.WHEEL_SPEED_INDICES)
L = schema.WINDOW_LEN


def _model() -> OsdModel:
    model = OsdModel(np.array([0.01, 0.01, 1.0, 0.05, math.radians(0.1) ** 2]), StandstillBias())
    model.metadata = SimpleNamespace(ekf_process_noise=None, error_model=None)
    return model


def _parked(n: int, offset_dps: float, noise_dps: float, step_dps: float, seed: int = 0) -> np.ndarray:
    """``n`` rows standing still, the CAN yaw rate ``offset_dps`` off with white noise, quantised to ``step_dps``."""
    onboard = np.zeros((n, schema.NUM_SIGNALS))
    yaw = math.radians(offset_dps) + np.random.default_rng(seed).normal(0.0, math.radians(noise_dps), n)
    onboard[:, YAW] = np.round(yaw / math.radians(step_dps)) * math.radians(step_dps)
    return onboard


@pytest.mark.parametrize("step_dps", [0.01, 0.244])
def test_the_runtime_restore_is_what_the_runtimes_own_standstill_update_leaves(step_dps):
    """The runtime stands 20 s with a 0.3 deg/s offset: the offset and its sigma it ends with are what
    ``standstill_offset`` computes from the standstill's episodes for the same config (fine and coarse gyro)."""
    onboard = _parked(L + 1000, 0.3, 0.15, step_dps)
    cfg = LocalizerConfig(yaw_cue_resolution_radps=math.radians(step_dps))
    loc = StreamingLocalizer(_model(), cfg)
    loc.run_arrays(onboard, np.zeros(EkfState.DIM), start_index=L - 1)
    cal, cov = loc.filter.calibration()
    mean, var = standstill_offset(standstill_bias(onboard[L - 1:]), cfg)
    assert math.degrees(mean) == pytest.approx(math.degrees(cal[0]), abs=0.01)
    assert math.sqrt(var) == pytest.approx(math.sqrt(cov[0, 0]), rel=0.25)
    assert math.sqrt(var) < 0.5 * RESTORE_STD_FLOOR[0]  # far better than the file's between-drive floor


def test_an_old_stop_is_known_less_and_a_recent_one_weighs_more():
    cfg = LocalizerConfig(yaw_cue_resolution_radps=math.radians(0.01))
    moving = np.zeros((3000, schema.NUM_SIGNALS))
    moving[:, WHEELS] = 10.0
    old, recent = _parked(500, 0.2, 0.1, 0.01, 1), _parked(500, 0.3, 0.1, 0.01, 2)
    just_stopped = standstill_offset(standstill_bias(old), cfg)
    ten_minutes = [moving] * 10
    long_ago = standstill_offset(standstill_bias(np.vstack([old, *ten_minutes])), cfg)
    assert long_ago[0] == pytest.approx(just_stopped[0])
    expected = just_stopped[1] + cfg.cal_yaw_offset_psd * 30000 * schema.DT_S  # the random walk since
    assert long_ago[1] == pytest.approx(expected, rel=1e-9) and long_ago[1] > 2.0 * just_stopped[1]
    both = standstill_offset(standstill_bias(np.vstack([old, *ten_minutes, recent])), cfg)
    plain = standstill_bias(np.vstack([old, *ten_minutes, recent])).yaw_rate_radps  # the baseline's mean
    assert math.degrees(plain) == pytest.approx(0.25, abs=0.01)
    assert 0.26 < math.degrees(both[0]) < 0.3


def test_the_file_restore_and_a_stop_after_the_window_keep_the_files_floor():
    cfg = LocalizerConfig()
    stop = _parked(500, 0.3, 0.1, 0.01)
    moving = np.zeros((1000, schema.NUM_SIGNALS))
    moving[:, WHEELS] = 10.0
    after = drive_bias(moving, np.vstack([moving, stop]))  # no stop before the window: the whole drive's
    assert after.n_samples == 500 and after.episodes == ()
    assert standstill_offset(after, cfg) is None
    for bias, how in ((after, "runtime"), (standstill_bias(stop), "file")):
        loc = StreamingLocalizer(_model(), cfg)
        assert restore_standstill_calibration(loc, bias, how=how)
        cal, cov = loc.filter.calibration0
        assert cal[0] == pytest.approx(bias.yaw_rate_radps) and math.sqrt(cov[0, 0]) == pytest.approx(
            RESTORE_STD_FLOOR[0])
    loc = StreamingLocalizer(_model(), cfg)
    assert restore_standstill_calibration(loc, standstill_bias(stop), how="runtime")
    assert math.sqrt(loc.filter.calibration0[1][0, 0]) < 0.2 * RESTORE_STD_FLOOR[0]


def test_an_unknown_restore_is_refused():
    with pytest.raises(ValueError, match="standstill_restore must be one of"):
        ModelSpec("PRML2", "onnx", "m.onnx", calibration=True, standstill_restore="garage")
    loc = StreamingLocalizer(_model(), LocalizerConfig())
    with pytest.raises(ValueError, match="standstill restore must be one of"):
        restore_standstill_calibration(loc, StandstillBias(n_samples=100), how="garage")
