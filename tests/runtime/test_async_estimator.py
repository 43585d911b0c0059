"""The asynchronous estimator: the model on a worker thread, no step waits for it, nothing used out of place."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.async_estimator import AsyncEstimator
from prml2_edge.runtime.estimator import Estimator
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer
from prml2_edge.runtime.status import InferenceStatus
from prml2_edge.schema import EkfState

DT = schema.DT_S


class _SlowModel:
    """Takes ``delay_s`` per window; its output's v_x is the number of the call; ``gate`` holds it back."""

    window_len = 10

    def __init__(self, delay_s: float, fail: bool = False) -> None:
        self.delay_s, self.fail, self.calls = delay_s, fail, 0
        self.gate = threading.Event()
        self.gate.set()
        self.mean = np.zeros((1, schema.NUM_STATES))
        self.var = np.ones((1, schema.NUM_STATES))

    def step(self, window: np.ndarray) -> InferenceStatus:
        self.gate.wait(5.0)
        time.sleep(self.delay_s)
        self.calls += 1
        self.mean = np.zeros((1, schema.NUM_STATES))
        self.mean[0, schema.Z.V_X] = self.calls
        return InferenceStatus.ERROR if self.fail else InferenceStatus.SUCCESS


def _feed(est, rows: int, period_s: float = DT):
    """``rows`` rows at ``period_s``; per row (seconds the step took, its Estimate)."""
    out = []
    for _ in range(rows):
        t0 = time.perf_counter()
        e = est.step(np.zeros(schema.NUM_SIGNALS), True)
        out.append((time.perf_counter() - t0, e))
        time.sleep(period_s)
    return out


def test_no_step_waits_for_a_model_slower_than_the_step():
    model = _SlowModel(0.06)  # 3 steps per inference
    est = AsyncEstimator(model, 5, 0.2, 10.0)
    out = _feed(est, 60)
    est.close()
    assert max(dt for dt, _ in out) < 0.02  # the synchronous estimator takes 60 ms at every fifth row
    used = [e.z for _, e in out]
    first = next(i for i, z in enumerate(used) if z is not None)
    # the first window is due at row 10 (index 9); its output arrives ~3 rows later, and then every row has one
    assert 11 <= first <= 20 and all(z is not None for z in used[first:])
    lag = est.summary()["async"]
    assert lag["lag_steps_min"] >= 3 and est.n_inferences >= 6 and lag["lag_steps_max"] < 10
    # outputs come in the order of their windows
    vx = [z[schema.Z.V_X] for z in used[first:]]
    assert vx == sorted(vx) and vx[-1] >= 6


def test_a_stuck_model_is_not_used_past_two_strides():
    model = _SlowModel(0.0)
    est = AsyncEstimator(model, 5, 0.2, 10.0)
    out = _feed(est, 20)
    assert out[-1][1].z is not None
    model.gate.clear()  # the next window never comes back while the test runs
    later = _feed(est, 14)
    # the last output is used for at most 2 strides after it arrived, then none
    assert [e.z is not None for _, e in later].count(True) <= 10 and later[-1][1].z is None
    model.gate.set()
    est.close()


def test_a_discontinuity_drops_the_window_in_flight():
    model = _SlowModel(0.0)
    est = AsyncEstimator(model, 5, 0.2, 10.0)
    model.gate.clear()
    _feed(est, 10, 0.0)  # the first window is sent, and held back in the model
    est.step(np.zeros(schema.NUM_SIGNALS), True, discontinuity=True)
    model.gate.set()
    time.sleep(0.05)
    out = _feed(est, 5, 0.0)
    assert all(e.z is None for _, e in out)  # its output arrived but belongs before the gap
    assert est.n_inferences == 0
    est.close()


def test_a_failed_inference_counts_and_gives_no_output():
    est = AsyncEstimator(_SlowModel(0.0, fail=True), 5, 0.2, 10.0)
    out = _feed(est, 30)
    est.close()
    assert all(e.z is None for _, e in out) and est.n_inference_failures == est.n_inferences >= 3


@pytest.mark.parametrize("asynchronous", [False, True])
def test_the_localizer_runs_a_real_model_either_way(tmp_path, asynchronous):
    drive = simulate_drive(0.15, 1.0, 11)  # 9 s
    model = OnnxModel(make_kinematic_model(tmp_path / "k.onnx"))
    loc = StreamingLocalizer(model, LocalizerConfig(async_inference=asynchronous))
    assert isinstance(loc.estimator, AsyncEstimator if asynchronous else Estimator)
    if asynchronous:
        # async inference is for a live feed: fed flat out (~0.1 ms a row) the loop can end before the worker
        # thread is ever scheduled, so each row here leaves it 1 ms, as a 50 Hz feed leaves it 20 ms
        step = loc.estimator.step

        def paced(*args, **kwargs):
            time.sleep(0.001)
            return step(*args, **kwargs)

        loc.estimator.step = paced
    x0 = np.zeros(EkfState.DIM)
    x0[:3] = drive.pose_gt[schema.WINDOW_LEN - 1]
    x0[list(schema.Z_TO_EKF_INDEX)] = drive.z_gt[schema.WINDOW_LEN - 1]
    traj = loc.run_arrays(drive.onboard, x0, start_index=schema.WINDOW_LEN - 1)
    if asynchronous:
        loc.estimator.close()
    assert np.isfinite(traj.x[schema.WINDOW_LEN - 1:]).all() and loc.n_inferences > 0
    err = np.hypot(*(traj.x[-1, :2] - drive.pose_gt[-1, :2]))
    assert err < 5.0, err
