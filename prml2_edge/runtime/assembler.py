"""50 Hz assembler: decoded frames -> rows of the onboard vector o_t on a fixed time grid.

Time base: frame timestamps (bus or log time), never the wall clock. The grid starts at the
first frame's timestamp, ``t_k = t_0 + k * dt_s``. Row k holds, for every signal, the newest
value with a timestamp ``<= t_k`` (zero-order hold; ``eps_s`` absorbs timestamp rounding).
A row is emitted as soon as a frame newer than ``t_k`` arrives, so a row costs no waiting.

Per signal the row carries the value's age ``t_k - t_last`` [s] and a validity flag: valid
when the signal has been received, its last quality bit was good and its age is at most
``stale_periods`` periods of the signal's rate (``rate_hz`` from the signal map).

Jitter and out-of-order frames: a value is applied only when its timestamp is not older
than the value already held for that signal; otherwise it is dropped (``stats.signal_late``).
A frame older than the last emitted row ("late") still updates the hold value when it is
newer than what is held (counted in ``stats.late_applied``); it cannot change rows already
emitted. A frame none of whose values could be applied is ``REJECTED_LATE``.

Gaps: bus silence up to ``max_gap_s`` is filled with held (stale, hence invalid) rows; a
longer gap, or a clock that jumps back by more than ``max_gap_s``, re-anchors the grid at
the new frame and flags the next row ``discontinuity`` (the localiser restarts its window).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.runtime.decode import DecodedFrame, GnssFix
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.status import FrameStatus


@dataclass
class AssembledRow:
    """One 50 Hz row of o_t.

    ``values`` (9,) SI, canonical order (never-received signals hold 0.0 and are invalid);
    ``valid`` (9,) bool; ``age_s`` (9,) seconds since the held value's frame (inf if never);
    ``gnss`` the newest GNSS fix that arrived within this row's interval;
    ``trigger_ns`` ``time.perf_counter_ns()`` when the frame that closed this row was received
    (0 when the row was flushed at the end), the start of the end-to-end latency.
    """

    k: int
    t_s: float
    values: np.ndarray
    valid: np.ndarray
    age_s: np.ndarray
    gnss: GnssFix | None = None
    discontinuity: bool = False
    trigger_ns: int = 0

    @property
    def all_valid(self) -> bool:
        return bool(self.valid.all())


class Assembler:
    """Zero-order-hold resampler onto the 50 Hz grid with per-signal age and validity.

    Parameters
    ----------
    rate_hz:
        (9,) expected rate of each canonical signal on this bus [Hz] (signal map ``rate_hz``).
    stale_periods:
        A signal older than this many of its periods is invalid (default 3; opendbc calls a
        message stale after ~10).
    dt_s:
        Grid period [s] (``schema.DT_S``).
    max_gap_s:
        Longest bus silence filled with rows; longer re-anchors the grid.
    eps_s:
        Timestamp tolerance [s] when assigning a frame to a row.
    """

    def __init__(self, rate_hz, stale_periods: float = 3.0, dt_s: float = schema.DT_S, max_gap_s: float = 5.0,
                 eps_s: float = 1e-4, stats: FrameStats | None = None) -> None:
        rate = np.asarray(rate_hz, dtype=np.float64)
        if rate.shape != (schema.NUM_SIGNALS,) or not np.all(rate > 0):
            raise ValueError(f"rate_hz must be ({schema.NUM_SIGNALS},) positive, got {rate!r}")
        if not stale_periods > 0:
            raise ValueError(f"stale_periods must be > 0, got {stale_periods!r}")
        self.stale_after_s = stale_periods / rate
        self.dt_s = float(dt_s)
        self.max_gap_s = float(max_gap_s)
        self.eps_s = float(eps_s)
        self.stats = stats if stats is not None else FrameStats()
        self.values = np.zeros(schema.NUM_SIGNALS)
        self.last_t_s = np.full(schema.NUM_SIGNALS, -math.inf)
        self.quality_ok = np.zeros(schema.NUM_SIGNALS, dtype=bool)
        self._t0: float | None = None
        self._k_next = 0  # index of the next row to emit
        self._pending_gnss: GnssFix | None = None
        self._discontinuity = False
        self.resyncs = 0
        self.rows_emitted = 0

    @classmethod
    def for_map(cls, signal_map, **kwargs) -> Assembler:
        """An assembler with the rates of ``signal_map`` (canonical order)."""
        return cls([s.rate_hz for s in signal_map.signals], **kwargs)

    def _t(self, k: int) -> float:
        return self._t0 + k * self.dt_s  # type: ignore[operator]

    @property
    def last_row_t_s(self) -> float | None:
        """Time of the last emitted row [s], None before the first."""
        return None if self._t0 is None or self._k_next == 0 else self._t(self._k_next - 1)

    def _emit(self, trigger_ns: int) -> AssembledRow:
        k = self._k_next
        t_k = self._t(k)
        age = t_k - self.last_t_s
        valid = self.quality_ok & (age <= self.stale_after_s + self.eps_s)
        row = AssembledRow(k, t_k, self.values.copy(), valid, age, self._pending_gnss, self._discontinuity,
                           trigger_ns)
        self._pending_gnss = None
        self._discontinuity = False
        self._k_next += 1
        self.rows_emitted += 1
        return row

    def step(self, frame: DecodedFrame, recv_ns: int = 0) -> tuple[FrameStatus, list[AssembledRow]]:
        """Take one decoded frame: emit the rows it closes, then apply its values.

        Returns the frame's final status (``REJECTED_LATE`` when none of its values could be
        applied, else the decoder's) and the rows emitted before it (usually 0 or 1).
        Frames the decoder ignored or rejected only advance the grid (their time is real).
        """
        t = frame.t_s
        rows: list[AssembledRow] = []
        if not math.isfinite(t):
            return (FrameStatus.REJECTED_DECODE if frame.status is FrameStatus.USED else frame.status), rows
        if self._t0 is None:
            self._t0 = t
        else:
            last_emitted = self._t(self._k_next - 1)
            if t - self._t(self._k_next) > self.max_gap_s or t < last_emitted - self.max_gap_s:
                self._reanchor(t)
            else:
                while t > self._t(self._k_next) + self.eps_s:
                    rows.append(self._emit(recv_ns))
        status = frame.status
        if status is not FrameStatus.USED and status is not FrameStatus.REJECTED_INVALID:
            return status, rows
        late = self._k_next > 0 and t <= self._t(self._k_next - 1) + self.eps_s
        applied = 0
        for i, value, ok in zip(frame.index, frame.value_si, frame.ok, strict=True):
            if t < self.last_t_s[i]:
                self.stats.signal_late[i] += 1
                continue
            self.last_t_s[i] = t
            self.quality_ok[i] = ok
            if ok:
                self.values[i] = value
                self.stats.signal_updates[i] += 1
            applied += 1
        if frame.gnss is not None:
            if self._pending_gnss is None or t >= self._pending_gnss.t_s:
                self._pending_gnss = frame.gnss
            applied += 1
        if applied == 0:
            return FrameStatus.REJECTED_LATE, rows
        if late:
            self.stats.late_applied += 1
        return status, rows

    def _reanchor(self, t: float) -> None:
        self._t0 = t
        self._k_next = 0
        self._discontinuity = True
        self.resyncs += 1
        self.last_t_s[:] = -math.inf  # everything held is stale until its signal arrives again

    def flush(self, recv_ns: int = 0) -> list[AssembledRow]:
        """At the end of a stream: emit the row that holds the last frame (if not yet emitted)."""
        if self._t0 is None:
            return []
        newest = float(np.max(self.last_t_s)) if np.isfinite(self.last_t_s).any() else self._t0
        rows = []
        while self._t(self._k_next) <= newest + self.eps_s:
            rows.append(self._emit(recv_ns))
        return rows
