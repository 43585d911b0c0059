"""The runtime never fails silently: a signal the bus does not carry is named at start-up, and a
replay in which the model never ran exits non-zero with the reason."""

from __future__ import annotations

import logging

import pytest
from runtime_models import make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.testing.map_mistakes import drop_message


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("silent")
    drive = simulate_drive(0.2, 1.0, 3)  # 12 s
    encode_drive_to_log(drive, root / "drive.log", gnss_seconds=2.0)
    drop_message(root / "drive.log", root / "no_yaw.log", 0x130)  # ESP_YAW_LAT never on the bus
    return root, make_kinematic_model(root / "kinematic.onnx")


def test_replay_with_a_signal_absent_exits_non_zero_naming_it(files, capsys, caplog):
    root, model = files
    with caplog.at_level(logging.WARNING):
        rc = main(["replay", str(root / "no_yaw.log"), "--model", str(model)])
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "the model never ran" in err, err
    assert "yaw_rate_radps (ESP_YAW_LAT.YAW_RATE, ID 0x130): no frame of that message is on this bus" in err
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(w.startswith("no value of yaw_rate_radps (ESP_YAW_LAT.YAW_RATE, ID 0x130)") for w in warnings)
    assert any("lat_accel_mps2" in w for w in warnings) and not any("wheel_speed" in w for w in warnings)


def test_clean_replay_warns_about_nothing(files, caplog):
    root, model = files
    with caplog.at_level(logging.WARNING):
        assert main(["replay", str(root / "drive.log"), "--model", str(model)]) == 0
    assert not [r for r in caplog.records if r.getMessage().startswith("no value of")]


def test_a_log_shorter_than_the_window_says_so(files, tmp_path, capsys):
    root, model = files
    drive = simulate_drive(0.05, 1.0, 4)  # 3 s < the 5 s window
    encode_drive_to_log(drive, tmp_path / "short.log", gnss_seconds=1.0)
    assert main(["replay", str(tmp_path / "short.log"), "--model", str(model)]) == 1
    assert "less than the model's 5 s window" in capsys.readouterr().err


def test_a_log_of_another_bus_says_no_frame_is_for_the_map(files, tmp_path, capsys):
    """Frames of IDs the map does not read (the wrong bus, the wrong map): named as such, not as a short log."""
    root, model = files
    lines = [f"({100.0 + 0.01 * i:.6f}) vcan0 7F0#0011223344556677" for i in range(600)]  # 6 s of one foreign ID
    (tmp_path / "other.log").write_text("\n".join(lines) + "\n")
    assert main(["replay", str(tmp_path / "other.log"), "--model", str(model)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "none of the 600 frames of the log is a message map prml2_onboard reads" in err, err
