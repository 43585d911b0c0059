"""prml2 replay / run / demo from the command line, and their one-line errors."""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from runtime_models import make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import ModelError


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    drive = simulate_drive(0.15, 1.0, 3)  # 9 s
    encode_drive_to_log(drive, root / "drive.log", gnss_seconds=2.0)
    return root, make_kinematic_model(root / "kinematic.onnx"), drive


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_replay_writes_every_sink_and_a_balanced_summary(files, capsys, tmp_path):
    root, model, drive = files
    rc = main(["replay", str(root / "drive.log"), "--model", str(model), "--jsonl", str(tmp_path / "p.jsonl"),
               "--csv", str(tmp_path / "p.csv"), "--tum", str(tmp_path / "p.tum"), "--can-out",
               str(tmp_path / "out.asc"), "--summary-json", str(tmp_path / "s.json")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "balanced: yes" in out and "end_to_end" in out and "deadline 20 ms" in out and "25-32 ms" in out
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["frames"]["balanced"] and summary["rows"] == len(drive)
    assert len((tmp_path / "p.jsonl").read_text().splitlines()) == len(drive)
    assert len(list(can.LogReader(str(tmp_path / "out.asc")))) == 3 * len(drive)


def test_replay_errors_are_one_line(files, capsys, tmp_path, shared_dir):
    root, model, _ = files
    assert main(["replay", str(tmp_path / "missing.log"), "--model", str(model)]) == 1
    assert "CAN log not found" in one_line_error(capsys)
    (tmp_path / "x.txt").write_text("hello")
    assert main(["replay", str(tmp_path / "x.txt"), "--model", str(model)]) == 1
    assert "unknown CAN log format" in one_line_error(capsys)
    assert main(["replay", str(root / "drive.log"), "--model", str(model), "--map", "vw_mqb"]) == 1
    assert "--dbc" in one_line_error(capsys)
    vw = shared_dir / "dbc" / "opendbc" / "vw_mqb.dbc"
    assert main(["replay", str(root / "drive.log"), "--model", str(model), "--map", "vw_mqb", "--dbc", str(vw)]) == 1
    assert "no GNSS fix message" in one_line_error(capsys)
    assert main(["replay", str(root / "drive.log"), "--model", str(tmp_path / "nope.onnx")]) == 1
    assert "model file not found" in one_line_error(capsys)
    assert main(["replay", str(root / "drive.log"), "--map", "no_such_map", "--model", str(model)]) == 1
    assert "unknown signal map" in one_line_error(capsys)


def test_a_broken_log_delivers_what_came_before_and_then_fails(files, capsys, tmp_path):
    root, model, _ = files
    lines = (root / "drive.log").read_text().splitlines()
    broken = tmp_path / "broken.log"
    broken.write_text("\n".join(lines[:500] + ["(1.0) vcan0 this-is-not-a-frame"] + lines[500:]) + "\n")
    assert main(["replay", str(broken), "--model", str(model)]) == 1
    assert "cannot read CAN log after 500 frames" in one_line_error(capsys)


def _send_frames(interface: str, channel: str, frames: list[can.Message], stop: threading.Event) -> None:
    with can.Bus(interface=interface, channel=channel) as bus:
        t0 = time.monotonic()
        for msg in frames:
            if stop.is_set():
                return
            delay = t0 + msg.timestamp - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            bus.send(can.Message(arbitration_id=msg.arbitration_id, is_extended_id=False, data=msg.data))


@pytest.mark.parametrize("interface", ["virtual", "socketcan"])
def test_run_live_stops_cleanly_on_sigterm(files, capsys, caplog, tmp_path, interface):
    if interface == "socketcan" and not Path("/sys/class/net/vcan0").exists():
        pytest.skip("no vcan0 here (sudo modprobe vcan; deploy/can-setup.sh vcan0)")
    caplog.set_level(logging.INFO)
    root, model, drive = files
    channel = f"prml2-live-{uuid.uuid4().hex}" if interface == "virtual" else "vcan0"
    frames = list(can.LogReader(str(root / "drive.log")))
    stop = threading.Event()
    default = signal.getsignal(signal.SIGTERM)

    def drive_the_bus() -> None:
        while signal.getsignal(signal.SIGTERM) is default and not stop.is_set():  # wait for the handler
            time.sleep(0.01)
        _send_frames(interface, channel, frames[: 450 * 6], stop)  # 6 s of traffic: the 5 s window fills
        os.kill(os.getpid(), signal.SIGTERM)

    feeder = threading.Thread(target=drive_the_bus, daemon=True)
    feeder.start()
    try:
        rc = main(["run", "--interface", interface, "--channel", channel, "--model", str(model), "--initial-pose",
                   "0,0,90", "--can-out", "--status-interval", "1", "--summary-json", str(tmp_path / "s.json"),
                   "--duration", "30", "--mcap", str(tmp_path / "live.mcap")])
    finally:
        stop.set()
        feeder.join(5)
    assert rc == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["wall_s"] < 25  # ended by SIGTERM, not by --duration
    fr = summary["frames"]
    assert fr["balanced"] and fr["used"] > 1000 and summary["rows"] > 100 and summary["model_used_steps"] > 0
    assert signal.getsignal(signal.SIGTERM) is default  # handlers restored
    from mcap.reader import make_reader

    with open(tmp_path / "live.mcap", "rb") as f:  # closed cleanly on SIGTERM: summary and footer written
        stats = make_reader(f).get_summary().statistics
    assert stats.message_count > 3 * summary["rows"]
    assert abs(stats.message_start_time / 1e9 - time.time()) < 120  # live frames: the bus's receive times
    assert f"listening on {interface}" in capsys.readouterr().out
    assert "frames/s" in caplog.text and "e2e p50/p99" in caplog.text  # the periodic status line (logging)


def test_run_live_without_frames_fails_in_one_line(files, capsys, tmp_path):
    """A live run that heard nothing did not do its job: non-zero, one line saying where it listened."""
    _, model, _ = files
    channel = f"prml2-silent-{uuid.uuid4().hex}"
    rc = main(["run", "--interface", "virtual", "--channel", channel, "--model", str(model), "--initial-pose",
               "0,0,90", "--duration", "0.3", "--status-interval", "0", "--summary-json", str(tmp_path / "s.json")])
    assert rc == 1
    err = one_line_error(capsys)
    assert f"no CAN frame arrived on virtual {channel}" in err and "interface is up" in err
    assert json.loads((tmp_path / "s.json").read_text())["frames"]["received"] == 0  # the summary is still written


def test_run_live_shorter_than_the_window_fails_like_replay(files, capsys):
    """Frames for 1 s, then the run ends: the model's 5 s window never filled, so the run exits 1 and says so."""
    root, model, _ = files
    channel = f"prml2-short-{uuid.uuid4().hex}"
    frames = list(can.LogReader(str(root / "drive.log")))[:450]  # 1 s of traffic
    stop = threading.Event()
    feeder = threading.Thread(target=lambda: (time.sleep(0.2), _send_frames("virtual", channel, frames, stop)),
                              daemon=True)
    feeder.start()
    try:
        rc = main(["run", "--interface", "virtual", "--channel", channel, "--model", str(model), "--initial-pose",
                   "0,0,90", "--duration", "1.8", "--status-interval", "0"])
    finally:
        stop.set()
        feeder.join(5)
    assert rc == 1
    err = one_line_error(capsys)
    assert "the model never ran: the run covers" in err and "less than the model's 5 s window" in err


def test_demo_with_a_given_model_prints_report_and_writes_a_plot(files, capsys, tmp_path):
    _, model, _ = files
    rc = main(["demo", "--seconds", "20", "--gnss-seconds", "6", "--model", str(model), "--out", str(tmp_path),
               "--summary-json", str(tmp_path / "s.json")])
    assert rc == 0
    out = capsys.readouterr().out
    for text in ("pose track vs ground truth", "whole outage", "end_to_end", "deadline 20 ms", "25-32 ms"):
        assert text in out
    from matplotlib.image import imread

    img = imread(tmp_path / "trajectory.png")  # matplotlib's PNG, 9 x 7 in at 100 dpi
    assert img.shape[:2] == (700, 900) and (img[..., :3] < 1.0).any()
    metrics = json.loads((tmp_path / "s.json").read_text())["metrics"]
    assert metrics["rmse_m_gnss"] < 0.3 and metrics["drift_pct"] < 5.0


def test_demo_without_the_shipped_model_is_a_one_line_error(monkeypatch, capsys, tmp_path):
    import prml2_edge.runtime.inference as inference

    def missing(*parts):
        raise ModelError("not here")

    monkeypatch.setattr(inference, "resource_path", missing)
    assert main(["demo", "--seconds", "20", "--out", str(tmp_path)]) == 1
    assert "shipped default model" in one_line_error(capsys)


def test_demo_runs_with_the_shipped_model(capsys, tmp_path):
    from prml2_edge.runtime.inference import default_model_path

    try:
        default_model_path()
    except ModelError:
        pytest.skip("no shipped model in this checkout")
    assert main(["demo", "--seconds", "15", "--gnss-seconds", "6", "--out", str(tmp_path), "--no-plot"]) == 0
    assert "preset" in capsys.readouterr().out


def test_deploy_config_with_flag_overrides(repo_root, files, tmp_path):
    import argparse

    from prml2_edge.cli.runtime_app import build_pipeline, config_from_args
    from prml2_edge.cli.runtime_args import add_pipeline_arguments

    _, model, _ = files
    parser = argparse.ArgumentParser()
    add_pipeline_arguments(parser)
    args = parser.parse_args(["--config", str(repo_root / "deploy" / "runtime.toml"), "--model", str(model),
                              "--jsonl", str(tmp_path / "p.jsonl"), "--mu", "0.4", "--initial-pose", "1,2,180",
                              "--driven-axle", "rear", "--steering-ratio", "14.5", "--threads", "2",
                              "--fixed-threads"])
    cfg = config_from_args(args)
    assert cfg.signals.mu == 0.4 and cfg.model.path == str(model) and cfg.initial_pose.source == "config"
    assert cfg.initial_pose.heading_deg == 180.0 and cfg.can.channel == "can0"  # untouched file value
    pipeline = build_pipeline(cfg)
    assert pipeline.localizer.a_max_mps2 == 5.0  # low-mu guard
    # the car's driven axle and steering ratio reach the filter and the plausibility checks
    assert (pipeline.localizer.config.driven_axle, pipeline.localizer.config.steering_ratio) == ("rear", 14.5)
    assert pipeline.plausibility.config.steering_ratio == 14.5
    assert pipeline.model.threads == 2 and pipeline.model.thread_timing_ms is None  # --fixed-threads: as asked
    assert pipeline.localizer.config.gnss_course_sideslip  # deploy/runtime.toml: [gnss] course = true
    pipeline.close()
    from dataclasses import replace

    yaw = build_pipeline(replace(cfg, gnss=replace(cfg.gnss, course=False)))  # fixes from an INS: the car's yaw
    assert not yaw.localizer.config.gnss_course_sideslip
    yaw.close()
    pinned = config_from_args(parser.parse_args(["--model", str(model)]))
    from dataclasses import replace

    pinned = replace(pinned, model=replace(pinned.model, sha256="0" * 64))
    with pytest.raises(ModelError, match="does not match the pinned"):
        build_pipeline(pinned)


def test_replay_saves_the_calibration_and_the_next_run_restores_it(files, tmp_path, capsys, caplog):
    root, model, _ = files
    cal = tmp_path / "state" / "calibration.json"
    args = ["replay", str(root / "drive.log"), "--model", str(model), "--calibration", str(cal), "--summary-json"]
    assert main(args + [str(tmp_path / "s1.json")]) == 0
    first = json.loads((tmp_path / "s1.json").read_text())["calibration"]
    assert cal.is_file() and first["saves"] >= 1 and not first["restored"] and first["error"] is None
    doc = json.loads(cal.read_text())
    assert doc["vehicle"].startswith("prml2_onboard") and len(doc["cal"]) == 3
    assert "yaw_gain" in doc  # the gyro gain's evidence is kept for the next drive
    doc["yaw_gain"].update(info=1e6, info_c=1e6 / 1.03)  # as if earlier drives had taught a 3 % gain
    assert doc["cue_offsets"]["names"][0] == "lat_accel_offset_mps2"  # so are the cues' own offsets
    cal.write_text(json.dumps(doc))
    assert main(args + [str(tmp_path / "s2.json")]) == 0
    second = json.loads((tmp_path / "s2.json").read_text())["calibration"]
    assert second["restored"] and second["yaw_rate_gain_pct"] == pytest.approx(3.0, abs=0.1)
    assert second["cue_offset"]["restored"]
    # a corrupt file: one warning line, the defaults, and the run still does its job
    cal.write_text("{")
    with caplog.at_level(logging.WARNING):
        assert main(args + [str(tmp_path / "s3.json")]) == 0
    assert sum("calibration file" in r.getMessage() for r in caplog.records) == 1
    assert json.loads(cal.read_text())["format"] == "prml2-calibration"  # rewritten at the end
    capsys.readouterr()


def test_a_calibration_file_that_cannot_be_written_is_refused_at_start(files, tmp_path, capsys):
    root, model, _ = files
    (tmp_path / "a_file").write_text("")
    rc = main(["replay", str(root / "drive.log"), "--model", str(model), "--calibration",
               str(tmp_path / "a_file" / "cal.json")])
    assert rc != 0
    assert "cannot write there" in one_line_error(capsys)
