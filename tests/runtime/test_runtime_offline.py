"""The offline schedule (``prml2 replay --batch``) gives the streaming replay's numbers on a log with faults.

A 40 s simulated drive (GNSS for the first 4 s) is encoded with the project DBC, rewritten with
faults (checksum errors, a dropped message, duplicated frames, error frames, a frozen yaw rate, a
clock jump back, a 6 s bus silence that re-anchors the grid, a yaw-rate offset, a second sender
replaying wheel-speed frames, a wheel reading 20 % high), written as a candump log and replayed
twice with the shipped model: through the virtual bus frame by frame (``run_source``) and on the
offline schedule (``run_offline``: in the filter's step for a model that reads rows less the filter's cue
offsets, else worker processes and in-thread). Poses, statuses, the summary and
the frame accounting must agree; the trajectories to 1e-6 m (they agree bitwise: same session
options, one window per ``session.run``).
"""

from __future__ import annotations

import logging

import can
import numpy as np
import pytest
from runtime_models import ListSink, make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_dbc
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import ModelError
from prml2_edge.resources import project_dbc_path
from prml2_edge.runtime.estimator import Estimator
from prml2_edge.runtime.inference import OnnxModel, default_model_path
from prml2_edge.runtime.localizer import LocalizerConfig
from prml2_edge.runtime.offline import run_offline, windows_wait_for_filter
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.runtime.status import InferenceStatus
from prml2_edge.testing.faults import Fault, inject

FAULTS = [
    Fault("checksum", 8.0, 9.0, message="WHEEL_SPEEDS_FRONT"),  # rejected frames
    Fault("drop_message", 10.0, 11.0, message="ESP_YAW_LAT"),  # stale yaw rate and lateral acceleration
    Fault("duplicate", 12.0, 12.5),  # counter rejects
    Fault("error_frames", 13.0, 13.2, count=50),
    Fault("freeze_signal", 14.0, 17.0, message="ESP_YAW_LAT", signal="YAW_RATE", value=0.0),  # stuck sensor
    Fault("time_shift", 18.0, 20.0, value=-0.5),  # logger clock jumps back, then forward
    Fault("bus_silent", 24.0, 30.5),  # longer than the assembler's max gap: grid re-anchored, window restarted
    # plausible lies: the cross-checks flag them and substitute, the injection monitor rejects the second sender
    Fault("offset", 32.0, 35.0, message="ESP_YAW_LAT", signal="YAW_RATE", value=4.0),
    Fault("intruder", 34.0, 37.0, message="WHEEL_SPEEDS_REAR", value=20.0),
    Fault("scale", 36.0, 39.0, message="WHEEL_SPEEDS_FRONT", signal="WHEEL_SPEED_FL", value=1.2),
]


@pytest.fixture(scope="module")
def faulty_log(tmp_path_factory):
    root = tmp_path_factory.mktemp("offline")
    drive = simulate_drive(40.0 / 60.0, 1.0, 12)
    clean = root / "clean.log"
    encode_drive_to_log(drive, clean, gnss_seconds=4.0)
    path = root / "faulty.log"
    with can.Logger(str(path)) as writer:
        for msg in inject(list(can.LogReader(str(clean))), FAULTS, load_dbc(project_dbc_path()), seed=3):
            writer.on_message_received(msg)
    return path


def streaming(path, model_path, **build):
    memory, sink = MemorySink(), ListSink()
    pipeline = Pipeline.build(model=OnnxModel(model_path), sinks=[memory, sink], **build)
    with LogReplay(path) as source:
        run_source(pipeline, source)
    pipeline.close()
    return pipeline, memory.arrays(), sink.outs


def offline(path, model_path, workers, batch=1, **build):
    memory, sink = MemorySink(), ListSink()
    pipeline = Pipeline.build(model=OnnxModel(model_path), sinks=[memory, sink], **build)
    result = run_offline(pipeline, path, batch=batch, workers=workers, verify=True, chunk_frames=3000)
    pipeline.close()
    return pipeline, memory.arrays(), sink.outs, result


