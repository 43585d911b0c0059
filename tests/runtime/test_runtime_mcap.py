"""MCAP out (issue 19): a replayed demo drive read back with the mcap reader, a truncated copy, a crashed run."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from collections import Counter, defaultdict

import jsonschema
import numpy as np
import pytest
import zstandard
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader
from runtime_models import make_kinematic_model

from prml2_edge.cli.main import main
from prml2_edge.runtime.localizer import StepOutput
from prml2_edge.runtime.mcap_sink import SCHEMAS, TOPICS, McapSink
from prml2_edge.runtime.status import PoseStatus

STEP_TOPICS = ("/dynamics", "/signals", "/status")  # every 50 Hz step
POSE_TOPICS = ("/pose", "/tf", "/pose/covariance")  # every step with a pose


@pytest.fixture(scope="module")
def replayed(tmp_path_factory):
    """The demo's drive (20 s, GNSS for 6 s) replayed with --mcap, --jsonl and --summary-json."""
    root = tmp_path_factory.mktemp("mcap")
    model = make_kinematic_model(root / "kinematic.onnx")
    assert main(["demo", "--seconds", "20", "--gnss-seconds", "6", "--model", str(model), "--out", str(root / "demo"),
                 "--no-plot"]) == 0
    log = root / "demo" / "demo_drive.log"
    assert main(["replay", str(log), "--model", str(model), "--mcap", str(root / "drive.mcap"),
                 "--jsonl", str(root / "pose.jsonl"), "--summary-json", str(root / "s.json")]) == 0
    records = [json.loads(line) for line in (root / "pose.jsonl").read_text().splitlines()]
    return root, model, log, records, json.loads((root / "s.json").read_text())


def _read_tolerant(path) -> tuple[list, bool]:
    """Every message the mcap stream reader gets out of ``path`` in file order, CRCs checked, up to where the file
    ends or is cut (the reader raises there: a short read, a partial record); True when it reached the footer."""
    out = []
    with open(path, "rb") as f:
        try:
            for schema, channel, message in NonSeekingReader(f, validate_crcs=True).iter_messages(
                    log_time_order=False):
                out.append((schema.name, channel.topic, message))
        except (McapError, struct.error, ValueError, zstandard.ZstdError):
            return out, False
    return out, True


def test_replayed_demo_drive_has_every_topic_with_the_step_and_fix_counts(replayed):
    root, _, _, records, summary = replayed
    steps = len(records)
    with_pose = sum(r["status"] != "INITIALISING" for r in records)
    fixes = summary["frames"]["gnss_fixes"]
    assert steps == summary["rows"] > 900 and 0.9 * steps < with_pose <= steps and fixes >= 50
    with open(root / "drive.mcap", "rb") as f:
        reader = make_reader(f)
        stats = reader.get_summary().statistics
        channels = {c.id: c.topic for c in reader.get_summary().channels.values()}
        by_topic = defaultdict(list)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema.name == TOPICS[channel.topic] and schema.encoding == "jsonschema"
            assert channel.message_encoding == "json"
            by_topic[channel.topic].append(message)
    assert set(by_topic) == set(TOPICS)  # every topic present
    counts = {t: len(m) for t, m in by_topic.items()}
    assert {channels[i]: n for i, n in stats.channel_message_counts.items()} == counts
    assert all(counts[t] == steps for t in STEP_TOPICS), counts
    assert all(counts[t] == with_pose for t in POSE_TOPICS), counts
    assert counts["/gnss/fix"] == counts["/gnss/pose"] == fixes  # every fix of the drive was valid
    for topic, messages in by_topic.items():
        times = [m.log_time for m in messages]
        assert all(b > a for a, b in zip(times, times[1:], strict=False)), topic  # strictly monotonic
        assert [m.sequence for m in messages] == list(range(1, len(messages) + 1))
    # timestamps are the CAN frame times: the 50 Hz rows' times, to the nanosecond
    assert [m.log_time for m in by_topic["/status"]] == [round(r["t_s"] * 1e9) for r in records]
    status = [json.loads(m.data) for m in by_topic["/status"]]
    assert [s["status"] for s in status] == [r["status"] for r in records]
    assert [s["guard_fired"] for s in status] == [r["guard_fired"] for r in records]
    first = json.loads(by_topic["/status"][0].data)["timestamp"]
    assert first["sec"] * 10**9 + first["nsec"] == by_topic["/status"][0].log_time


