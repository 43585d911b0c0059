"""Sinks: JSON lines, CSV, TUM and the PRML2_* CAN messages, checked by reading them back."""

from __future__ import annotations

import csv
import json
import math

import can
import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.can.signal_map import load_dbc
from prml2_edge.ekf.numpy_ekf import StepStatus
from prml2_edge.resources import project_dbc_path
from prml2_edge.runtime.localizer import StepOutput
from prml2_edge.runtime.sinks import CSV_COLUMNS, CanSink, CsvSink, JsonlSink, TumSink
from prml2_edge.runtime.status import PoseStatus


def output(k: int, status=PoseStatus.DEAD_RECKONING) -> StepOutput:
    x = np.array([10.0 + k, -5.0, math.radians(100.0), 0.2, 12.0, -0.3, 0.5, 2.4])
    if status is PoseStatus.INITIALISING:
        x[:] = np.nan
    valid = np.ones(schema.NUM_SIGNALS, dtype=bool)
    valid[4] = False
    return StepOutput(k, 0.02 * k, x, 1.25, math.radians(3.0), status, StepStatus.SUCCESS, True, True, False,
                      False, True, 12.5, True, valid)


def test_file_sinks_write_what_they_are_given(tmp_path):
    sinks = [JsonlSink(tmp_path / "p.jsonl"), CsvSink(tmp_path / "p.csv"), TumSink(tmp_path / "p.tum")]
    outs = [output(0, PoseStatus.INITIALISING), output(1), output(2)]
    for out in outs:
        for s in sinks:
            s.step(out)
    for s in sinks:
        s.close()
    rows = [json.loads(line) for line in (tmp_path / "p.jsonl").read_text().splitlines()]
    assert len(rows) == 3 and rows[0]["p_x_m"] is None and rows[0]["status"] == "INITIALISING"
    assert rows[2]["p_x_m"] == 12.0 and rows[2]["status"] == "DEAD_RECKONING" and rows[2]["gnss_outage"]
    assert rows[2]["valid"]["brake_pressure_bar"] is False and rows[2]["valid"]["yaw_rate_radps"] is True
    with open(tmp_path / "p.csv") as f:
        table = list(csv.DictReader(f))
    assert list(table[0]) == CSV_COLUMNS and len(table) == 3
    assert table[0]["p_x_m"] == "" and float(table[1]["v_x_mps"]) == 12.0
    assert table[1]["valid_brake_pressure_bar"] == "0" and table[1]["valid_yaw_rate_radps"] == "1"
    tum = [line.split() for line in (tmp_path / "p.tum").read_text().splitlines()]
    assert len(tum) == 2 and len(tum[0]) == 8  # initialising step skipped
    qz, qw = float(tum[0][6]), float(tum[0][7])
    assert 2 * math.atan2(qz, qw) == pytest.approx(math.radians(100.0), abs=1e-6)


def test_can_sink_frames_decode_with_the_project_dbc(tmp_path):
    db = load_dbc(project_dbc_path())
    path = tmp_path / "out.log"
    sink = CanSink(can.Logger(str(path)), db)
    for k in range(3):
        sink.step(output(k))
    sink.step(output(3, PoseStatus.INITIALISING))
    sink.close()
    frames = list(can.LogReader(str(path)))
    assert len(frames) == 9 and sink.errors == 0
    by_name = {}
    for f in frames:
        by_name.setdefault(db.get_message_by_frame_id(f.arbitration_id).name, []).append(
            db.decode_message(f.arbitration_id, f.data, decode_choices=False))
    pose = by_name["PRML2_POSE"][2]
    assert pose["POSE_X"] == pytest.approx(12.0) and pose["POSE_Y"] == pytest.approx(-5.0)
    assert pose["POSE_HEADING"] == pytest.approx(100.0, abs=0.05) and pose["POSE_STATUS"] == 2
    dyn = by_name["PRML2_DYNAMICS"][0]
    assert dyn["DYN_V_X"] == pytest.approx(12.0) and dyn["DYN_YAW_RATE"] == pytest.approx(0.2)
    std = by_name["PRML2_POSE_STD"]
    assert [m["COUNTER"] for m in std] == [0, 1, 2] and std[0]["OUTAGE_TIME"] == pytest.approx(12.5)


def test_can_sink_clips_out_of_range_values_and_counts_send_failures():
    sent = []

    class Bus:
        def send(self, msg):
            sent.append(msg)
            if len(sent) > 3:
                raise can.CanOperationError("bus off")

    sink = CanSink(Bus())
    out = output(0)
    out.x[4] = 500.0  # beyond DYN_V_X's range: clipped, not an encode error
    sink.step(out)
    sink.step(out)
    assert sink.frames == 3 and sink.errors == 1 and "bus off" in sink.last_error
