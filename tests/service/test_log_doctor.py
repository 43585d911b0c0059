"""prml2 doctor --log: a map checked against a recorded drive names the culprit and the fix for each
mistake a user makes, and raises no false alarm on clean logs (the 20-drive version is
benchmarks/doctor_log.py)."""

from __future__ import annotations

import json

import pytest

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import SHIPPED_MAPS, load_map_and_dbc, shipped_map_path
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.service.log_doctor import check_log_file, culprits
from prml2_edge.testing.map_mistakes import MISTAKES, drop_message, expected_culprit, wrong_map

OPENDBC = {"vw_mqb": "vw_mqb.dbc", "hyundai_2015_ccan": "hyundai_2015_ccan.dbc",
           "toyota_rav4_2018": "toyota_new_mc_pt_generated.dbc"}


def dbc_for(shared_dir, name):
    return shared_dir / "dbc" / "opendbc" / OPENDBC[name] if name in OPENDBC else None


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(0.75, 1.0, 1, family="mixed")  # 45 s with turns, some below 12 m/s


@pytest.mark.parametrize("name", SHIPPED_MAPS)
def test_every_mistake_is_named_with_its_fix_and_clean_logs_pass(tmp_path, shared_dir, drive, name):
    dbc = dbc_for(shared_dir, name)
    log = tmp_path / "clean.log"
    encode_drive_to_log(drive, log, signal_map_path=shipped_map_path(name), dbc_path=dbc)
    clean = check_log_file(log, shipped_map_path(name), dbc)
    assert clean.ok, culprits(clean)
    smap, db, _ = load_map_and_dbc(shipped_map_path(name), dbc)
    for mistake in MISTAKES:
        map_path = wrong_map(shipped_map_path(name), mistake, tmp_path / f"{mistake}.toml")
        log_used = log
        if mistake == "message_absent":
            yaw = next(s for s in smap.signals if s.name == "yaw_rate_radps")
            log_used = tmp_path / "absent.log"
            assert drop_message(log, log_used, db.get_message_by_name(yaw.message).frame_id) > 0
        report = check_log_file(log_used, map_path, dbc)
        found = dict(culprits(report))
        want = expected_culprit(mistake)
        assert not report.ok and want in found, (mistake, found)
        if mistake.startswith("flip_"):
            right = next(s for s in smap.signals if s.name == want).scale
            assert found[want] == f"set scale = {right:.10g} in [signals.{want}]", found[want]
            assert list(found) == [want]  # one culprit, not a cascade
        elif mistake == "wheel_kmh_as_mps":
            assert found[want].startswith(f"set scale = {1 / 3.6:.10g}") and "km/h -> m/s" in found[want]
        else:
            bad = next(s for s in report.signals if s.name == want)
            assert "never seen" in bad.problems[0] and f"(ID {bad.frame_id:#x})" in bad.problems[0]


def test_cli_table_and_json(tmp_path, drive, capsys):
    log = tmp_path / "d.log"
    encode_drive_to_log(drive, log)
    assert main(["doctor", "--log", str(log)]) == 0
    assert "OK: the map reads this log as the physics expects" in capsys.readouterr().out
    bad = wrong_map(shipped_map_path("prml2_onboard"), "flip_lat", tmp_path / "m.toml")
    assert main(["doctor", "--log", str(log), "--map", str(bad), "--json"]) == 1
    doc = json.loads(capsys.readouterr().out)
    failed = [f for f in doc["physics"] if f["result"] == "FAIL"]
    assert not doc["ok"] and [f["signal"] for f in failed] == ["lat_accel_mps2"]
    assert "opposite sign of v*yaw rate" in failed[0]["detail"] and failed[0]["fix"] == \
        "set scale = 1 in [signals.lat_accel_mps2]"


def test_wrong_dbc_names_every_missing_message(tmp_path, shared_dir, drive, capsys):
    log = tmp_path / "toyota.log"
    encode_drive_to_log(drive, log, signal_map_path=shipped_map_path("toyota_rav4_2018"),
                        dbc_path=dbc_for(shared_dir, "toyota_rav4_2018"))
    assert main(["doctor", "--log", str(log)]) == 1  # the project map on a Toyota bus
    out = capsys.readouterr().out
    assert "never seen: no frame of ESP_YAW_LAT (ID 0x130) in the log" in out and "9 problem(s) to fix" in out