def test_messages_follow_their_json_schemas_and_agree_with_the_jsonl(replayed):
    root, _, _, records, _ = replayed
    posed = [r for r in records if r["status"] != "INITIALISING"]
    seen = Counter()
    validators = {}
    with open(root / "drive.mcap", "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            data = json.loads(message.data)
            if schema.name not in validators:
                assert json.loads(schema.data) == SCHEMAS[schema.name]
                cls = jsonschema.validators.validator_for(SCHEMAS[schema.name])
                cls.check_schema(SCHEMAS[schema.name])
                validators[schema.name] = cls(SCHEMAS[schema.name])
            i = seen[channel.topic]
            seen[channel.topic] += 1
            if i % 10 == 0 or channel.topic.startswith("/gnss"):
                validators[schema.name].validate(data)
            if channel.topic == "/pose" and i % 97 == 0:
                p = data["pose"]["position"]
                assert p["x"] == pytest.approx(posed[i]["p_x_m"], abs=1e-5)
                assert p["y"] == pytest.approx(posed[i]["p_y_m"], abs=1e-5)
                q = data["pose"]["orientation"]
                assert q["z"] ** 2 + q["w"] ** 2 == pytest.approx(1.0)
            if channel.topic == "/tf" and i == 0:
                assert (data["parent_frame_id"], data["child_frame_id"]) == ("world", "vehicle")
            if channel.topic == "/signals" and i % 101 == 0:
                assert data["valid"] == records[i]["valid"] and set(data["values"]) == set(records[i]["valid"])
            if channel.topic == "/dynamics" and records[i]["model_used"]:
                assert all(v is not None and v >= 0 for v in data["z_std"].values())


def test_a_truncated_copy_is_readable_up_to_its_last_whole_chunk(replayed, tmp_path):
    root = replayed[0]
    full, complete = _read_tolerant(root / "drive.mcap")
    assert complete
    data = (root / "drive.mcap").read_bytes()
    for fraction in (0.3, 0.7, 0.97):  # in the data section; 0.97: in the summary, after the last message
        cut = tmp_path / f"cut_{fraction}.mcap"
        cut.write_bytes(data[: int(len(data) * fraction)])
        got, complete = _read_tolerant(cut)
        assert not complete and 0 < len(got) <= len(full)
        if fraction < 0.9:
            assert len(got) < len(full)
        assert [(t, m.log_time, m.data) for _, t, m in got] == [(t, m.log_time, m.data) for _, t, m in full[:len(got)]]
        topics = {t for _, t, _ in got}
        assert set(STEP_TOPICS) | set(POSE_TOPICS) <= topics


def test_a_crashed_run_leaves_a_file_readable_up_to_its_last_chunk(replayed, tmp_path):
    """The process dies without closing the sink (no summary, no footer): all but < 1 s of steps are there."""
    _, model, log, records, _ = replayed
    path = tmp_path / "crash.mcap"
    code = (
        "import os, sys\n"
        "from prml2_edge.runtime.mcap_sink import McapSink\n"
        "from prml2_edge.runtime.pipeline import Pipeline, run_source\n"
        "from prml2_edge.runtime.source import LogReplay\n"
        f"sink = McapSink({str(path)!r})\n"
        f"pipeline = Pipeline.build(model={str(model)!r}, sinks=[sink])\n"
        f"with LogReplay({str(log)!r}) as source:\n"
        "    run_source(pipeline, source)\n"
        "print(sink.rows, flush=True)\n"
        "os._exit(3)  # a crash: no close(), no summary, no footer\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={"PRML2_NO_PROGRESS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 3, proc.stderr[-2000:]
    written = int(proc.stdout.split()[-1])
    assert written == len(records)
    got, complete = _read_tolerant(path)
    assert not complete
    status = [m for _, t, m in got if t == "/status"]
    assert written - 50 <= len(status) < written  # at most one 1 s chunk (50 steps) lost
    with open(path, "rb") as f:  # what a tool that needs the summary sees: an error, not silence
        with pytest.raises(Exception):  # noqa: B017 - the mcap library's own error for a file without a footer
            list(make_reader(f).iter_messages())


def test_mcap_to_a_folder_is_a_one_line_error(replayed, capsys, tmp_path):
    _, model, log, _, _ = replayed
    assert main(["replay", str(log), "--model", str(model), "--mcap", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(tmp_path) in err



def _out(t_s: float) -> StepOutput:
    return StepOutput(k=0, t_s=t_s, x=np.zeros(8), pos_std_m=1.0, yaw_std_rad=0.1, status=PoseStatus.DEAD_RECKONING,
                      ekf_status=None, model_used=False, inferred=False, guard_fired=np.bool_(False),
                      gnss_fused=False, gnss_outage=False, outage_s=math.nan, degraded=False, valid=np.ones(9, bool))


def test_a_clock_jump_closes_the_chunk_and_bad_times_are_counted_not_raised(tmp_path):
    sink = McapSink(tmp_path / "jump.mcap")
    for k in range(75):  # 1.5 s: one chunk closed at 101 s, one open
        sink.step(_out(100.0 + 0.02 * k))
    assert sum(t == "/status" for _, t, _ in _read_tolerant(tmp_path / "jump.mcap")[0]) == 50
    sink.step(_out(10.0))  # the CAN clock jumps back: the open chunk is closed and synced at once
    assert sum(t == "/status" for _, t, _ in _read_tolerant(tmp_path / "jump.mcap")[0]) == 75
    for bad in (math.nan, math.inf, -1.0):
        sink.step(_out(bad))
    assert sink.errors == 3 and str(tmp_path / "jump.mcap") in sink.last_error
    sink.close()
    got, complete = _read_tolerant(tmp_path / "jump.mcap")
    assert complete and sink.rows == 76 and sum(t == "/status" for _, t, _ in got) == 76
