"""End to end: a simulated drive encoded with the project DBC, replayed through a python-can virtual bus."""

from __future__ import annotations

import time

import can
import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.demo import trajectory_metrics
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.source import LogReplay, count_log_frames
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import psi_rad_to_heading_deg

GNSS_S = 8.0


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return make_kinematic_model(tmp_path_factory.mktemp("m") / "kinematic.onnx")


@pytest.fixture(scope="module")
def encoded(tmp_path_factory):
    drive = simulate_drive(0.75, 1.0, 5)  # 45 s
    log = tmp_path_factory.mktemp("log") / "drive.log"
    info = encode_drive_to_log(drive, log, gnss_seconds=GNSS_S)
    return drive, log, info


def replay(log, model_path, **build) -> tuple[Pipeline, MemorySink, LogReplay]:
    sink = MemorySink()
    pipeline = Pipeline.build(model=model_path, sinks=[sink], **build)
    with LogReplay(log) as source:
        run_source(pipeline, source)
    pipeline.close()
    return pipeline, sink, source


def test_replayed_drive_tracks_ground_truth_and_accounts_for_every_frame(encoded, model_path):
    drive, log, info = encoded
    pipeline, sink, source = replay(log, model_path)
    assert source.error is None and source.sent == source.received == info["frames"]
    st = pipeline.stats
    assert st.received == info["frames"] and st.used == info["frames"] and st.balanced()
    assert st.gnss_fixes == info["gnss_frames"]
    out = sink.arrays()
    assert len(out["t_s"]) == len(drive)  # one row per 50 Hz sample
    np.testing.assert_allclose(out["t_s"], drive.t_s, atol=1e-6)
    status = out["status"]
    assert (status[: int(GNSS_S * 50)] == PoseStatus.GNSS_AIDED).all()
    assert (status[int((GNSS_S + 0.6) * 50):] == PoseStatus.DEAD_RECKONING).all()
    assert out["gnss_outage"][-1] and not out["gnss_outage"][int(GNSS_S * 50)]
    m = trajectory_metrics(out["t_s"], out["x"][:, :2], drive.pose_gt[:, :2], GNSS_S)
    assert m["rmse_m_gnss"] < 0.3
    # the closed-form test model is an odometry baseline: bound its drift like the evaluation's OSD level
    assert m["distance_m"] > 150.0
    assert m["drift_pct"] < 5.0 and m["rmse_m"] < 10.0, m
    lat = pipeline.latency.summary()
    assert lat["end_to_end"]["count"] == len(drive) and lat["infer"]["count"] == \
        (len(drive) - schema.WINDOW_LEN) // DEFAULT_STRIDE + 1


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".trc"])
def test_every_python_can_log_format_replays_the_same_frames(tmp_path, model_path, suffix):
    drive = simulate_drive(0.1, 1.0, 2)  # 6 s
    info = encode_drive_to_log(drive, tmp_path / f"d{suffix}", gnss_seconds=1.0)
    n, _, _ = count_log_frames(tmp_path / f"d{suffix}")
    assert n == info["frames"]
    pipeline, sink, source = replay(tmp_path / f"d{suffix}", model_path)
    assert source.received == n and pipeline.stats.used == n and pipeline.stats.balanced()
    assert len(sink.t_s) == len(drive)


def test_faulty_frames_are_counted_and_the_pose_survives(tmp_path, encoded, model_path, rng):
    drive, log, info = encoded
    frames = list(can.LogReader(str(log)))[: 20 * 450]  # the first ~20 s
    faulty = []
    injected = {"ignored": 0, "checksum": 0, "dlc": 0}
    for i, msg in enumerate(frames):
        faulty.append(msg)
        if i % 97 == 0:
            faulty.append(can.Message(timestamp=msg.timestamp, arbitration_id=0x321, is_extended_id=False,
                                      data=b"\x01\x02"))
            injected["ignored"] += 1
        if i % 89 == 0 and msg.arbitration_id != 0x610:
            data = bytearray(msg.data)
            data[3] ^= 0x40
            faulty.append(can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, is_extended_id=False,
                                      data=bytes(data)))
            injected["checksum"] += 1
        if i % 131 == 0:
            faulty.append(can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id, is_extended_id=False,
                                      data=msg.data[:3]))
            injected["dlc"] += 1
    path = tmp_path / "faulty.log"
    with can.Logger(str(path)) as writer:
        for msg in faulty:
            writer.on_message_received(msg)
    pipeline, sink, _ = replay(path, model_path)
    st = pipeline.stats
    assert st.received == len(faulty) and st.balanced()
    assert st.ignored == injected["ignored"]
    rejected = st.rejected_by_reason()
    assert rejected["dlc"] == injected["dlc"]
    # a corrupted copy fails its checksum (or, once in a while, the counter check: same counter twice)
    assert rejected.get("checksum", 0) + rejected.get("counter", 0) >= injected["checksum"]
    out = sink.arrays()
    err = np.hypot(*(out["x"][:, :2] - drive.pose_gt[: len(out["t_s"]), :2]).T)
    assert np.isfinite(out["x"]).all() and err[: int(GNSS_S * 50)].max() < 0.5


def test_realtime_replay_keeps_the_log_timing(tmp_path, model_path):
    drive = simulate_drive(0.02, 1.0, 2)  # 1.2 s
    encode_drive_to_log(drive, tmp_path / "rt.log")
    pose = InitialPose(0.0, 0.0, psi_rad_to_heading_deg(float(drive.pose_gt[0, 2])))
    pipeline = Pipeline.build(model=model_path, initial_pose=pose)
    t0 = time.monotonic()
    with LogReplay(tmp_path / "rt.log", realtime=True, speed=2.0) as source:
        run_source(pipeline, source)
    wall = time.monotonic() - t0
    assert 0.5 <= wall < 5.0  # 1.2 s of log at 2x
    assert source.received == source.sent > 0
