"""Encoding a drive to a CAN log: python-can reads it back, cantools decodes the original signals."""

from __future__ import annotations

import math
from collections import defaultdict

import can
import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.can.checksum import prml2_crc8
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.cli.main import main
from prml2_edge.data.revsted import write_drive_csv
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import ConfigError


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(0.4, 1.0, seed=4, family="mixed")


@pytest.fixture(scope="module")
def map_db():
    smap, db, _ = load_map_and_dbc(shipped_map_path("prml2_onboard"))
    return smap, db


def _read(path, db):
    frames = defaultdict(list)  # message name -> [(timestamp, raw bytes, decoded)]
    for msg in can.LogReader(str(path)):
        m = db.get_message_by_frame_id(msg.arbitration_id)
        frames[m.name].append((msg.timestamp, bytes(msg.data), m.decode(msg.data, decode_choices=False)))
    return frames


@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_log_decodes_to_original_signals(drive, map_db, tmp_path, suffix):
    smap, db = map_db
    out = tmp_path / f"drive{suffix}"
    stats = encode_drive_to_log(drive, out, gnss_seconds=2.0)
    frames = _read(out, db)
    assert sum(len(v) for v in frames.values()) == stats["frames"]
    duration = len(drive) * schema.DT_S
    for spec in smap.signals:
        got = frames[spec.message]
        assert len(got) == pytest.approx(duration * spec.rate_hz, abs=1)  # message rate from the map
        t = np.array([g[0] for g in got])
        idx = np.minimum(np.floor((t - drive.t_s[0]) / schema.DT_S + 1e-6).astype(int), len(drive) - 1)
        decoded = np.array([spec.to_si(g[2][spec.signal], g[2].get(spec.sign, 0) if spec.sign else 0) for g in got])
        original = drive.onboard[idx, schema.SIGNAL_BY_NAME[spec.name].index]
        dbc_step = db.get_message_by_name(spec.message).get_signal_by_name(spec.signal).scale * abs(spec.scale)
        step = max(dbc_step, schema.SIGNAL_BY_NAME[spec.name].revsted_step)
        assert np.max(np.abs(decoded - original)) <= step, spec.name
        assert all(g[2][spec.valid] == spec.valid_value for g in got)
    for name, checks in smap.messages.items():
        got = frames[name]
        counters = np.array([g[2][checks.counter] for g in got])
        assert np.array_equal(counters, np.arange(len(got)) % 16)
        frame_id = db.get_message_by_name(name).frame_id
        assert all(g[1][0] == prml2_crc8(frame_id, g[1]) for g in got)
    gnss = frames["GNSS_FIX"]
    assert len(gnss) == stats["gnss_frames"] == 20
    x0, y0, psi0 = drive.pose_gt[0]
    assert gnss[0][2]["GNSS_POS_X"] == pytest.approx(x0, abs=0.01)
    assert gnss[0][2]["GNSS_HEADING"] == pytest.approx((90 - math.degrees(psi0)) % 360, abs=0.1)
    assert gnss[-1][0] < drive.t_s[0] + 2.0


def test_gnss_frames_carry_the_course_over_ground():
    """A receiver on the bus sends the direction of travel, not the yaw: psi + atan2(v_y, v_x) while moving."""
    from types import SimpleNamespace

    from prml2_edge.can.encode import course_over_ground

    pose = np.array([[0.0, 0.0, 0.3], [1.0, 0.0, 0.3], [2.0, 0.0, 0.3]])
    z = np.zeros((3, schema.NUM_STATES))
    z[:, schema.Z.V_X] = (10.0, 0.2, 10.0)
    z[:, schema.Z.V_Y] = (1.0, 0.1, -1.0)  # the middle row too slow for a course: the yaw
    got = course_over_ground(SimpleNamespace(pose_gt=pose, z_gt=z))
    np.testing.assert_allclose(got, [0.3 + math.atan(0.1), 0.3, 0.3 - math.atan(0.1)])
    np.testing.assert_array_equal(course_over_ground(SimpleNamespace(pose_gt=pose, z_gt=None)), pose[:, 2])


def test_frames_in_time_order_and_cli(drive, tmp_path, capsys):
    csv = tmp_path / "d.csv"
    write_drive_csv(drive, csv)
    out = tmp_path / "d.log"
    assert main(["encode", str(csv), "--dbc", str(shipped_map_path("prml2_onboard").parents[1] / "prml2_onboard.dbc"),
                 "--out", str(out)]) == 0
    assert "frames" in capsys.readouterr().out
    ts = [m.timestamp for m in can.LogReader(str(out))]
    assert ts == sorted(ts) and len(ts) > 1000


def test_bad_extension_and_corrupt_sample(drive, tmp_path):
    with pytest.raises(ConfigError, match="unsupported log format"):
        encode_drive_to_log(drive, tmp_path / "d.xyz")
    bad = drive.slice(0, 100)
    bad.onboard[10, 2] = np.nan
    stats = encode_drive_to_log(bad, tmp_path / "bad.log")
    assert stats["invalid"] == {"yaw_rate_radps": 1}


def test_data_and_encode_import_without_torch():
    import subprocess
    import sys

    code = ("import sys; sys.modules['torch'] = None; sys.modules['scipy'] = None; "
            "import prml2_edge.data.datasets, prml2_edge.data.windows, prml2_edge.data.simulate; "
            "import prml2_edge.can.encode; "
            "from prml2_edge.data.simulate import simulate_drive; simulate_drive(0.05, 1.0, 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize("name", ["vw_mqb", "hyundai_2015_ccan"])
def test_production_dbc_maps_round_trip(drive, shared_dir, tmp_path, name):
    """Sign bits (VW), offsets and other resolutions: decoded within one DBC step of the original."""
    map_path = shipped_map_path(name)
    dbc = shared_dir / "dbc" / "opendbc" / f"{name}.dbc"
    smap, db, _ = load_map_and_dbc(map_path, dbc)
    part = drive.slice(0, 500)
    encode_drive_to_log(part, tmp_path / "d.trc", signal_map_path=map_path, dbc_path=dbc)
    n = 0
    for msg in can.LogReader(str(tmp_path / "d.trc")):
        m = db.get_message_by_frame_id(msg.arbitration_id)
        values = m.decode(msg.data, decode_choices=False)
        i = min(int(np.floor((msg.timestamp - part.t_s[0]) / schema.DT_S + 1e-6)), len(part) - 1)
        for spec in (s for s in smap.signals if s.message == m.name):
            decoded = spec.to_si(values[spec.signal], values[spec.sign] if spec.sign else 0)
            step = m.get_signal_by_name(spec.signal).scale * abs(spec.scale)
            assert abs(decoded - part.onboard[i, schema.SIGNAL_BY_NAME[spec.name].index]) <= step * 0.51 + 1e-9
            n += 1
    assert n > 1000
