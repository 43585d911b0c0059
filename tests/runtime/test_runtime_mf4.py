"""ASAM MDF4 logs (issue 19): `prml2 replay drive.mf4` through python-can's MF4 support (asammdf, the mf4 extra)."""

from __future__ import annotations

import json
import subprocess
import sys

import can
import numpy as np
import pytest
from runtime_models import make_kinematic_model

pytest.importorskip("asammdf")  # the mf4 extra (in dev)

from prml2_edge.can.encode import encode_drive_to_log  # noqa: E402
from prml2_edge.can.signal_map import load_dbc  # noqa: E402
from prml2_edge.cli.main import main  # noqa: E402
from prml2_edge.data.simulate import simulate_drive  # noqa: E402
from prml2_edge.resources import project_dbc_path  # noqa: E402
from prml2_edge.testing.faults import Fault, InjectionCounts, inject  # noqa: E402

FAULTS = [Fault("checksum", 2.0, 2.5, message="WHEEL_SPEEDS"), Fault("duplicate", 3.0, 3.2),
          Fault("random_burst", 4.0, 4.5, count=40), Fault("error_frames", 5.0, 5.0, count=5),
          Fault("drop_message", 6.0, 6.6, message="YAW_LATACC")]


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """One faulty frame stream written twice: candump .log (python-can) and .mf4 (python-can's MF4Writer)."""
    root = tmp_path_factory.mktemp("mf4")
    drive = simulate_drive(0.15, 1.0, 3)  # 9 s
    encode_drive_to_log(drive, root / "clean.log", gnss_seconds=2.0)
    counts = InjectionCounts()
    frames = list(inject(can.LogReader(str(root / "clean.log")), FAULTS, load_dbc(project_dbc_path()), seed=1,
                         counts=counts))
    for name in ("drive.log", "drive.mf4"):
        with can.Logger(str(root / name)) as writer:  # .mf4: can.io.MF4Writer
            for msg in frames:
                writer.on_message_received(msg)
    assert isinstance(can.Logger(str(root / "probe.mf4")), can.io.MF4Writer)
    return root, make_kinematic_model(root / "kinematic.onnx"), frames


def _replay(root, model, name):
    out = root / name.replace(".", "_")
    assert main(["replay", str(root / name), "--model", str(model), "--jsonl", str(out) + ".jsonl",
                 "--summary-json", str(out) + ".json"]) == 0
    records = [json.loads(line) for line in open(str(out) + ".jsonl")]
    return json.loads(open(str(out) + ".json").read()), records


def test_mf4_replay_has_the_same_frame_accounting_and_poses_as_the_candump_log(logs):
    root, model, frames = logs
    log_summary, log_rows = _replay(root, model, "drive.log")
    mf4_summary, mf4_rows = _replay(root, model, "drive.mf4")
    fr = mf4_summary["frames"]
    assert fr["received"] == len(frames) and fr["balanced"]
    assert fr["rejected"] > 0 and fr["error_frames"] >= 5 and fr["ignored"] > 0  # the faults are there
    assert fr == log_summary["frames"]  # every counter, per reason, per message and per signal
    assert mf4_summary["rows"] == log_summary["rows"] == len(mf4_rows) == len(log_rows)
    assert mf4_summary["steps_by_status"] == log_summary["steps_by_status"]
    t_mf4, t_log = (np.array([r["t_s"] for r in rows]) for rows in (mf4_rows, log_rows))
    np.testing.assert_allclose(t_mf4, t_log, rtol=0, atol=2e-6)  # MF4 stores times as offsets from its start
    for key in ("p_x_m", "p_y_m", "psi_rad"):
        a = np.array([np.nan if r[key] is None else r[key] for r in mf4_rows])
        b = np.array([np.nan if r[key] is None else r[key] for r in log_rows])
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4)


def test_prml2_encode_writes_mf4_that_replays_balanced(logs, tmp_path, capsys):
    root, model, _ = logs
    from prml2_edge.data.revsted import write_drive_csv

    write_drive_csv(simulate_drive(0.15, 1.0, 4), tmp_path / "d.csv")
    assert main(["encode", str(tmp_path / "d.csv"), "--out", str(tmp_path / "d.mf4"), "--gnss-seconds", "2"]) == 0
    assert main(["replay", str(tmp_path / "d.mf4"), "--model", str(model)]) == 0
    assert "balanced: yes" in capsys.readouterr().out


@pytest.mark.parametrize("fraction", [0.2, 0.6, 0.95])
def test_a_cut_off_mf4_is_a_one_line_error(logs, tmp_path, fraction):
    root, model, _ = logs
    data = (root / "drive.mf4").read_bytes()
    (tmp_path / "cut.mf4").write_bytes(data[: int(len(data) * fraction)])
    proc = subprocess.run([sys.executable, "-m", "prml2_edge.cli.main", "replay", str(tmp_path / "cut.mf4"),
                           "--model", str(model)], capture_output=True, text=True, timeout=120,
                          env={"PRML2_NO_PROGRESS": "1", "PATH": "/usr/bin:/bin"})
    err = proc.stderr.strip()
    assert proc.returncode == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "cut.mf4" in err


def test_without_asammdf_an_mf4_is_a_one_line_error_naming_the_extra(logs):
    root, model, _ = logs
    code = ("import sys; sys.modules['asammdf'] = None\n"
            "from prml2_edge.cli.main import main\n"
            f"sys.exit(main(['replay', {str(root / 'drive.mf4')!r}, '--model', {str(model)!r}]))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={"PRML2_NO_PROGRESS": "1", "PATH": "/usr/bin:/bin"})
    err = proc.stderr.strip()
    assert proc.returncode == 1 and len(err.splitlines()) == 1, err
    assert "asammdf" in err and "'.[mf4]'" in err and "drive.mf4" in err
