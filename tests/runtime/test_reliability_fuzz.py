"""Hostile input: 20 000 fuzzed frames (10^6 in ``benchmarks/fuzz.py``) and hypothesis frame streams never
raise out of the pipeline;the EKF covariance stays symmetric positive definite under random valid inputs.

CAN has no authentication: anything on the bus can send any frame, with any ID, length and
payload; logs add broken timestamps. Frames go straight into ``Pipeline.step`` (the replay path
minus the virtual bus, which only moves frames).
"""

from __future__ import annotations

import math

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from runtime_models import make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.ekf.numpy_ekf import STATE_DIM, Ekf, StepStatus
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import Pipeline
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.testing.fuzz import KNOWN_IDS, fuzz_stream

N_FUZZ = 20_000


@pytest.fixture(scope="module")
def genuine(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    encode_drive_to_log(simulate_drive(0.1, 1.0, 9), root / "d.log", gnss_seconds=1.0)
    return list(can.LogReader(str(root / "d.log"))), OnnxModel(make_kinematic_model(root / "k.onnx"))


def test_fuzzed_frames_never_raise_and_are_all_accounted_for(genuine):
    # 20 000 here; benchmarks/fuzz.py runs 10^6 through the same stream
    frames, model = genuine
    pipeline = Pipeline.build(model=model, initial_pose=InitialPose(0.0, 0.0, 0.0))
    outs = []
    for fuzzed in fuzz_stream(frames, N_FUZZ, seed=2024):
        outs += pipeline.step(fuzzed)  # an exception here fails the test
    outs += pipeline.finish()
    st_ = pipeline.stats
    assert st_.received == N_FUZZ and st_.balanced()
    assert st_.used > 0.4 * N_FUZZ and st_.ignored > 0 and st_.rejected > 0.05 * N_FUZZ
    reasons = st_.rejected_by_reason()
    assert {"dlc", "checksum", "counter", "timestamp"} <= set(reasons), reasons
    # lone old outlier timestamps are refused; a far-future one re-anchors and the clock is re-based back
    assert st_.clock_jumps > 0 and pipeline.assembler.resyncs > 0
    assert len(outs) > 200
    assert all(np.isfinite(o.x).all() for o in outs if o.status is not PoseStatus.INITIALISING)
    assert pipeline.summary()["frames"]["balanced"]


def _frame_strategy():
    payload = st.binary(min_size=0, max_size=64)
    return st.tuples(
        st.one_of(st.sampled_from(KNOWN_IDS), st.integers(0, 0x7FF), st.integers(0, 0x1FFFFFFF)),
        payload,
        st.one_of(st.floats(-0.01, 0.2), st.sampled_from([math.nan, math.inf, -math.inf, 1e9, -1e9])),
        st.sampled_from(["data", "data", "data", "error", "remote", "extended"]),
    )


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_frame_strategy(), min_size=1, max_size=200))
def test_random_frame_streams_never_raise_out_of_the_pipeline(genuine, stream):
    _, model = genuine
    pipeline = Pipeline.build(model=model, initial_pose=InitialPose(0.0, 0.0, 0.0))
    t_s = 100.0
    for arb, data, dt, kind in stream:
        t_s = t_s + dt if math.isfinite(dt) and abs(dt) < 1.0 else dt
        extended = kind == "extended" or arb > 0x7FF
        msg = can.Message(timestamp=t_s, arbitration_id=arb, is_extended_id=extended, data=data,
                          is_error_frame=kind == "error", is_remote_frame=kind == "remote", is_fd=len(data) > 8)
        pipeline.step(msg)
        if not math.isfinite(t_s) or abs(t_s) > 1e6:
            t_s = 100.0
    pipeline.finish()
    assert pipeline.stats.received == len(stream) and pipeline.stats.balanced()
    if pipeline.last is not None and pipeline.last.status is not PoseStatus.INITIALISING:
        assert np.isfinite(pipeline.last.x).all()


def _spd(p: np.ndarray) -> bool:
    return bool(np.allclose(p, p.T, rtol=0, atol=1e-9 * max(1.0, np.abs(p).max()))
                and np.linalg.eigvalsh(0.5 * (p + p.T)).min() > 0)


_z = st.tuples(st.floats(-30, 30), st.floats(-3, 3), st.floats(-10, 10), st.floats(-10, 10), st.floats(-1.5, 1.5))
_var = st.tuples(*[st.floats(1e-6, 1e3)] * 5)
_op = st.one_of(
    st.tuples(st.just("update"), _z, _var),
    st.tuples(st.just("predict"), st.integers(1, 200)),
    st.tuples(st.just("fix"), st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), st.floats(1e-4, 1e2),
              st.one_of(st.none(), st.floats(-10, 10))),
)


@settings(max_examples=60, deadline=None)
@given(st.lists(_op, min_size=1, max_size=40))
def test_ekf_covariance_stays_spd_under_mixed_updates_predictions_and_fixes(ops):
    """Model updates, long predict-only stretches (degraded mode) and GNSS pose fixes in any order."""
    ekf = Ekf()
    for op in ops:
        if op[0] == "update":
            status = ekf.step(np.array(op[1]), np.array(op[2]))
        elif op[0] == "predict":
            for _ in range(op[1]):
                status = ekf.step()
        else:
            status = ekf.fuse_pose(np.array(op[1]), op[2], op[3], None if op[3] is None else 1e-3)
        assert status in (StepStatus.SUCCESS, StepStatus.PREDICT_ONLY, StepStatus.RESET)
        assert ekf.x.shape == (STATE_DIM,) and np.isfinite(ekf.x).all()
        assert _spd(ekf.P), np.linalg.eigvalsh(ekf.P)


def test_latency_samples_are_bounded_for_a_service_running_for_days():
    from prml2_edge.runtime.latency import LatencyRecorder

    rec = LatencyRecorder(max_samples=1000)
    for i in range(10_000):
        rec.add("end_to_end", 1_000_000 + i)
    assert rec.total("end_to_end") == 10_000 and rec.count("end_to_end") <= 1000
    assert rec.dropped + rec.count("end_to_end") == 10_000
    recent = rec.stage_summary("end_to_end", since_total=9_990)  # the status line: since the last report
    assert recent["count"] == 10 and recent["max_ms"] == pytest.approx(1.009999)
