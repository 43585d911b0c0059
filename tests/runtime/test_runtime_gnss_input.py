"""GNSS from where it really comes from: replay --gnss with an NMEA log, a CSV and a TUM file gives the
trajectory the same fixes give on CAN; run --gnss against a gpsd-protocol server on 127.0.0.1."""

from __future__ import annotations

import dataclasses
import json
import math
import socket
import threading
import time
import uuid

import can
import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import DataError
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.gnss_input import LocalFrame, fix_sentences, load_fixes, nmea_sentence, open_live
from prml2_edge.schema import heading_deg_to_psi_rad
from prml2_edge.tum import tum_line

T0 = 1_780_000_000.0  # the CAN log in Unix time, as a logger writes it
ORIGIN = (48.137, 11.575)


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("gnss")
    drive = simulate_drive(0.4, 1.0, 3)  # 24 s
    drive = dataclasses.replace(drive, t_s=drive.t_s + T0)
    encode_drive_to_log(drive, root / "with_fixes.log", gnss_seconds=10.0)
    encode_drive_to_log(drive, root / "no_fixes.log")
    smap, db, _ = load_map_and_dbc(shipped_map_path("prml2_onboard"))
    dec = FrameDecoder(smap, db)
    fixes = [f.gnss for f in (dec.step(m) for m in can.LogReader(str(root / "with_fixes.log"))) if f.gnss]
    assert len(fixes) == 100
    return root, fixes, make_kinematic_model(root / "kinematic.onnx")


def write_inputs(root, fixes):
    """The same fixes as an NMEA log (GGA+RMC, lat/lon about ORIGIN), a CSV and a TUM file."""
    frame = LocalFrame(ORIGIN)
    with open(root / "fixes.nmea", "w") as f:
        for fix in fixes:
            lat, lon = frame.to_geodetic(fix.x_m, fix.y_m)
            for s in fix_sentences(fix.t_s, lat, lon, fix.heading_deg, speed_mps=10.0):
                f.write(s + "\r\n")
    with open(root / "fixes.csv", "w") as f:
        f.write("t_s,x_m,y_m,heading_deg\n")
        for fix in fixes:
            f.write(f"{fix.t_s:.3f},{fix.x_m},{fix.y_m},{fix.heading_deg}\n")
    with open(root / "fixes.tum", "w") as f:
        for fix in fixes:
            f.write(tum_line(fix.t_s, fix.x_m, fix.y_m, heading_deg_to_psi_rad(fix.heading_deg)))


def read_tum(path):
    return np.loadtxt(path)


