"""Fault injection over the replay path: one scenario each, status flags, error bounds, frame accounting.

A 24 s simulated drive (GNSS for the first 4 s, then dead reckoning) is encoded with the project
DBC; each scenario rewrites its frames with :mod:`prml2_edge.testing.faults`, writes a candump log
and replays it through ``LogReplay`` (python-can virtual bus) -> ``Pipeline``. Timing is checked in
50 Hz frame periods (``DT``): a signal's validity flag and the degraded flag change within 3
periods of a fault's start and end (a frozen value can only be recognised after the hold time).
"""

from __future__ import annotations

from dataclasses import dataclass

import can
import numpy as np
import pytest
from runtime_models import ListSink, make_kinematic_model

from prml2_edge import schema
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_dbc
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.resources import project_dbc_path
from prml2_edge.runtime.assembler import YAW_RATE_STUCK
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.pipeline import Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.testing.faults import Fault, InjectionCounts, inject

DT = schema.DT_S
GNSS_S = 4.0
T0, T1 = 9.0, 11.0  # default fault interval [s]
YAW, SW, WFL, WFR = 2, 1, 5, 6  # canonical signal indices
FROZEN = (14.0, 17.0)  # seed 12 turns here: the steering wheel moves > 0.5 rad within 1.5 s


@dataclass
class Run:
    pipeline: Pipeline
    outs: list
    counts: InjectionCounts
    frames_written: int

    @property
    def t(self) -> np.ndarray:
        return np.array([o.t_s for o in self.outs])

    def valid(self, i: int) -> np.ndarray:
        return np.array([bool(o.valid[i]) for o in self.outs])

    @property
    def degraded(self) -> np.ndarray:
        return np.array([o.degraded for o in self.outs])

    @property
    def xy(self) -> np.ndarray:
        return np.array([o.x[:2] for o in self.outs])

    @property
    def pos_std(self) -> np.ndarray:
        return np.array([o.pos_std_m for o in self.outs])


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("faults")
    drive = simulate_drive(0.4, 1.0, 12)  # 24 s
    log = root / "clean.log"
    encode_drive_to_log(drive, log, gnss_seconds=GNSS_S)
    frames = list(can.LogReader(str(log)))
    model = OnnxModel(make_kinematic_model(root / "kinematic.onnx"))
    db = load_dbc(project_dbc_path())
    return root, drive, frames, model, db


def run_faults(setup, faults: list[Fault], name: str, model=None, **build) -> Run:
    root, _, frames, default_model, db = setup
    counts = InjectionCounts()
    path = root / f"{name}.log"
    n = 0
    with can.Logger(str(path)) as writer:
        for msg in inject(frames, faults, db, seed=3, counts=counts):
            writer.on_message_received(msg)
            n += 1
    sink = ListSink()
    pipeline = Pipeline.build(model=model or default_model, sinks=[sink], **build)
    with LogReplay(path) as source:
        run_source(pipeline, source)
    pipeline.close()
    assert source.error is None and source.received == n
    return Run(pipeline, sink.outs, counts, n)


@pytest.fixture(scope="module")
def clean(setup):
    return run_faults(setup, [], "clean")


def check_common(run: Run, drive) -> None:
    """Every frame counted once; the runtime kept going; the pose is finite once initialised."""
    st = run.pipeline.stats
    assert st.received == run.frames_written and st.balanced(), st.as_dict()
    assert [o.k for o in run.outs] == list(range(len(run.outs)))  # no row lost
    assert run.outs[-1].t_s == pytest.approx(drive.t_s[-1], abs=1e-6)
    started = [o for o in run.outs if o.status is not PoseStatus.INITIALISING]
    assert len(started) >= len(run.outs) - 2
    assert all(np.isfinite(o.x).all() and np.isfinite(o.pos_std_m) for o in started)


def first_t(run: Run, mask: np.ndarray, after: float) -> float:
    idx = np.flatnonzero(mask & (run.t >= after - 1e-9))
    assert idx.size, f"never after {after} s"
    return float(run.t[idx[0]])


def check_flag_window(run: Run, flag: np.ndarray, t0: float, t1: float, periods: float = 3) -> None:
    """``flag`` is off before ``t0``, on within ``periods`` frame periods of ``t0`` until ``t1``, and off
    again within ``periods`` frame periods of ``t1`` (to the end of the drive)."""
    t = run.t
    tol = 1e-6
    assert not flag[(t > GNSS_S) & (t < t0)].any()
    assert first_t(run, flag, t0) <= t0 + periods * DT + tol
    on = first_t(run, flag, t0)
    assert flag[(t >= on) & (t < t1)].all()
    back = first_t(run, ~flag, t1)
    assert back <= t1 + periods * DT + tol
    assert not flag[t >= back].any()