def comparable(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in ("latency", "wall_s", "realtime_factor")}


@pytest.fixture(scope="module")
def stream_runs(faulty_log):
    """The streaming run of the faulty log with the shipped model, per calibration setting (each run once)."""
    runs: dict[bool, tuple] = {}

    def get(calibration: bool):
        if calibration not in runs:
            runs[calibration] = streaming(faulty_log, default_model_path(), calibration=calibration)
        return runs[calibration]
    return get


@pytest.mark.parametrize("workers, calibration", [(2, True), (2, False), (1, False)])
def test_offline_replay_of_a_faulty_log_gives_the_streaming_poses(faulty_log, stream_runs, workers, calibration):
    """The shipped model reads rows less the cue offsets the filter learns: with calibration on its windows run in
    the filter's step; with it off they run ahead of the filter (worker processes, or in the filter's thread)."""
    ps, a, outs_s = stream_runs(calibration)
    po, b, outs_o, result = offline(faulty_log, default_model_path(), workers, calibration=calibration)
    in_step = calibration and OnnxModel(default_model_path()).metadata.reads_debiased_cues
    assert (po.offline.get("in_step") is not None) == in_step
    assert po.offline["workers"] == (0 if in_step else workers)
    fr = ps.stats.as_dict()
    # the log really has the faults the test is about
    assert fr["rejected_by_reason"].get("checksum") and fr["rejected_by_reason"].get("counter")
    assert fr["clock_jumps"] == 1 and fr["error_frames"] == 50 and ps.assembler.resyncs == 1
    assert sum(o.degraded for o in outs_s) > 100 and ps.stats.signal_frozen[2] == 1
    summary = ps.summary()
    assert summary["injection_suspected"]["WHEEL_SPEEDS_REAR"]["intruder_frames_rejected"] > 0
    assert fr["rejected_by_reason"].get("intruder")
    assert {"yaw_rate_radps", "wheel_speed_fl_mps"} <= set(summary["plausibility"]["first_flag"])
    assert any(o.substituted is not None and o.substituted[2] and o.model_used for o in outs_s)
    assert result.problem is None and result.frames == fr["received"] and result.rows == len(outs_s)
    assert result.inferences == ps.localizer.n_inferences
    # same rows, same statuses, same model use, trajectories within 1e-6 m (in fact bitwise)
    assert len(outs_o) == len(outs_s)
    for key in ("t_s", "status", "model_used", "gnss_outage", "standstill"):
        assert np.array_equal(a[key], b[key]), key
    started = np.isfinite(a["x"][:, 0])
    assert started.sum() > 1500 and np.array_equal(started, np.isfinite(b["x"][:, 0]))
    assert np.abs(a["x"][started, :2] - b["x"][started, :2]).max() <= 1e-6
    assert np.array_equal(a["x"], b["x"], equal_nan=True) and np.array_equal(a["pos_cov"], b["pos_cov"],
                                                                              equal_nan=True)
    assert [(o.inferred, o.guard_fired, o.gnss_fused) for o in outs_o] == \
        [(o.inferred, o.guard_fired, o.gnss_fused) for o in outs_s]
    # every counter: frames by outcome and per signal, rows, estimator, filter, calibration
    assert comparable(po.summary()) == comparable(ps.summary())


def test_a_model_reading_rows_less_the_filters_cue_offsets_runs_in_the_filters_step(faulty_log, tmp_path, caplog):
    """Its windows depend on what the filter has learned by each row, so they cannot run ahead of it: run ahead on
    raw rows they would differ from the streaming estimator's (the check here caught it). Asked for workers and a
    batch, the run says they do not apply and gives the streaming poses."""
    model = make_kinematic_model(tmp_path / "kin_cues.onnx")
    cfg = LocalizerConfig(model_inputs_from_cues=True)
    ps, a, _ = streaming(faulty_log, model, localizer_config=cfg)
    with caplog.at_level(logging.WARNING, logger="prml2_edge.runtime.offline"):
        po, b, _, result = offline(faulty_log, model, workers=2, localizer_config=LocalizerConfig(
            model_inputs_from_cues=True))
    assert "do not apply" in caplog.text
    assert po.offline["in_step"] and po.offline["workers"] == 0
    assert result.inferences == ps.localizer.n_inferences == po.offline["windows"] > 0
    assert np.array_equal(a["x"], b["x"], equal_nan=True)
    assert comparable(po.summary()) == comparable(ps.summary())
    raw = Pipeline.build(model=OnnxModel(model), localizer_config=LocalizerConfig(model_inputs_from_cues=True,
                                                                                 calibration=False))
    assert windows_wait_for_filter(raw) is None  # no cue estimator: it reads raw rows, which can run ahead