def test_nmea_sentences_are_real(logs):
    _, fixes, _ = logs
    gga, rmc = fix_sentences(T0, 48.1173, 11.5166667, 84.4, 12.0)
    assert gga.startswith("$GNGGA,") and rmc.startswith("$GNRMC,") and rmc.split(",")[2] == "A"
    import pynmea2

    assert pynmea2.parse(gga, check=True).latitude == pytest.approx(48.1173, abs=1e-9)
    # the textbook GGA of the NMEA reference, with its published checksum
    assert nmea_sentence("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == \
        "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"


@pytest.mark.parametrize("kind", ["nmea", "csv", "tum"])
def test_replay_gnss_file_equals_the_same_fixes_on_can(logs, tmp_path, kind, capsys):
    root, fixes, model = logs
    write_inputs(tmp_path, fixes)
    ref = tmp_path / "ref.tum"
    assert main(["replay", str(root / "with_fixes.log"), "--model", str(model), "--tum", str(ref)]) == 0
    got = tmp_path / "got.tum"
    extra = ["--gnss-origin", f"{ORIGIN[0]},{ORIGIN[1]}"] if kind == "nmea" else []
    assert main(["replay", str(root / "no_fixes.log"), "--model", str(model), "--tum", str(got),
                 "--gnss", str(tmp_path / f"fixes.{kind}"), "--summary-json", str(tmp_path / "s.json"), *extra]) == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["gnss_input"]["merged"] == 100 and summary["frames"]["gnss_fixes"] == 100
    a, b = read_tum(ref), read_tum(got)
    assert a.shape == b.shape and np.array_equal(a[:, 0], b[:, 0])
    err = np.hypot(a[:, 1] - b[:, 1], a[:, 2] - b[:, 2])
    # NMEA: 1e-7 arc-minute steps (0.2 mm) and the course to 0.001 deg; CSV/TUM carry the same numbers
    print(kind, "max position difference", err.max())
    assert err.max() < (0.005 if kind == "nmea" else 1e-3), err.max()
    assert np.hypot(*(a[-1, 1:3] - a[0, 1:3])) > 50.0  # it drove somewhere


def test_first_fix_origin_and_bad_files(tmp_path, logs):
    _, fixes, _ = logs
    write_inputs(tmp_path, fixes)
    first = load_fixes(tmp_path / "fixes.nmea")  # origin: the first fix
    assert (first[0].x_m, first[0].y_m) == (0.0, 0.0)
    d = np.hypot(first[-1].x_m - first[0].x_m, first[-1].y_m - first[0].y_m)
    assert d == pytest.approx(math.hypot(fixes[-1].x_m - fixes[0].x_m, fixes[-1].y_m - fixes[0].y_m), abs=0.01)
    lines = (tmp_path / "fixes.nmea").read_text().splitlines()
    (tmp_path / "gga_only.nmea").write_text("\n".join(ln for ln in lines if "GGA" in ln) + "\n")
    with pytest.raises(DataError, match="no RMC sentence with a date"):
        load_fixes(tmp_path / "gga_only.nmea")
    (tmp_path / "bad.csv").write_text("time,x,y\n1,2,3\n")
    with pytest.raises(DataError, match="lacks column"):
        load_fixes(tmp_path / "bad.csv")


def test_fixes_on_another_clock_are_refused_with_the_offset(logs, tmp_path, capsys):
    root, fixes, model = logs
    with open(tmp_path / "late.csv", "w") as f:
        f.write("t_s,x_m,y_m\n")
        for fix in fixes:
            f.write(f"{fix.t_s - T0},{fix.x_m},{fix.y_m}\n")  # drive time, not Unix time
    assert main(["replay", str(root / "no_fixes.log"), "--model", str(model), "--gnss", str(tmp_path / "late.csv")]) \
        == 1
    assert "do not overlap; shift them with --gnss-time-offset +1780000000.000" in capsys.readouterr().err


class GpsdServer:
    """A small server speaking gpsd's JSON protocol on 127.0.0.1: VERSION on connect, ?WATCH, then TPV reports."""

    def __init__(self, points, rate_hz=10.0):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.points = points
        self.rate_hz = rate_hz
        self.watched = threading.Event()
        self.sent = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        self.sock.settimeout(10.0)
        conn, _ = self.sock.accept()
        with conn:
            conn.sendall(b'{"class":"VERSION","release":"3.25","rev":"3.25","proto_major":3,"proto_minor":15}\n')
            buf = b""
            while b";" not in buf and b"\n" not in buf:
                buf += conn.recv(1024)
            assert buf.startswith(b"?WATCH=") and json.loads(buf[7:].split(b";")[0])["enable"] is True
            self.watched.set()
            conn.sendall(b'{"class":"DEVICES","devices":[{"class":"DEVICE","path":"/dev/ttyACM0"}]}\n'
                         b'{"class":"WATCH","enable":true,"json":true}\n')
            for lat, lon, track in self.points:
                if self._stop.is_set():
                    return
                tpv = {"class": "TPV", "device": "/dev/ttyACM0", "mode": 3, "time": time.strftime(
                    "%Y-%m-%dT%H:%M:%S.000Z", time.gmtime()), "lat": lat, "lon": lon, "track": track, "speed": 5.0}
                conn.sendall((json.dumps(tpv) + "\n").encode())
                self.sent += 1
                time.sleep(1.0 / self.rate_hz)

    def close(self):
        self._stop.set()
        self.thread.join(timeout=5.0)
        self.sock.close()


def test_run_with_gpsd_fuses_its_fixes(logs, tmp_path, capsys):
    root, fixes, model = logs
    frame = LocalFrame(ORIGIN)
    points = [(*frame.to_geodetic(f.x_m, f.y_m), f.heading_deg) for f in fixes[:40]]
    server = GpsdServer(points)
    channel = f"prml2-test-{uuid.uuid4().hex}"
    stop = threading.Event()

    def feed():  # the car's bus: the drive's frames on a python-can virtual channel, at 2x real time
        with can.Bus(interface="virtual", channel=channel) as bus:
            msgs = list(can.LogReader(str(root / "no_fixes.log")))
            t0, w0 = msgs[0].timestamp, time.monotonic()
            for m in msgs:
                if stop.is_set():
                    return
                delay = w0 + (m.timestamp - t0) / 2.0 - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                bus.send(can.Message(arbitration_id=m.arbitration_id, data=m.data, is_extended_id=m.is_extended_id))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        rc = main(["run", "--interface", "virtual", "--channel", channel, "--model", str(model), "--duration", "6.5",
                   "--gnss", f"gpsd://127.0.0.1:{server.port}", "--gnss-origin", f"{ORIGIN[0]},{ORIGIN[1]}",
                   "--status-interval", "0", "--summary-json", str(tmp_path / "s.json")])
    finally:
        stop.set()
        feeder.join(timeout=5.0)
        server.close()
    assert rc == 0
    assert server.watched.is_set()
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["gnss_input"]["source"] == f"gpsd://127.0.0.1:{server.port}" and s["gnss_input"]["fixes"] >= 20
    assert s["frames"]["gnss_fixes"] >= 20 and s["steps_by_status"].get("GNSS_AIDED", 0) > 0
    assert s["last"]["x_m"] is not None and s["model_used_steps"] > 0  # 6.5 s on the bus: the 5 s window filled


def test_serial_nmea_receiver_on_a_pty():
    import os

    master, slave = os.openpty()
    frame = LocalFrame(ORIGIN)
    source = open_live(os.ttyname(slave), frame).start()
    try:
        lat, lon = frame.to_geodetic(10.0, -5.0)
        deadline = time.monotonic() + 10.0
        got = []
        k = 0
        # a new epoch every 0.1 s (pyserial flushes what arrived before it opened the port); an epoch's fix
        # is complete when the next epoch begins
        while len(got) < 2 and time.monotonic() < deadline:
            os.write(master, ("\r\n".join(fix_sentences(T0 + 0.1 * k, lat, lon, 45.0, 8.0)) + "\r\n").encode())
            k += 1
            time.sleep(0.1)
            got += source.pop()
    finally:
        source.close()
        os.close(master)
        os.close(slave)
    assert len(got) >= 2 and all(f.valid and f.heading_deg == 45.0 for f in got)
    assert got[0].x_m == pytest.approx(10.0, abs=1e-3) and got[0].y_m == pytest.approx(-5.0, abs=1e-3)


def test_live_gnss_spec_errors_are_one_line(logs, capsys):
    _, _, model = logs
    assert main(["run", "--interface", "virtual", "--channel", "x", "--model", str(model), "--gnss",
                 "/dev/does-not-exist"]) == 1
    assert "serial device /dev/does-not-exist not found" in capsys.readouterr().err
    assert main(["run", "--interface", "virtual", "--channel", "x", "--model", str(model), "--gnss", "fixes.nmea"]) == 1
    assert "for a live run give gpsd://HOST[:PORT] or a serial device" in capsys.readouterr().err


def test_gnss_from_the_config_file(logs, tmp_path, capsys):
    """[gnss] file (and origin) of --config replays like --gnss FILE; a receiver the config names that is not
    there is one line naming the config key."""
    root, fixes, model = logs
    write_inputs(tmp_path, fixes)
    cfg = tmp_path / "runtime.toml"
    cfg.write_text(f'[gnss]\nfile = "{tmp_path / "fixes.nmea"}"\norigin = [{ORIGIN[0]}, {ORIGIN[1]}]\n'
                   'receiver = "/dev/prml2-no-such-receiver"\n')
    assert main(["replay", str(root / "no_fixes.log"), "--model", str(model), "--config", str(cfg),
                 "--summary-json", str(tmp_path / "s.json")]) == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["gnss_input"]["merged"] == 100 and summary["gnss_input"]["source"].endswith("fixes.nmea")
    assert "GNSS: 100 fixes from" in capsys.readouterr().out
    assert main(["run", "--interface", "virtual", "--channel", "x", "--model", str(model), "--config", str(cfg)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "prml2: error: [gnss] receiver '/dev/prml2-no-such-receiver': serial device " \
                  "/dev/prml2-no-such-receiver not found (is the receiver plugged in?)", err