def check_predicts_smoothly(run: Run, t0: float, t1: float) -> None:
    """While degraded, the covariance grows and the pose moves by no more than the car could."""
    t = run.t
    seg = (t >= t0 + 3 * DT) & (t < t1)
    std = run.pos_std[seg]
    assert np.all(np.diff(std) > 0) and std[-1] > std[0]
    step = np.hypot(*np.diff(run.xy[seg], axis=0).T)
    assert step.max() < 30.0 * DT  # never faster than 30 m/s (the guard's speed limit)


def deviation_from_clean(run: Run, clean: Run) -> np.ndarray:
    n = min(len(run.outs), len(clean.outs))
    return np.hypot(*(run.xy[:n] - clean.xy[:n]).T)


def test_clean_replay_is_the_reference(setup, clean):
    drive = setup[1]
    check_common(clean, drive)
    assert not clean.degraded[clean.t > 0.1].any()
    err = np.hypot(*(clean.xy - drive.pose_gt[:, :2]).T)
    assert err.max() < 6.0  # the closed-form test model, 20 s of dead reckoning over ~400 m (3.9 m here)


def test_wheel_speed_message_absent_for_2_s_then_back(setup, clean):
    run = run_faults(setup, [Fault("drop_message", T0, T1, message="WHEEL_SPEEDS_FRONT")], "drop")
    check_common(run, setup[1])
    for i in (WFL, WFR):
        check_flag_window(run, ~run.valid(i), T0, T1)
    assert run.valid(YAW)[run.t > 0.1].all()
    check_flag_window(run, run.degraded, T0, T1)
    assert all(run.outs[k].status is PoseStatus.DEGRADED for k in np.flatnonzero(run.degraded))
    check_predicts_smoothly(run, T0, T1)
    assert run.counts.dropped["drop_message"] == 200  # 2 s at 100 Hz
    assert run.outs[-1].model_used  # the model is back once the invalid rows left its window
    # 2 s predict-only at ~20 m/s, then ~4 s until the invalid rows leave the model's window
    assert deviation_from_clean(run, clean).max() < 15.0


def test_yaw_rate_frozen_at_one_value_is_flagged_after_the_hold_time(setup, clean):
    drive = setup[1]
    t0, t1 = FROZEN
    frozen_deg_s = float(np.degrees(drive.onboard[int(t0 / DT) - 1, YAW]))
    frozen_deg_s = round(frozen_deg_s, 2)  # the DBC's resolution, so the value is exactly representable
    run = run_faults(setup, [Fault("freeze_signal", t0, t1, message="ESP_YAW_LAT", signal="YAW_RATE",
                                   value=frozen_deg_s)], "frozen")
    check_common(run, drive)
    bad = ~run.valid(YAW)
    assert not bad[(run.t > GNSS_S) & (run.t < t0 + YAW_RATE_STUCK.hold_s - DT)].any()
    on = first_t(run, bad, t0)
    assert on <= t0 + 1.5 + 3 * DT  # held 1 s, and the steering moved enough within 1.5 s
    assert bad[(run.t >= on) & (run.t < t1)].all() and run.degraded[(run.t >= on) & (run.t < t1)].all()
    assert first_t(run, ~bad, t1) <= t1 + 3 * DT  # the value moves again: valid at once
    assert run.pipeline.stats.signal_frozen[YAW] == 1
    assert clean.pipeline.stats.signal_frozen[YAW] == 0 and clean.valid(YAW)[clean.t > 0.1].all()
    check_predicts_smoothly(run, on, t1)


def test_random_frame_burst_is_counted_and_does_not_move_the_pose(setup, clean):
    run = run_faults(setup, [Fault("random_burst", T0, T0 + 0.5, count=3000)], "burst")
    check_common(run, setup[1])
    st = run.pipeline.stats
    assert run.counts.added["random_burst"] == 3000
    assert st.received == clean.pipeline.stats.received + 3000
    assert st.error_frames > 0 and st.remote_frames > 0 and st.by_status[2] > 0  # error, remote, wrong DLC
    assert st.ignored >= st.error_frames + st.remote_frames
    # random GNSS_FIX frames (no checksum): refused by the innovation gate or as contradicting the odometry
    assert run.pipeline.localizer.n_gnss_rejected + run.pipeline.localizer.filter.n_gnss_suspect > 0
    assert deviation_from_clean(run, clean).max() < 0.5


