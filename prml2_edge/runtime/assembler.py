"""50 Hz assembler: decoded frames -> rows of the onboard vector o_t on a fixed time grid.

Time base: frame timestamps (bus or log time), never the wall clock. The grid starts at the
first frame's timestamp, ``t_k = t_0 + k * dt_s``. Row k holds, for every signal, the newest
value with a timestamp ``<= t_k`` (zero-order hold; ``eps_s`` absorbs timestamp rounding).
A row is emitted as soon as a frame newer than ``t_k`` arrives, so a row costs no waiting.

Per signal the row carries the value's age ``t_k - t_last`` [s] and a validity flag: valid
when the signal has been received, its last quality bit was good and its age is at most
``stale_periods`` periods of the signal's rate (``rate_hz`` from the signal map).

Jitter and out-of-order frames: a value is applied only when its timestamp is not older
than the value already held for that signal; otherwise it is dropped (``DecodedFrame.late``).
A frame older than the last emitted row ("late") still updates the hold value when it is
newer than what is held (``DecodedFrame.late_applied``); it cannot change rows already
emitted. A frame none of whose values could be applied is ``REJECTED_LATE``.

Gaps: bus silence up to ``max_gap_s`` is filled with held (stale, hence invalid) rows, flagged
``bus_silent`` once no frame at all (any ID) has arrived for more than ``bus_silent_s``
(opendbc's separate bus timeout); a longer gap re-anchors the grid at the new frame and flags
the next row ``discontinuity`` (the localiser restarts its window). A clock that jumps back by
more than ``max_backstep_s`` (a logger or gateway clock reset, not jitter) re-bases the grid
and every held timestamp by the jump, so rows and ages continue without a loss
(``DecodedFrame.clock_jump``). A jump back must be confirmed by the next frame (within
``max_backstep_s`` of it): a lone frame with an old outlier timestamp is ``REJECTED_TIMESTAMP``
and moves nothing (the first frame after a real jump back is lost that way). A lone frame far in
the future re-anchors at once (after a real silence nothing else would start the grid again).

Stuck sensors (:class:`StuckCheck`): a signal whose value has not changed for ``hold_s``
while the car moves (speedometer >= ``min_speed_mps``) and a witness signal moved by more
than its span is frozen; it stays invalid until its value changes (``AssembledRow.newly_frozen``
counts the episodes). The default check is the yaw rate against the steering wheel angle and
the lateral acceleration: a turning car whose yaw rate does not move has a stuck gyro.

Substitutes: a signal the car lacks (a map's ``absent = true``) holds its constant
``substitute`` in every row, valid, age 0; a ``wheel_deceleration`` substitute is
``idle + per_mps2 * max(0, -a)`` with ``a`` the change of the rows' mean wheel speed over the
last :data:`DECEL_LAG_ROWS` rows (0 until there are that many; restarted at a re-anchor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.runtime.rows import AssembledRow, DecodedFrame, GnssFix
from prml2_edge.runtime.status import FrameStatus


@dataclass(frozen=True)
class StuckCheck:
    """A signal frozen while witnesses say the car's state changed (indices into ``schema.SIGNALS``).

    ``index`` is frozen when its value has been unchanged for ``hold_s`` [s], the speedometer
    reads at least ``min_speed_mps`` [m/s] and, since that value arrived, a witness
    ``witness[j]`` spanned at least ``span[j]`` [its SI unit].
    """

    index: int
    hold_s: float
    witness: tuple[int, ...]
    span: tuple[float, ...]
    min_speed_mps: float = 5.0


# Yaw rate held for 1 s while the steering wheel moved by 20 deg or the lateral acceleration by
# 2 m/s^2 at >= 5 m/s: each implies a yaw-rate change of several 1.28 deg/s sensor steps.
# Simulated drives (seed 3, 5, 11; up to 50 s without a yaw-rate step) stay below 0.16 rad and
# 0.45 m/s^2 while the yaw rate holds, so a healthy sensor does not trip it.
_SIG = {name: s.index for name, s in schema.SIGNAL_BY_NAME.items()}
DECEL_LAG_ROWS = 10  # wheel_deceleration substitute: speed change over 0.2 s
_SPEEDOMETER = _SIG["speedometer_mps"]
YAW_RATE_STUCK = StuckCheck(index=_SIG["yaw_rate_radps"], hold_s=1.0,
                            witness=(_SIG["steering_wheel_angle_rad"], _SIG["lat_accel_mps2"]), span=(0.35, 2.0))


def wheel_deceleration_substitute(onboard: np.ndarray, idle: float, per_mps2: float) -> np.ndarray:
    """(N,) the ``wheel_deceleration`` substitute over 50 Hz rows ``onboard`` (N, 9), as the assembler streams it."""
    v = np.asarray(onboard)[:, list(schema.WHEEL_SPEED_INDICES)].mean(axis=1)
    a = np.zeros_like(v)
    a[DECEL_LAG_ROWS:] = (v[DECEL_LAG_ROWS:] - v[:-DECEL_LAG_ROWS]) / (DECEL_LAG_ROWS * schema.DT_S)
    return idle + per_mps2 * np.clip(-a, 0.0, None)


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
    bus_silent_s:
        Rows after more than this long without any frame are flagged ``bus_silent`` [s]
        (default 3 grid periods).
    max_backstep_s:
        A frame older than the newest frame by more than this is a clock jump, not jitter [s].
    stuck_checks:
        Stuck-sensor checks (default: :data:`YAW_RATE_STUCK`; ``()`` turns them off).
    substitutes:
        ``{canonical index: SI value}`` for signals the car lacks: held in every row, always valid.
    decel_substitutes:
        ``{canonical index: (idle, per_mps2)}``: substitutes derived from the wheels' deceleration.
    """

    def __init__(self, rate_hz, stale_periods: float = 3.0, dt_s: float = schema.DT_S, max_gap_s: float = 5.0,
                 eps_s: float = 1e-4, bus_silent_s: float = 3 * schema.DT_S,
                 max_backstep_s: float = 0.25, stuck_checks: tuple[StuckCheck, ...] = (YAW_RATE_STUCK,),
                 substitutes: dict[int, float] | None = None,
                 decel_substitutes: dict[int, tuple[float, float]] | None = None) -> None:
        rate = np.asarray(rate_hz, dtype=np.float64)
        if rate.shape != (schema.NUM_SIGNALS,) or not np.all(rate > 0):
            raise ValueError(f"rate_hz must be ({schema.NUM_SIGNALS},) positive, got {rate!r}")
        if not stale_periods > 0:
            raise ValueError(f"stale_periods must be > 0, got {stale_periods!r}")
        self.stale_after_s = stale_periods / rate
        self.dt_s = float(dt_s)
        self.max_gap_s = float(max_gap_s)
        self.eps_s = float(eps_s)
        self._stale_limit_s = self.stale_after_s + self.eps_s  # a held value older than this is stale (_emit)
        self.bus_silent_s = float(bus_silent_s)
        self.max_backstep_s = float(max_backstep_s)
        self.stuck_checks = tuple(stuck_checks)
        self._stuck_since = {c.index: -math.inf for c in self.stuck_checks}  # time the held value arrived [s]
        self._stuck_lo = {c.index: np.full(len(c.witness), math.inf) for c in self.stuck_checks}
        self._stuck_hi = {c.index: np.full(len(c.witness), -math.inf) for c in self.stuck_checks}
        # signal -> the (lo, hi, position) of every witness span it widens (_track_stuck, once per value)
        self._witness_of: dict[int, list[tuple[np.ndarray, np.ndarray, int]]] = {}
        for c in self.stuck_checks:
            for j, w in enumerate(c.witness):
                self._witness_of.setdefault(w, []).append((self._stuck_lo[c.index], self._stuck_hi[c.index], j))
        self._frozen = np.zeros(schema.NUM_SIGNALS, dtype=bool)
        self.last_frame_t_s = -math.inf  # newest frame of any kind [s]
        self._jump_t_s: float | None = None  # timestamp of an unconfirmed clock jump [s]
        self.values = np.zeros(schema.NUM_SIGNALS)
        self.last_t_s = np.full(schema.NUM_SIGNALS, -math.inf)
        self.quality_ok = np.zeros(schema.NUM_SIGNALS, dtype=bool)
        self.substituted = np.zeros(schema.NUM_SIGNALS, dtype=bool)
        for index, value in (substitutes or {}).items():
            self.substituted[index] = True
            self.values[index] = float(value)
        self.decel_substitutes = dict(decel_substitutes or {})
        for index, (idle, _) in self.decel_substitutes.items():
            self.substituted[index] = True
            self.values[index] = float(idle)
        self._wheel_history: list[float] = []  # mean wheel speed of the last rows (decel substitutes)
        self._t0: float | None = None
        self._k_next = 0  # index of the next row to emit
        self._pending_gnss: GnssFix | None = None
        self._discontinuity = False
        self.resyncs = 0

    @classmethod
    def for_map(cls, signal_map, **kwargs) -> Assembler:
        """An assembler with the rates of ``signal_map`` (canonical order) and its absent signals' substitutes."""
        subs = {schema.SIGNAL_BY_NAME[s.name].index: s.substitute for s in signal_map.signals
                if s.absent and s.substitute_kind == "constant"}
        decel = {schema.SIGNAL_BY_NAME[s.name].index: (s.substitute, s.substitute_per_mps2) for s in signal_map.signals
                 if s.absent and s.substitute_kind == "wheel_deceleration"}
        return cls([s.rate_hz for s in signal_map.signals], substitutes=subs or None, decel_substitutes=decel or None,
                   **kwargs)

    def _t(self, k: int) -> float:
        return self._t0 + k * self.dt_s  # type: ignore[operator]

    @property
    def last_row_t_s(self) -> float | None:
        """Time of the last emitted row [s], None before the first."""
        return None if self._t0 is None or self._k_next == 0 else self._t(self._k_next - 1)

    def _emit(self, trigger_ns: int) -> AssembledRow:
        k = self._k_next
        t_k = self._t(k)
        if self.decel_substitutes:
            self._update_decel()
        age = t_k - self.last_t_s
        valid = self.quality_ok & (age <= self._stale_limit_s)
        if self.substituted.any():
            age[self.substituted] = 0.0
            valid |= self.substituted
        newly_frozen: tuple[int, ...] = ()
        if self.stuck_checks:
            newly_frozen = self._check_stuck(t_k)
            valid &= ~self._frozen
        silent = t_k - self.last_frame_t_s > self.bus_silent_s + self.eps_s
        row = AssembledRow(k, t_k, self.values.copy(), valid, age, self._pending_gnss, self._discontinuity,
                           trigger_ns, silent, newly_frozen)
        self._pending_gnss = None
        self._discontinuity = False
        self._k_next += 1
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
            for index in self._stuck_since:
                self._stuck_since[index] = t
        else:
            back = t < self.last_frame_t_s - self.max_backstep_s
            if back:
                candidate, self._jump_t_s = self._jump_t_s, t
                if candidate is None or abs(t - candidate) > self.max_backstep_s:
                    return FrameStatus.REJECTED_TIMESTAMP, rows  # wait for the next frame to confirm
            self._jump_t_s = None
            if back:
                self._rebase(t - self.last_frame_t_s)
                frame.clock_jump = True
            if t - (self._t0 + self._k_next * self.dt_s) > self.max_gap_s:  # (self._t, inlined: once per frame)
                self._reanchor(t)
            else:
                while t > self._t0 + self._k_next * self.dt_s + self.eps_s:
                    rows.append(self._emit(recv_ns))
        self.last_frame_t_s = max(self.last_frame_t_s, t)
        status = frame.status
        if status is not FrameStatus.USED and status is not FrameStatus.REJECTED_INVALID:
            return status, rows
        late = self._k_next > 0 and t <= self._t0 + (self._k_next - 1) * self.dt_s + self.eps_s
        applied = 0
        for i, value, ok in zip(frame.index, frame.value_si, frame.ok, strict=True):
            if t < self.last_t_s[i]:
                frame.late.append(i)
                continue
            self.last_t_s[i] = t
            self.quality_ok[i] = ok
            if ok:
                if self.stuck_checks:
                    self._track_stuck(i, value, t)
                self.values[i] = value
                frame.updated.append(i)
            applied += 1
        if frame.gnss is not None:
            if self._pending_gnss is None or t >= self._pending_gnss.t_s:
                self._pending_gnss = frame.gnss
            applied += 1
        if applied == 0:
            return FrameStatus.REJECTED_LATE, rows
        frame.late_applied = late
        return status, rows

    def _update_decel(self) -> None:
        """The wheel-deceleration substitutes for the row about to be emitted (causal: this row and older ones)."""
        hist = self._wheel_history
        hist.append(float(np.mean(self.values[list(schema.WHEEL_SPEED_INDICES)])))
        if len(hist) > DECEL_LAG_ROWS + 1:
            del hist[0]
        a = (hist[-1] - hist[0]) / (DECEL_LAG_ROWS * self.dt_s) if len(hist) == DECEL_LAG_ROWS + 1 else 0.0
        for index, (idle, gain) in self.decel_substitutes.items():
            self.values[index] = idle + gain * max(0.0, -a)

    def add_gnss(self, fix: GnssFix, recv_ns: int = 0) -> list[AssembledRow]:
        """A fix from outside the bus (NMEA, gpsd, a file of fixes), as if a GNSS frame with its time arrived:
        the rows before it are emitted, then it rides on the next row. It never starts, re-anchors or re-bases
        the grid (only CAN frames do): a fix before the first frame waits for it, one later than the bus's
        gap limit is held for the row that comes."""
        rows: list[AssembledRow] = []
        t = fix.t_s
        if not math.isfinite(t):
            return rows
        if self._t0 is not None and t - self._t(self._k_next) <= self.max_gap_s:
            while t > self._t(self._k_next) + self.eps_s:
                rows.append(self._emit(recv_ns))
        if self._pending_gnss is None or t >= self._pending_gnss.t_s:
            self._pending_gnss = fix
        return rows

    def _reanchor(self, t: float) -> None:
        self._t0 = t
        self._k_next = 0
        self._discontinuity = True
        self.resyncs += 1
        self.last_t_s[:] = -math.inf  # everything held is stale until its signal arrives again
        self.last_frame_t_s = t
        self._wheel_history.clear()
        for index in self._stuck_since:
            self._stuck_since[index] = t

    def _rebase(self, shift_s: float) -> None:
        """The clock jumped by ``shift_s`` [s] (< 0): move the grid and every held time with it."""
        self._t0 += shift_s  # type: ignore[operator]
        self.last_t_s += shift_s
        self.last_frame_t_s += shift_s
        for index in self._stuck_since:
            self._stuck_since[index] += shift_s
        if self._pending_gnss is not None:
            self._pending_gnss = None  # its time belongs to the old clock

    def _track_stuck(self, i: int, value: float, t: float) -> None:
        """Before ``values[i]`` takes ``value``: restart the hold of a checked signal, widen witness spans."""
        if i in self._stuck_since and value != self.values[i]:
            self._stuck_since[i] = t
            self._stuck_lo[i][:] = math.inf
            self._stuck_hi[i][:] = -math.inf
            self._frozen[i] = False
        for lo, hi, j in self._witness_of.get(i, ()):
            if value < lo[j]:  # (min() and max() as before: the old bound unless the value is beyond it)
                lo[j] = value
            if value > hi[j]:
                hi[j] = value

    def _check_stuck(self, t_k: float) -> tuple[int, ...]:
        """Freeze checked signals held too long while their witnesses moved; return the newly frozen ones."""
        frozen = []
        for c in self.stuck_checks:
            if self._frozen[c.index]:
                continue
            moving = self.values[_SPEEDOMETER] >= c.min_speed_mps and np.isfinite(self.last_t_s[_SPEEDOMETER])
            spans = self._stuck_hi[c.index] - self._stuck_lo[c.index]
            if moving and t_k - self._stuck_since[c.index] >= c.hold_s - self.eps_s and \
                    bool(np.any(spans >= np.asarray(c.span))):
                self._frozen[c.index] = True
                frozen.append(c.index)
        return tuple(frozen)

    @property
    def frozen(self) -> np.ndarray:
        """(9,) bool: signals a :class:`StuckCheck` currently holds frozen."""
        return self._frozen.copy()

    def max_signal_age_s(self) -> float | None:
        """Age [s] of the oldest held signal at the last emitted row (None before the first row or any value)."""
        t_row = self.last_row_t_s
        held = self.last_t_s[~self.substituted]
        if t_row is None or not np.isfinite(held).any():
            return None
        return float(np.max(t_row - held))

    def summary(self) -> dict:
        """The assembler's part of the end-of-run summary."""
        return {"grid_resyncs": self.resyncs,
                "frozen_now": [schema.SIGNAL_NAMES[i] for i in np.flatnonzero(self._frozen)]}

    def flush(self, recv_ns: int = 0) -> list[AssembledRow]:
        """At the end of a stream: emit the row that holds the last frame (if not yet emitted)."""
        if self._t0 is None:
            return []
        newest = float(np.max(self.last_t_s)) if np.isfinite(self.last_t_s).any() else self._t0
        rows = []
        while self._t(self._k_next) <= newest + self.eps_s:
            rows.append(self._emit(recv_ns))
        return rows