def test_stride_and_batched_calls_follow_the_streaming_schedule(faulty_log, tmp_path):
    """Stride 3 with a graph whose batch dimension is free, 7 windows per call: the same schedule and poses
    (the kinematic model's arithmetic does not depend on the batch)."""
    model = make_kinematic_model(tmp_path / "kin.onnx", batch="batch")
    ps, a, _ = streaming(faulty_log, model, stride=3)
    po, b, _, result = offline(faulty_log, model, workers=2, batch=7, stride=3)
    assert result.inferences == ps.localizer.n_inferences
    assert np.abs(np.nan_to_num(a["x"] - b["x"])).max() <= 1e-6
    assert comparable(po.summary()) == comparable(ps.summary())


def test_a_graph_with_a_fixed_batch_refuses_batched_calls(faulty_log, tmp_path):
    model = make_kinematic_model(tmp_path / "kin1.onnx")
    pipeline = Pipeline.build(model=OnnxModel(model))
    with pytest.raises(ModelError, match="batch dimension is fixed at 1"):
        run_offline(pipeline, faulty_log, batch=4, workers=1)


def test_failed_inferences_count_as_in_streaming(faulty_log, tmp_path):
    """A model whose variance goes non-positive at speed (in some of its 100 decoder rows, not always the newest):
    the same windows fail in both schedules."""
    model = make_kinematic_model(tmp_path / "neg.onnx", var_scale_on_input=-0.1)  # var <= 0 above 10 m/s
    ps, a, _ = streaming(faulty_log, model)
    po, b, _, _ = offline(faulty_log, model, workers=1)
    assert ps.localizer.n_inference_failures > 0
    assert po.localizer.n_inference_failures == ps.localizer.n_inference_failures
    assert np.array_equal(a["x"], b["x"], equal_nan=True)


@pytest.mark.parametrize("stride", [1, 2, 5])
def test_schedule_is_the_estimators_inference_rule(stride, rng):
    class Recorder:
        window_len = 20
        mean = np.zeros((1, 5))
        var = np.ones((1, 5))

        def __init__(self) -> None:
            self.rows = []
            self.i = -1

        def step(self, window):
            self.rows.append(self.i)
            return InferenceStatus.SUCCESS

    disc = rng.random(400) < 0.01
    disc[0] = True
    model = Recorder()
    est = Estimator(model, stride, 0.2, 10.0)
    for i, d in enumerate(disc):
        model.i = i
        est.step(np.zeros(9), bool(rng.random() < 0.9), bool(d))
    want = np.asarray(model.rows)
    assert np.array_equal(Estimator.schedule(disc, 20, stride), want)
    state = [0, -1]  # in pieces, as the offline runner calls it
    parts = [Estimator.schedule(disc[s:s + 37], 20, stride, state, offset=s) for s in range(0, 400, 37)]
    assert np.array_equal(np.concatenate(parts), want)


def test_replay_batch_cli(faulty_log, tmp_path, capsys):
    out = tmp_path / "s.json"
    assert main(["replay", str(faulty_log), "--batch", "--workers", "1", "--summary-json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "(offline schedule)" in text and "offline: " in text and "balanced: yes" in text
    assert main(["replay", str(faulty_log), "--batch", "--realtime"]) == 1
    assert "drop --realtime" in capsys.readouterr().err
    assert main(["replay", str(faulty_log), "--workers", "2"]) == 1
    assert "go with --batch" in capsys.readouterr().err
