"""Deployment kit files: systemd unit verification and the CAN bring-up script's errors."""

import os
import shutil
import subprocess

import pytest


def test_systemd_unit_verifies(repo_root, tmp_path):
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not installed here (apt-get install systemd)")
    unit = (repo_root / "deploy" / "prml2-edge.service").read_text()
    # verify resolves ExecStart binaries: point them at files that exist in this checkout/venv
    fake_root = tmp_path / "opt"
    (fake_root / "deploy").mkdir(parents=True)
    (fake_root / ".venv" / "bin").mkdir(parents=True)
    for rel in ("deploy/can-setup.sh", ".venv/bin/prml2"):
        p = fake_root / rel
        p.write_text("#!/bin/sh\nexit 0\n")
        p.chmod(0o755)
    unit = unit.replace("/opt/prml2-edge", str(fake_root))
    (tmp_path / "prml2-edge.service").write_text(unit)
    proc = subprocess.run(["systemd-analyze", "verify", "--man=no", str(tmp_path / "prml2-edge.service")],
                          capture_output=True, text=True)
    relevant = [line for line in proc.stderr.splitlines()
                if "prml2-edge.service" in line and "sys-subsystem-net-devices-can0.device" not in line]
    assert proc.returncode == 0 or not relevant, proc.stderr
    assert not relevant, proc.stderr


def test_unit_runs_unprivileged_with_watchdog(repo_root):
    unit = (repo_root / "deploy" / "prml2-edge.service").read_text()
    for needle in ("Type=notify", "WatchdogSec=", "User=prml2", "Restart=on-failure",
                   "After=network-pre.target sys-subsystem-net-devices-can0.device", "StandardOutput=journal"):
        assert needle in unit


def test_can_setup_says_what_is_missing(repo_root):
    script = repo_root / "deploy" / "can-setup.sh"
    proc = subprocess.run(["bash", str(script), "vcan0"], capture_output=True, text=True)
    if proc.returncode == 0:
        # this machine can create vcan0: running again is a no-op (idempotent)
        again = subprocess.run(["bash", str(script), "vcan0"], capture_output=True, text=True)
        assert again.returncode == 0, again.stderr
        return
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("can-setup: "), proc.stderr
    if os.geteuid() == 0:
        assert "vcan" in lines[0] or "ip" in lines[0]
    else:
        assert "root" in lines[0]
