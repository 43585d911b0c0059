"""dbc/prml2_onboard.dbc against the schema, through its shipped signal map."""

import tomllib

import cantools
import pytest

from prml2_edge import schema
from prml2_edge.can.checksum import checksum_function, crc8_sae_j1850, prml2_crc8
from prml2_edge.resources import project_dbc_path, resource_path

# Expected message periods of a production car (issue 2): signal -> (min Hz, max Hz).
RATE_BANDS = {
    "speedometer_mps": (10, 50),
    "steering_wheel_angle_rad": (80, 120),
    "yaw_rate_radps": (40, 60),
    "lat_accel_mps2": (40, 60),
    "brake_pressure_bar": (40, 60),
}
UNIT_TO_SI = {"km/h": 1 / 3.6, "deg": 0.017453292519943295, "deg/s": 0.017453292519943295, "m/s2": 1.0, "bar": 1.0}


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(project_dbc_path(), strict=True)


@pytest.fixture(scope="module")
def signal_map():
    with open(resource_path("dbc", "maps", "prml2_onboard.toml"), "rb") as f:
        return tomllib.load(f)


def test_every_schema_signal_is_mapped_and_fits(db, signal_map):
    assert set(signal_map["signals"]) == set(schema.SIGNAL_NAMES)
    for sig in schema.SIGNALS:
        entry = signal_map["signals"][sig.name]
        msg = db.get_message_by_name(entry["message"])
        dbc_sig = msg.get_signal_by_name(entry["signal"])
        # the map converts the DBC unit to the schema's SI unit
        assert entry["scale"] == pytest.approx(UNIT_TO_SI[dbc_sig.unit]), sig.name
        # resolution at least as fine as ReV-StED's
        assert dbc_sig.scale * entry["scale"] <= sig.revsted_step + 1e-12, sig.name
        # the DBC's range covers the schema's physical range
        lo = dbc_sig.minimum * entry["scale"]
        hi = dbc_sig.maximum * entry["scale"]
        assert lo <= sig.min and hi >= sig.max, (sig.name, lo, hi)
        # declared rate matches the DBC cycle time, and the schema's rate
        assert msg.cycle_time == pytest.approx(1000.0 / entry["rate_hz"])
        assert entry["rate_hz"] == sig.rate_hz
        msg.get_signal_by_name(entry["valid"])


def test_rates_are_like_a_real_car(db, signal_map):
    for name, (lo, hi) in RATE_BANDS.items():
        assert lo <= signal_map["signals"][name]["rate_hz"] <= hi, name
    for name in schema.WHEEL_SPEED_NAMES:
        assert 80 <= signal_map["signals"][name]["rate_hz"] <= 120


def test_every_input_message_has_counter_and_checksum(db, signal_map):
    mapped = {e["message"] for e in signal_map["signals"].values()}
    assert mapped == set(signal_map["messages"])
    for name in mapped:
        msg = db.get_message_by_name(name)
        checks = signal_map["messages"][name]
        assert msg.get_signal_by_name(checks["counter"]).length == 4
        assert msg.get_signal_by_name(checks["checksum"]).length == 8
        checksum_function(checks["checksum_algorithm"])


def test_checksum_round_trip_detects_corruption(db):
    msg = db.get_message_by_name("ESP_YAW_LAT")
    data = bytearray(msg.encode({"CHECKSUM": 0, "COUNTER": 3, "YAW_RATE_VALID": 1, "LAT_ACCEL_VALID": 1,
                                 "YAW_RATE": 12.5, "LAT_ACCEL": -1.25}))
    data[0] = prml2_crc8(msg.frame_id, bytes(data))
    decoded = msg.decode(bytes(data))
    assert decoded["YAW_RATE"] == pytest.approx(12.5) and decoded["LAT_ACCEL"] == pytest.approx(-1.25)
    assert prml2_crc8(msg.frame_id, bytes(data)) == data[0]
    corrupted = bytearray(data)
    corrupted[3] ^= 0x10
    assert prml2_crc8(msg.frame_id, bytes(corrupted)) != corrupted[0]
    # same payload on another ID fails
    assert prml2_crc8(msg.frame_id + 1, bytes(data)) != data[0]
    assert crc8_sae_j1850(b"123456789") == 0x4B


def test_output_and_gnss_messages_exist(db, signal_map):
    for name in ("PRML2_POSE", "PRML2_DYNAMICS", "PRML2_POSE_STD", signal_map["gnss"]["message"]):
        db.get_message_by_name(name)
