"""Assembler: 50 Hz zero-order hold with per-signal age and validity; jitter, late frames, gaps."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.rows import DecodedFrame, GnssFix
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.status import FrameStatus

RATES = [50.0] * schema.NUM_SIGNALS


def upd(t_s: float, values: dict[int, float], ok: bool = True) -> DecodedFrame:
    return DecodedFrame(FrameStatus.USED, t_s, "M", list(values), list(values.values()), [ok] * len(values))


def all_signals(t_s: float, v: float) -> DecodedFrame:
    return upd(t_s, dict.fromkeys(range(schema.NUM_SIGNALS), v))


def feed(asm: Assembler, frames):
    rows = []
    for f in frames:
        rows += asm.step(f)[1]
    return rows


def test_rows_on_the_grid_hold_the_newest_value_and_tolerate_jitter(rng):
    asm = Assembler(RATES)
    times = np.arange(0, 101) * schema.DT_S
    jitter = rng.uniform(-0.004, 0.004, times.size)
    jitter[0] = 0.0
    rows = feed(asm, [all_signals(float(t + j), float(k)) for k, (t, j) in enumerate(zip(times, jitter, strict=True))])
    rows += asm.flush()
    ts = np.array([r.t_s for r in rows])
    np.testing.assert_allclose(np.diff(ts), schema.DT_S)
    for r in rows:  # row k holds the newest frame with t <= t_k
        newest = max(k for k, (t, j) in enumerate(zip(times, jitter, strict=True)) if t + j <= r.t_s + 1e-4)
        assert r.values[0] == newest
        assert r.all_valid


def test_signal_turns_invalid_after_stale_periods():
    asm = Assembler([25.0] + [50.0] * 8, stale_periods=3.0)  # speedometer 25 Hz: stale after 120 ms
    frames = [upd(0.0, dict.fromkeys(range(schema.NUM_SIGNALS), 1.0))]
    frames += [upd(k * 0.02, {i: 1.0 for i in range(1, schema.NUM_SIGNALS)}) for k in range(1, 12)]
    rows = feed(asm, frames)
    age = np.array([r.age_s[0] for r in rows])
    valid = np.array([r.valid[0] for r in rows])
    np.testing.assert_allclose(age, np.arange(len(rows)) * 0.02, atol=1e-9)
    assert valid[age <= 0.12 + 1e-9].all() and not valid[age > 0.12 + 1e-9].any()
    assert all(r.valid[1:].all() for r in rows)


def test_quality_bit_invalidates_at_once_and_never_received_is_invalid():
    asm = Assembler(RATES)
    rows = feed(asm, [upd(0.0, {0: 5.0}), upd(0.02, {0: 6.0}, ok=False), upd(0.04, {0: 7.0}), upd(0.06, {})])
    assert [bool(r.valid[0]) for r in rows] == [True, False, True]
    assert [r.values[0] for r in rows] == [5.0, 5.0, 7.0]  # an invalid value is not held
    assert not any(r.valid[1] for r in rows) and rows[0].age_s[1] == np.inf


def test_out_of_order_frames_apply_only_when_newer_than_the_held_value():
    stats = FrameStats()
    asm = Assembler(RATES)
    for f in [upd(0.0, {0: 1.0, 1: 1.0}), upd(0.03, {0: 3.0}), upd(0.041, {2: 0.0})]:  # rows at 0, 0.02, 0.04
        stats.add_frame(asm.step(f)[0], f)
    late = upd(0.025, {0: 2.5, 1: 2.5})  # late: older than the row at 0.04
    st, rows = asm.step(late)
    stats.add_frame(st, late)
    assert st is FrameStatus.USED and rows == []  # signal 1 was older, so it is applied
    assert stats.late_applied == 1 and stats.signal_late[0] == 1
    st, _ = asm.step(upd(0.01, {0: 9.0}))  # older than everything held for signal 0
    assert st is FrameStatus.REJECTED_LATE
    rows = asm.step(all_signals(0.07, 0.0))[1]
    assert rows[0].values[0] == 3.0 and rows[0].values[1] == 2.5


def test_gaps_are_filled_with_stale_rows_and_long_gaps_reanchor():
    asm = Assembler(RATES, max_gap_s=1.0)
    feed(asm, [all_signals(0.0, 1.0)])
    rows = asm.step(all_signals(0.5, 2.0))[1]
    assert len(rows) == 25 and not rows[-1].valid.any() and rows[-1].values[0] == 1.0
    st, rows = asm.step(all_signals(100.0, 3.0))  # bus silent for 99.5 s
    assert rows == [] and asm.resyncs == 1
    rows = asm.step(all_signals(100.02, 4.0))[1]
    assert len(rows) == 1 and rows[0].discontinuity and rows[0].t_s == pytest.approx(100.0)
    assert rows[0].valid.all()


def test_gnss_fix_travels_with_the_row_of_its_interval():
    asm = Assembler(RATES)
    fix = GnssFix(0.03, 1.0, 2.0, 45.0, True)
    frames = [all_signals(0.0, 0.0), all_signals(0.02, 0.0),
              DecodedFrame(FrameStatus.USED, 0.03, "GNSS", gnss=fix), all_signals(0.04, 0.0), all_signals(0.06, 0.0)]
    rows = feed(asm, frames)
    assert [r.gnss for r in rows] == [None, None, fix]


def test_ignored_frames_advance_the_grid_and_keep_their_status():
    asm = Assembler(RATES)
    asm.step(all_signals(0.0, 1.0))
    st, rows = asm.step(DecodedFrame(FrameStatus.IGNORED, 0.05))
    assert st is FrameStatus.IGNORED and [r.t_s for r in rows] == pytest.approx([0.0, 0.02, 0.04])