def test_known_ids_with_the_wrong_dlc_are_rejected_one_for_one(setup):
    rng = np.random.default_rng(5)
    _, _, frames, model, db = setup
    pipeline = Pipeline.build(model=model)
    for msg in frames[:4000]:
        pipeline.step(msg)
    ids = [m.frame_id for m in db.messages if m.frame_id < 0x600]
    before = pipeline.stats.by_status[2]
    for k in range(500):
        dlc = int(rng.choice([0, 1, 2, 3, 4, 5, 6, 7]))
        pipeline.step(can.Message(timestamp=frames[3999].timestamp + 1e-4 * k, arbitration_id=int(rng.choice(ids)),
                                  is_extended_id=False, data=rng.integers(0, 256, dlc, dtype=np.uint8).tobytes()))
    assert pipeline.stats.by_status[2] - before == 500 and pipeline.stats.balanced()


@pytest.mark.parametrize("checks", [True, False])
def test_checksum_failures_reject_frames_when_the_map_enables_the_check(setup, clean, tmp_path, checks,
                                                                       repo_root):
    build = {}
    if not checks:  # the same map without [messages.*] integrity checks
        text = (repo_root / "dbc" / "maps" / "prml2_onboard.toml").read_text()
        text = text.split("# Integrity checks per message")[0] + "[gnss]" + text.split("[gnss]")[1]
        text = text.replace('dbc = "prml2_onboard.dbc"', f'dbc = "{repo_root / "dbc" / "prml2_onboard.dbc"}"')
        (tmp_path / "nochecks.toml").write_text(text)
        build["map"] = str(tmp_path / "nochecks.toml")
    run = run_faults(setup, [Fault("checksum", T0, T0 + 1.0, message="WHEEL_SPEEDS_FRONT")], f"crc{checks}",
                     **build)
    check_common(run, setup[1])
    edited = run.counts.edited["checksum"]
    assert edited == 100
    rejected = run.pipeline.stats.rejected_by_reason()
    if checks:
        assert rejected == {"checksum": edited}
        for i in (WFL, WFR):
            check_flag_window(run, ~run.valid(i), T0, T0 + 1.0)
        check_predicts_smoothly(run, T0, T0 + 1.0)
    else:  # unchecked: the (undamaged) values are used
        assert rejected == {} and not run.degraded[run.t > 0.1].any()
        assert deviation_from_clean(run, clean).max() < 1e-9


def test_duplicated_frames_fail_the_counter_check_and_change_nothing(setup, clean):
    run = run_faults(setup, [Fault("duplicate", T0, T0 + 1.0)], "dup")
    check_common(run, setup[1])
    dup = run.counts.added["duplicate"]
    assert dup > 400 and run.pipeline.stats.rejected_by_reason() == {"counter": dup}
    assert not run.degraded[run.t > 0.1].any()
    assert deviation_from_clean(run, clean).max() < 1e-9


def test_error_frames_are_counted_and_ignored(setup, clean):
    run = run_faults(setup, [Fault("error_frames", T0, T0 + 0.2, count=200)], "errors")
    check_common(run, setup[1])
    st = run.pipeline.stats
    assert st.error_frames == 200 and st.ignored == 200
    assert not run.degraded[run.t > 0.1].any()
    assert deviation_from_clean(run, clean).max() < 1e-9


def test_the_whole_bus_silent_for_1_s(setup, clean):
    run = run_faults(setup, [Fault("bus_silent", T0, T0 + 1.0)], "silent")
    check_common(run, setup[1])
    assert len(run.outs) == len(clean.outs)  # the silence is filled with (stale) rows
    silent = np.array([o.bus_silent for o in run.outs])
    check_flag_window(run, silent, T0, T0 + 1.0)
    check_flag_window(run, run.degraded, T0, T0 + 1.0)
    for i in range(schema.NUM_SIGNALS):
        assert not run.valid(i)[(run.t >= T0 + 0.2) & (run.t < T0 + 1.0)].any()
    check_predicts_smoothly(run, T0, T0 + 1.0)
    assert not any(o.bus_silent for o in clean.outs)
    assert run.pipeline.bus_silent_rows == int(silent.sum())


