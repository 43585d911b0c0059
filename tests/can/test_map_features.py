"""Richer signal maps: summed parts, absent signals, short payloads, GNSS from another DBC, duplicate IDs."""

from __future__ import annotations

import can
import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.can.signal_map import load_map_and_dbc, load_signal_map, shipped_map_path
from prml2_edge.errors import ConfigError, DbcError
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.rows import DecodedFrame
from prml2_edge.runtime.status import FrameStatus

IDX = {n: s.index for n, s in schema.SIGNAL_BY_NAME.items()}
PROJECT_MAP = shipped_map_path("prml2_onboard")


def toyota_dbc(shared_dir):
    return shared_dir / "dbc" / "opendbc" / "toyota_new_mc_pt_generated.dbc"


def _write(tmp_path, text, name="m.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_toyota_map_loads_with_summed_steering_and_absent_brake(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("toyota_rav4_2018"), toyota_dbc(shared_dir))
    by = {s.name: s for s in smap.signals}
    assert by["steering_wheel_angle_rad"].summed_parts == (("STEER_ANGLE", 1.0), ("STEER_FRACTION", 1.0))
    assert by["brake_pressure_bar"].absent and "BRAKE_MODULE" not in smap.message_names
    assert by["brake_pressure_bar"].substitute_kind == "wheel_deceleration"
    assert by["lat_accel_mps2"].scale == -1.0 and by["yaw_rate_radps"].scale > 0
    assert by["yaw_rate_radps"].rate_hz == 83.0 and by["speedometer_mps"].rate_hz == 41.5
    assert not smap.strict and smap.short_frames


def test_two_part_steering_is_summed_by_hand(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("toyota_rav4_2018"), toyota_dbc(shared_dir))
    # STEER_ANGLE 3|12@0- x1.5: bits 3..0 of byte 0 and byte 1; STEER_FRACTION 39|4@0- x0.1: bits 7..4 of byte 4.
    # -30 steps (-45 deg) = 0xFE2 (12-bit two's complement), fraction -3 (-0.3 deg) = 0xD.
    data = bytes([0x0F, 0xE2, 0x00, 0x00, 0xD0, 0x00, 0x00, 0x00])
    out = FrameDecoder(smap, db).step(can.Message(arbitration_id=0x25, is_extended_id=False, data=data))
    assert out.status is FrameStatus.USED
    got = dict(zip(out.index, out.value_si, strict=True))
    assert got[IDX["steering_wheel_angle_rad"]] == pytest.approx(np.radians(-45.3))


def test_short_payload_is_accepted_when_it_holds_the_mapped_bits(shared_dir):
    smap, db, _ = load_map_and_dbc(shipped_map_path("toyota_rav4_2018"), toyota_dbc(shared_dir))
    dec = FrameDecoder(smap, db)
    # STEER_ANGLE_SENSOR's mapped signals end in byte 4: a 5-byte payload holds them, a 4-byte one does not
    five = dec.step(can.Message(arbitration_id=0x25, is_extended_id=False, data=bytes([0x00, 0x0A, 0, 0, 0x10])))
    assert five.status is FrameStatus.USED
    assert dict(zip(five.index, five.value_si, strict=True))[IDX["steering_wheel_angle_rad"]] == \
        pytest.approx(np.radians(15.1))
    four = dec.step(can.Message(arbitration_id=0x25, is_extended_id=False, data=bytes(4)))
    assert four.status is FrameStatus.REJECTED_DLC
    strict_map = FrameDecoder(load_map_and_dbc(PROJECT_MAP)[0], load_map_and_dbc(PROJECT_MAP)[1])
    assert strict_map.step(can.Message(arbitration_id=0xA0, is_extended_id=False, data=bytes(7))).status \
        is FrameStatus.REJECTED_DLC


def _no_brake_map(tmp_path, substitute: str):
    src = PROJECT_MAP.read_text()
    brake = src[src.index("[signals.brake_pressure_bar]"):src.index("[signals.wheel_speed_fl_mps]")]
    text = src.replace(brake, f"[signals.brake_pressure_bar]\nabsent = true\nsubstitute = {substitute}\n\n")
    return load_signal_map(_write(tmp_path, text))


def test_absent_signal_is_fed_its_constant_substitute_always_valid(tmp_path):
    asm = Assembler.for_map(_no_brake_map(tmp_path, "1.5"))
    i = IDX["brake_pressure_bar"]
    rows = []
    for k in range(5):
        _, emitted = asm.step(DecodedFrame(FrameStatus.USED, 0.02 * k, "SPEED", [0], [10.0], [True]))
        rows += emitted
    assert rows and all(r.valid[i] and r.values[i] == 1.5 and r.age_s[i] == 0.0 for r in rows)


def test_wheel_deceleration_substitute_streams_what_the_formula_gives(tmp_path):
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.runtime.assembler import wheel_deceleration_substitute

    smap = _no_brake_map(tmp_path, '"wheel_deceleration"')
    spec = smap.signals[IDX["brake_pressure_bar"]]
    assert (spec.substitute, spec.substitute_per_mps2) == (0.85, 10.0)
    drive = simulate_drive(0.5, 1.0, 4, family="longitudinal")  # brakes hard, also to standstill
    asm = Assembler.for_map(smap)
    wheels = list(schema.WHEEL_SPEED_INDICES)
    rows = []
    for k in range(len(drive)):  # one frame per 50 Hz row with the four wheel speeds
        frame = DecodedFrame(FrameStatus.USED, drive.t_s[k], "W", wheels, list(drive.onboard[k, wheels]), [True] * 4)
        rows += asm.step(frame)[1]
    rows += asm.flush()
    got = np.array([r.values[IDX["brake_pressure_bar"]] for r in rows])
    want = wheel_deceleration_substitute(drive.onboard, 0.85, 10.0)
    np.testing.assert_allclose(got, want[:len(got)], atol=1e-9)
    assert got.max() > 20.0 and np.all(got >= 0.85)  # braking shows, idle otherwise


def test_only_brake_pressure_may_be_absent_and_keys_are_checked(tmp_path):
    src = PROJECT_MAP.read_text()
    yaw = src[src.index("[signals.yaw_rate_radps]"):src.index("[signals.lat_accel_mps2]")]
    with pytest.raises(ConfigError, match="yaw_rate_radps cannot be absent"):
        load_signal_map(_write(tmp_path, src.replace(yaw, "[signals.yaw_rate_radps]\nabsent = true\n\n")))
    brake = src[src.index("[signals.brake_pressure_bar]"):src.index("[signals.wheel_speed_fl_mps]")]
    with pytest.raises(ConfigError, match="unknown key 'message' with absent = true"):
        load_signal_map(_write(tmp_path, src.replace(brake, brake.replace("message", "absent = true\nmessage"))))
    with pytest.raises(ConfigError, match="substitute 900.0 outside"):
        load_signal_map(_write(tmp_path, src.replace(brake, "[signals.brake_pressure_bar]\nabsent = true\n"
                                                            "substitute = 900\n\n")))
    ok = load_signal_map(_write(tmp_path, src.replace(brake, "[signals.brake_pressure_bar]\nabsent = true\n"
                                                             "substitute = 1.5\n\n")))
    assert ok.signals[IDX["brake_pressure_bar"]].substitute == 1.5
    with pytest.raises(ConfigError, match="substitute 'zeros' unknown"):
        load_signal_map(_write(tmp_path, src.replace(brake, "[signals.brake_pressure_bar]\nabsent = true\n"
                                                            'substitute = "zeros"\n\n')))
    with pytest.raises(ConfigError, match="'per_mps2' goes with"):
        load_signal_map(_write(tmp_path, src.replace(brake, "[signals.brake_pressure_bar]\nabsent = true\n"
                                                            "per_mps2 = 3.0\n\n")))
    with pytest.raises(ConfigError, match="'part_scale' must be a list of 2"):
        load_signal_map(_write(tmp_path, src.replace('signal = "YAW_RATE"',
                                                     'signal = ["YAW_RATE", "LAT_ACCEL"]\npart_scale = [1.0]')))


def test_strict_dbc_failure_names_the_map_fix(shared_dir, tmp_path):
    src = shipped_map_path("toyota_rav4_2018").read_text().replace("strict = false", "strict = true")
    with pytest.raises(DbcError, match="overlapping in message PCS_HUD.*set strict = false"):
        load_map_and_dbc(_write(tmp_path, src), toyota_dbc(shared_dir))


def test_gnss_message_colliding_with_a_vehicle_message_is_refused_naming_both(shared_dir, tmp_path):
    src = shipped_map_path("toyota_rav4_2018").read_text()
    src += ('\n[gnss]\nmessage = "GNSS_FIX"\nx = "GNSS_POS_X"\ny = "GNSS_POS_Y"\nheading = "GNSS_HEADING"\n'
            'valid = "GNSS_VALID"\ndbc = "prml2_onboard.dbc"\n')
    with pytest.raises(DbcError, match=r"GNSS_FIX \(ID 0x610.*BODY_CONTROL_STATE_2 \(ID 0x610"):
        load_map_and_dbc(_write(tmp_path, src), toyota_dbc(shared_dir))
    # the same GNSS message beside a bus that leaves 0x610 free is taken from the project DBC
    vw = shipped_map_path("vw_mqb").read_text() + src[src.index("\n[gnss]"):]
    smap, db, _ = load_map_and_dbc(_write(tmp_path, vw, "vw.toml"), shared_dir / "dbc" / "opendbc" / "vw_mqb.dbc")
    assert db.get_message_by_name("GNSS_FIX").frame_id == 0x610


def test_two_messages_on_one_id_are_refused(tmp_path):
    dbc = (PROJECT_MAP.parent.parent / "prml2_onboard.dbc").read_text()
    merged = dbc + '\nBO_ 160 BODY_STATE: 8 XXX\n SG_ DOOR : 0|1@1+ (1,0) [0|1] "" XXX\n'
    p = tmp_path / "merged.dbc"
    p.write_text(merged)
    with pytest.raises(DbcError, match=r"WHEEL_SPEEDS_FRONT \(ID 0xa0\) shares its ID with BODY_STATE"):
        load_map_and_dbc(PROJECT_MAP, p)
