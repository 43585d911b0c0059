"""Production DBCs (opendbc VW MQB and Hyundai): frames encoded with the real DBC decode to the canonical vector."""

from __future__ import annotations

import math

import can
import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.status import FrameStatus
from prml2_edge.schema import psi_rad_to_heading_deg

IDX = {n: s.index for n, s in schema.SIGNAL_BY_NAME.items()}
MAPS = ["vw_mqb", "hyundai_2015_ccan"]


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(0.4, 1.0, 4, family="lateral")  # 24 s with left and right turns


def dbc_path(shared_dir, name):
    return shared_dir / "dbc" / "opendbc" / f"{name}.dbc"


def resolution_si(smap, db) -> np.ndarray:
    """(9,) DBC resolution of each canonical signal in SI units."""
    res = np.zeros(schema.NUM_SIGNALS)
    for spec in smap.signals:
        res[IDX[spec.name]] = abs(db.get_message_by_name(spec.message).get_signal_by_name(spec.signal).scale
                                  * spec.scale)
    return res


@pytest.mark.parametrize("name", MAPS)
def test_frames_encoded_with_the_real_dbc_decode_to_the_drive(tmp_path, shared_dir, drive, name):
    smap, db, _ = load_map_and_dbc(shipped_map_path(name), dbc_path(shared_dir, name))
    info = encode_drive_to_log(drive, tmp_path / "d.log", signal_map_path=shipped_map_path(name),
                               dbc_path=dbc_path(shared_dir, name))
    stats = FrameStats()
    dec = FrameDecoder(smap, db)
    asm = Assembler.for_map(smap)
    rows = []
    for msg in can.LogReader(str(tmp_path / "d.log")):
        decoded = dec.step(msg)
        status, emitted = asm.step(decoded)
        stats.add_frame(status, decoded)
        rows += emitted
    rows += asm.flush()
    assert stats.received == info["frames"] == stats.used and stats.balanced()
    values = np.array([r.values for r in rows])
    assert len(rows) == len(drive) and all(r.all_valid for r in rows)
    tol = 0.5 * resolution_si(smap, db) + 1e-9
    np.testing.assert_array_less(np.abs(values - drive.onboard), np.broadcast_to(tol, values.shape) + 1e-6)
    steer, yaw = drive.onboard[:, IDX["steering_wheel_angle_rad"]], drive.onboard[:, IDX["yaw_rate_radps"]]
    assert steer.min() < -0.05 < 0.05 < steer.max() and yaw.min() < -0.05 < 0.05 < yaw.max()  # both signs tested


def test_vw_sign_bits_g_units_and_quality_bits_by_hand(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("vw_mqb"), dbc_path(shared_dir, "vw_mqb"))
    msg = db.get_message_by_name("ESP_02")
    values = {s.name: 0 for s in msg.signals}
    values.update({"ESP_Gierrate": 10.0, "ESP_VZ_Gierrate": 1, "ESP_Querbeschleunigung": 0.5})
    frame = can.Message(arbitration_id=msg.frame_id, is_extended_id=False, data=msg.encode(values))
    out = FrameDecoder(smap, db).step(frame)
    got = dict(zip(out.index, out.value_si, strict=True))
    assert got[IDX["yaw_rate_radps"]] == pytest.approx(-math.radians(10.0))
    assert got[IDX["lat_accel_mps2"]] == pytest.approx(0.5 * schema.G_MPS2, abs=1e-6)
    values["ESP_QBit_Gierrate"] = 1  # VW: quality bit set = substitute value
    out = FrameDecoder(smap, db).step(can.Message(arbitration_id=msg.frame_id, is_extended_id=False,
                                                  data=msg.encode(values)))
    ok = dict(zip(out.index, out.ok, strict=True))
    assert not ok[IDX["yaw_rate_radps"]] and ok[IDX["lat_accel_mps2"]]


def test_hyundai_alive_counter_is_checked(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("hyundai_2015_ccan"), dbc_path(shared_dir, "hyundai_2015_ccan"))
    msg = db.get_message_by_name("SAS11")
    dec = FrameDecoder(smap, db)

    def sas(counter):
        values = {s.name: 0 for s in msg.signals} | {"SAS_Angle": -45.0, "MsgCount": counter}
        return can.Message(arbitration_id=msg.frame_id, is_extended_id=False, data=msg.encode(values))

    assert dec.step(sas(3)).status is FrameStatus.USED
    assert dec.step(sas(3)).status is FrameStatus.REJECTED_COUNTER
    out = dec.step(sas(4))
    assert out.status is FrameStatus.USED and out.value_si == [pytest.approx(math.radians(-45.0))]


def _replay(tmp_path, drive, model, log_name, **build) -> np.ndarray:
    pose = InitialPose(float(drive.pose_gt[0, 0]), float(drive.pose_gt[0, 1]),
                       psi_rad_to_heading_deg(float(drive.pose_gt[0, 2])))
    sink = MemorySink()
    pipeline = Pipeline.build(model=model, initial_pose=pose, sinks=[sink], **build)
    with LogReplay(tmp_path / log_name) as source:
        run_source(pipeline, source)
    assert pipeline.stats.balanced() and pipeline.stats.rejected == 0
    out = sink.arrays()
    assert len(out["t_s"]) == len(drive) and out["model_used"].sum() == len(drive) - schema.WINDOW_LEN + 1
    return out["x"]


@pytest.mark.parametrize("name", MAPS)
def test_replay_with_a_production_map_matches_the_project_dbc(tmp_path, shared_dir, drive, name):
    model = make_kinematic_model(tmp_path / "m.onnx")
    encode_drive_to_log(drive, tmp_path / "d.blf", signal_map_path=shipped_map_path(name),
                        dbc_path=dbc_path(shared_dir, name))
    encode_drive_to_log(drive, tmp_path / "ref.log")
    x = _replay(tmp_path, drive, model, "d.blf", map=name, dbc=dbc_path(shared_dir, name))
    ref = _replay(tmp_path, drive, model, "ref.log")
    dist = float(np.sum(np.hypot(*np.diff(drive.pose_gt[:, :2], axis=0).T)))
    diff = np.hypot(*(x[:, :2] - ref[:, :2]).T)
    # the same drive through another car's DBC differs only by that DBC's resolutions
    assert dist > 100.0 and diff.max() < 0.01 * dist