def test_timestamps_jumping_backwards_and_forwards(setup, clean):
    run = run_faults(setup, [Fault("time_shift", T0, T1, value=-0.5)], "clock")
    check_common_rows = run.pipeline.stats
    assert check_common_rows.balanced() and check_common_rows.received == run.frames_written
    assert check_common_rows.clock_jumps == 1
    # nothing dropped as "late" after the jump back; its first frame waits for the next to confirm the jump
    assert check_common_rows.rejected_by_reason() == {"timestamp": 1}
    assert [o.k for o in run.outs] == list(range(len(run.outs)))
    assert len(run.outs) == len(clean.outs) + 25  # the forward jump of 0.5 s: 25 stale rows
    k_back = int(T0 / DT)
    assert not any(o.degraded for o in run.outs[k_back - 5: k_back + 95])  # jump back: ages carried over
    forward = [o.degraded for o in run.outs[k_back + 100: k_back + 130]]  # the 0.5 s forward gap
    assert sum(forward) >= 22 and not run.outs[-1].degraded
    assert all(np.isfinite(o.x).all() for o in run.outs[1:])
    assert run.pipeline.assembler.resyncs == 0


def test_decoded_value_outside_the_schema_range(setup, clean):
    run = run_faults(setup, [Fault("out_of_range", T0, T0 + 1.0, message="ESP_YAW_LAT", signal="YAW_RATE",
                                   value=200.0)], "range")  # 200 deg/s > 2.5 rad/s
    check_common(run, setup[1])
    st = run.pipeline.stats
    assert st.signal_out_of_range[YAW] == run.counts.edited["out_of_range"] == 50
    assert st.rejected == 0  # the frame's lateral acceleration is still used
    check_flag_window(run, ~run.valid(YAW), T0, T0 + 1.0)
    check_flag_window(run, run.degraded, T0, T0 + 1.0)
    check_predicts_smoothly(run, T0, T0 + 1.0)


class _FlakySession:
    """An onnxruntime session whose outputs are NaN on calls ``[start, stop)``."""

    def __init__(self, session, start: int, stop: int) -> None:
        self.session, self.start, self.stop, self.calls = session, start, stop, 0

    def run(self, names, feeds):
        out = self.session.run(names, feeds)
        self.calls += 1
        if self.start <= self.calls - 1 < self.stop:
            out = [np.full_like(out[0], np.nan), out[1]]
        return out


def test_non_finite_model_output_means_predict_only_then_recovery(setup, clean, tmp_path):
    model = OnnxModel(make_kinematic_model(tmp_path / "k.onnx"))
    first = schema.WINDOW_LEN - 1  # row of the first inference
    k0, k1 = int(T0 / DT), int(T0 / DT) + 50
    model.session = _FlakySession(model.session, k0 - first, k1 - first)
    run = run_faults(setup, [], "nanmodel", model=model, stride=1)  # one session call per row: call i is row first + i
    check_common(run, setup[1])
    used = np.array([o.model_used for o in run.outs])
    status = np.array([o.status for o in run.outs])
    assert not used[k0:k1].any() and (status[k0:k1] == PoseStatus.PREDICT_ONLY).all()
    assert used[k1:].all() and used[first + 1:k0].all()  # back at the next good inference
    assert run.pipeline.localizer.n_inference_failures == 50 and model.n_invalid == 50
    std = run.pos_std[k0:k1]
    assert np.all(np.diff(std) > 0)
    assert deviation_from_clean(run, clean).max() < 2.0


class _BusOffBus:
    """A python-can bus that goes bus-off (recv raises) for a while, then delivers frames again."""

    def __init__(self, frames: list, fail_from: int, fail_count: int) -> None:
        self.frames, self.i, self.fail_from, self.fail_left = list(frames), 0, fail_from, fail_count

    def recv(self, timeout=None):
        if self.i == self.fail_from and self.fail_left > 0:
            self.fail_left -= 1
            raise can.CanOperationError("bus-off")
        if self.i >= len(self.frames):
            return None
        self.i += 1
        return self.frames[self.i - 1]

    def shutdown(self) -> None:
        pass


def test_bus_off_errors_are_counted_and_the_loop_keeps_going(setup):
    from prml2_edge.runtime.source import BusSource

    _, drive, frames, model, _ = setup
    bus = _BusOffBus(frames[:4000], fail_from=2000, fail_count=5)
    source = BusSource(bus)
    sink = ListSink()
    pipeline = Pipeline.build(model=model, sinks=[sink])
    run_source(pipeline, source, should_stop=lambda: bus.i >= 4000, timeout_s=0.001)
    assert source.errors == 5 and "bus-off" in source.last_error
    assert source.received == 4000 and pipeline.stats.received == 4000 and pipeline.stats.balanced()
    assert np.isfinite(sink.outs[-1].x).all() and sink.outs[-1].t_s > 9.0
