"""`prml2 doctor` on this machine (CPU only): it runs, reports a table, and each check can fail."""

import json
import re
import subprocess
import sys

import pytest

from prml2_edge.config import RuntimeConfig, config_from_dict
from prml2_edge.service import doctor


def _run(*argv):
    return subprocess.run([sys.executable, "-m", "prml2_edge.cli.main", "doctor", *argv],
                          capture_output=True, text=True, timeout=120)


def test_doctor_on_this_box_with_a_virtual_bus():
    proc = _run("--interface", "virtual", "--channel", "doctor-test", "--json")
    report = json.loads(proc.stdout)
    by_name = {c["name"]: c for c in report["checks"]}
    warm = by_name["warm inference"]
    # the latency itself is a measurement (benchmarks/doctor_inference.py): on a shared box a scheduling stall can
    # put its p99 over 20 ms, which the doctor then reports as such. Here only what holds at any load: it reports a
    # p50 and a p99, positive and in order, and fails only for the deadline; every other check must pass, and the
    # exit code follows the checks
    timing = re.search(r"p50 ([0-9.]+) ms, p99 ([0-9.]+) ms on ", warm["detail"])
    assert timing is not None, warm
    p50, p99 = float(timing[1]), float(timing[2])
    assert 0 < p50 <= p99, warm
    assert warm["result"] == "PASS" or f"> {doctor.DEADLINE_MS:.0f} ms" in warm["detail"], warm
    assert all(c["result"] != "FAIL" for c in report["checks"] if c is not warm), proc.stdout + proc.stderr
    assert report["ok"] == (warm["result"] == "PASS") and proc.returncode == (0 if report["ok"] else 1)
    assert by_name["DBC and signal map"]["result"] == "PASS"
    assert "CPUExecutionProvider" in by_name["ONNX Runtime providers"]["detail"]


def test_doctor_table_names_failures_with_hints(tmp_path):
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"not onnx")
    proc = _run("--interface", "socketcan", "--channel", "nosuchcan7", "--model", str(bad))
    assert proc.returncode == 1
    out = proc.stdout
    assert "CAN link" in out and "no SocketCAN interface 'nosuchcan7'" in out
    assert "hint: sudo deploy/can-setup.sh nosuchcan7" in out
    assert "broken.onnx" in out and "FAIL" in out
    assert "Traceback" not in proc.stderr


def test_can_links_reads_sysfs(tmp_path):
    for name, typ, state in (("can0", 280, "up"), ("eth0", 1, "up"), ("vcan0", 280, "unknown")):
        d = tmp_path / name
        d.mkdir()
        (d / "type").write_text(f"{typ}\n")
        (d / "operstate").write_text(f"{state}\n")
    assert doctor.can_links(tmp_path) == {"can0": "up", "vcan0": "unknown"}
    (tmp_path / "can0" / "operstate").write_text("down\n")
    check = doctor.check_can_link(RuntimeConfig(), sys_class_net=tmp_path)
    assert check.result == doctor.FAIL and "down" in check.detail


@pytest.mark.parametrize("section, expected", [({"signals": {"map": "no_such_map"}}, "unknown signal map"),
                                               ({"model": {"sha256": "0" * 64}}, "does not match the pinned")])
def test_mismatches_fail_the_right_check(section, expected):
    cfg = config_from_dict(section)
    checks = doctor.check_map_and_dbc(cfg) if "signals" in section else doctor.check_model(cfg)[0]
    assert checks.result == doctor.FAIL and expected in checks.detail
