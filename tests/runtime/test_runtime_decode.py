"""FrameDecoder: project-DBC frames decoded to SI; every bad frame rejected with its reason, never raised."""

from __future__ import annotations

import math

import can
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prml2_edge import schema
from prml2_edge.can.checksum import prml2_crc8
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.status import FrameStatus

IDX = {n: s.index for n, s in schema.SIGNAL_BY_NAME.items()}


@pytest.fixture(scope="module")
def project():
    smap, db, _ = load_map_and_dbc(shipped_map_path("prml2_onboard"))
    return smap, db


def frame(db, name: str, values: dict, t_s: float = 0.0, counter: int = 0, fix_crc: bool = True,
          dlc: int | None = None) -> can.Message:
    msg = db.get_message_by_name(name)
    full = {s.name: 0 for s in msg.signals}
    full.update(values)
    if "COUNTER" in full:
        full["COUNTER"] = counter
    data = bytearray(msg.encode(full))
    if fix_crc and "CHECKSUM" in full:
        data[0] = prml2_crc8(msg.frame_id, bytes(data))
    if dlc is not None:
        data = data[:dlc]
    return can.Message(timestamp=t_s, arbitration_id=msg.frame_id, is_extended_id=False, data=bytes(data))


def test_wheel_speeds_and_yaw_frame_decode_to_si(project):
    smap, db = project
    dec = FrameDecoder(smap, db)
    out = dec.step(frame(db, "WHEEL_SPEEDS_FRONT", {"WHEEL_SPEED_FL": 36.0, "WHEEL_SPEED_FR": 72.0,
                                                    "WHEEL_SPEED_FL_VALID": 1, "WHEEL_SPEED_FR_VALID": 1}, 1.5))
    assert out.status is FrameStatus.USED and out.t_s == 1.5
    got = dict(zip(out.index, out.value_si, strict=True))
    assert got[IDX["wheel_speed_fl_mps"]] == pytest.approx(10.0)
    assert got[IDX["wheel_speed_fr_mps"]] == pytest.approx(20.0)
    out = dec.step(frame(db, "ESP_YAW_LAT", {"YAW_RATE": -57.2958, "LAT_ACCEL": 3.5, "YAW_RATE_VALID": 1,
                                             "LAT_ACCEL_VALID": 1}))
    got = dict(zip(out.index, out.value_si, strict=True))
    assert got[IDX["yaw_rate_radps"]] == pytest.approx(-1.0, abs=2e-4)
    assert got[IDX["lat_accel_mps2"]] == pytest.approx(3.5)


def test_bad_frames_are_rejected_with_their_reason_and_never_raise(project):
    smap, db = project
    stats = FrameStats()
    dec = FrameDecoder(smap, db)
    ok = {"VEHICLE_SPEED": 50.0, "VEHICLE_SPEED_VALID": 1}
    cases = [
        (can.Message(arbitration_id=0x7FF, data=b"\x00" * 8), FrameStatus.IGNORED),
        (frame(db, "VEHICLE_SPEED", ok, counter=0), FrameStatus.USED),
        (frame(db, "VEHICLE_SPEED", ok, counter=0), FrameStatus.REJECTED_COUNTER),  # repeated counter
        (frame(db, "VEHICLE_SPEED", ok, counter=1, dlc=5), FrameStatus.REJECTED_DLC),
        (frame(db, "VEHICLE_SPEED", ok, counter=1, fix_crc=False), FrameStatus.REJECTED_CHECKSUM),
        (frame(db, "VEHICLE_SPEED", ok, counter=1), FrameStatus.USED),
        (frame(db, "VEHICLE_SPEED", ok, counter=9), FrameStatus.REJECTED_COUNTER),  # jump of 8 > 7
        (frame(db, "VEHICLE_SPEED", ok, counter=11), FrameStatus.USED),  # 2 frames lost: a gap, accepted
        (frame(db, "VEHICLE_SPEED", {"VEHICLE_SPEED": 400.0, "VEHICLE_SPEED_VALID": 1}, counter=12),
         FrameStatus.REJECTED_RANGE),  # 111 m/s > schema max 84
        (frame(db, "VEHICLE_SPEED", {"VEHICLE_SPEED": 50.0, "VEHICLE_SPEED_VALID": 0}, counter=13),
         FrameStatus.REJECTED_INVALID),
        (can.Message(arbitration_id=db.get_message_by_name("VEHICLE_SPEED").frame_id, is_remote_frame=True),
         FrameStatus.IGNORED),
        (can.Message(arbitration_id=db.get_message_by_name("VEHICLE_SPEED").frame_id, is_extended_id=True,
                     data=b"\x00" * 8), FrameStatus.IGNORED),
    ]
    for msg, want in cases:
        out = dec.step(msg)
        assert out.status is want, (msg, out.status, want)
        stats.add_frame(out.status, out)
    assert stats.balanced() and stats.received == len(cases)
    assert stats.counter_gaps == 1
    assert stats.signal_out_of_range[IDX["speedometer_mps"]] == 1
    assert stats.signal_invalid_flag[IDX["speedometer_mps"]] == 1
    assert stats.rejected_by_reason() == {"dlc": 1, "checksum": 1, "counter": 2, "range": 1, "invalid": 1}


def test_invalid_quality_bit_is_passed_on_as_not_ok(project):
    smap, db = project
    out = FrameDecoder(smap, db).step(frame(db, "WHEEL_SPEEDS_REAR", {"WHEEL_SPEED_RL": 10.0, "WHEEL_SPEED_RR": 10.0,
                                                                       "WHEEL_SPEED_RL_VALID": 1,
                                                                       "WHEEL_SPEED_RR_VALID": 0}))
    assert out.status is FrameStatus.USED  # one good value
    ok = dict(zip(out.index, out.ok, strict=True))
    assert ok[IDX["wheel_speed_rl_mps"]] and not ok[IDX["wheel_speed_rr_mps"]]


def test_gnss_fix_heading_converts_to_psi(project):
    smap, db = project
    out = FrameDecoder(smap, db).step(frame(db, "GNSS_FIX", {"GNSS_POS_X": 12.5, "GNSS_POS_Y": -3.0,
                                                             "GNSS_HEADING": 90.0, "GNSS_VALID": 1}, 2.0))
    assert out.status is FrameStatus.USED and out.gnss is not None and out.gnss.valid
    assert (out.gnss.x_m, out.gnss.y_m) == pytest.approx((12.5, -3.0))
    assert out.gnss.psi_rad == pytest.approx(0.0, abs=1e-9)  # heading 90 deg cw from north = east
    bad = FrameDecoder(smap, db).step(frame(db, "GNSS_FIX", {"GNSS_VALID": 0}))
    assert bad.status is FrameStatus.REJECTED_INVALID and not bad.gnss.valid


def test_garbage_payloads_never_raise(project, rng):
    smap, db = project
    stats = FrameStats()
    dec = FrameDecoder(smap, db)
    ids = sorted(dec.plans) + [0x123]
    for _ in range(2000):
        msg = can.Message(timestamp=float(rng.random()), arbitration_id=int(rng.choice(ids)),
                          data=bytes(rng.integers(0, 256, int(rng.integers(0, 9)), dtype=np.uint8)))
        out = dec.step(msg)
        stats.count(out.status, out.message)
        assert all(math.isfinite(v) for v in out.value_si)
    assert stats.balanced() and stats.received == 2000


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(range(schema.NUM_SIGNALS)), st.floats(-0.99, 0.99))  # the range edge may round outside
def test_round_trip_through_the_dbc_within_one_resolution_step(project, index, u):
    smap, db = project
    spec = smap.signals[index]
    sig = schema.SIGNALS[index]
    lo, hi = max(sig.min, -100.0), min(sig.max, 60.0)
    value_si = lo + (u + 1.0) / 2.0 * (hi - lo)
    msg = db.get_message_by_name(spec.message)
    phys, sign = spec.from_si(value_si)
    values = {spec.signal: phys}
    if spec.valid:
        values[spec.valid] = spec.valid_value
    out = FrameDecoder(smap, db).step(frame(db, spec.message, values))
    got = dict(zip(out.index, out.value_si, strict=True))[index]
    resolution_si = abs(msg.get_signal_by_name(spec.signal).scale * spec.scale)
    assert got == pytest.approx(value_si, abs=0.51 * resolution_si + 1e-9)
