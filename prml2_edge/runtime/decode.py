"""ID-filtered DBC decoding: one CAN frame -> canonical signal values in SI units (or a GNSS fix).

Each arbitration ID the signal map uses is resolved once at start-up into a
:class:`_MessagePlan` (the cantools message, which canonical signals it carries, their
scale/offset/sign/quality bits, counter and checksum), so :meth:`FrameDecoder.step` is a
dict lookup plus one cantools decode. Checks, in order: ID mapped (else ``IGNORED``),
data length equals the DBC's, checksum, alive counter, decode, then per value: quality bit,
finiteness, the schema's physical range. A value failing a check is dropped (counted per
signal); the frame is ``USED`` when at least one value or a GNSS fix survives. Nothing
raises on the hot path.

Injected frames (a second sender on the bus, :class:`InjectionMonitor` per message): a message
whose frames arrive faster than its declared rate (the signal map's ``rate_hz``) by
:data:`RATE_MARGIN` over the last :data:`RATE_WINDOW_S`, or whose alive counter shows two
interleaved sequences, is *injection suspected* (``DecodedFrame.injection``, the summary and the
status line name the message and ID). With a counter, the decoder then follows the ECU's sequence
(the one that was there first) and rejects the frames continuing the other as
``REJECTED_INTRUDER``; exact repeats of the previous payload (a gateway duplicating frames) are
not counted as a second sender (the counter check rejects them). The suspicion ends
:data:`CLEAR_S` after the last evidence.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import cantools

from prml2_edge import schema
from prml2_edge.can.checksum import checksum_function
from prml2_edge.can.fields import SplitField
from prml2_edge.can.signal_map import SignalMap
from prml2_edge.runtime.rows import DecodedFrame, GnssFix
from prml2_edge.runtime.status import FrameStatus

RATE_MARGIN = 1.4  # frames per RATE_WINDOW_S above this many times the declared rate: a second sender
RATE_WINDOW_S = 1.0
CLEAR_S = 2.0  # no evidence for this long: the suspicion ends


@dataclass
class InjectionMonitor:
    """Rate and counter-sequence evidence of a second sender for one message (module docstring)."""

    rate_hz: float
    times: collections.deque = field(default_factory=collections.deque)
    last_payload: bytes = b""
    prev_counter: int | None = None  # the counter before the last frame's
    primary: int | None = None  # two-track mode: head of the ECU's sequence ...
    secondary: int | None = None  # ... and of the intruder's
    evidence_t: float = -math.inf  # last time a frame showed a second sender
    since_t: float | None = None  # suspicion started
    first_t: float | None = None  # the first suspicion started
    observed_hz: float = 0.0
    intruder_frames: int = 0
    episodes: int = 0

    def __post_init__(self) -> None:
        self.max_frames = RATE_MARGIN * self.rate_hz * RATE_WINDOW_S + 1  # more in the window: a second sender

    def rate(self, t: float, payload: bytes) -> None:
        """Count a frame at ``t`` [s] (not an exact repeat of the previous payload) in the rate window."""
        if payload == self.last_payload:
            return
        self.last_payload = payload
        times = self.times
        if times and t < times[-1] - 0.25:
            times.clear()  # the clock jumped back
        times.append(t)
        while times and times[0] <= t - RATE_WINDOW_S:
            times.popleft()
        n = len(times)
        if n > self.max_frames:
            self.observed_hz = n / RATE_WINDOW_S
            self.evidence(t)

    def evidence(self, t: float) -> None:
        if self.since_t is None:
            self.since_t = t
            self.episodes += 1
            if self.first_t is None:
                self.first_t = t
        self.evidence_t = t

    def suspected(self, t: float) -> bool:
        if self.since_t is not None and t - self.evidence_t > CLEAR_S:
            self.since_t = None
            self.primary = self.secondary = None
        return self.since_t is not None


@dataclass
class _SignalPlan:
    index: int  # canonical index
    signal: str
    parts: tuple[tuple[str, float], ...] | None  # summed (signal, part scale) pairs; None: just ``signal``
    to_si: Callable[[float, int], float]  # SignalSpec.to_si, bound once
    sign: str | None
    valid: str | None
    valid_value: int
    lo: float
    hi: float


@dataclass
class _MessagePlan:
    name: str
    frame_id: int
    is_extended: bool
    length: int
    message: cantools.database.can.Message
    signals: list[_SignalPlan]
    counter: SplitField | None = None
    counter_modulus: int = 16
    checksum: SplitField | None = None
    checksum_fn: object = None
    checksum_keep: bytes = b""  # the payload bits outside the checksum (the function sees the checksum cleared)
    checksum_keep_int: int | None = None  # the same as one big-endian integer (a full frame is cleared in one AND)
    gnss: object = None  # GnssSpec when this message carries the GNSS fix
    last_counter: int | None = None
    min_length: int | None = None  # shortest payload accepted (maps with short_frames): holds every mapped bit
    injection: InjectionMonitor | None = None


class FrameDecoder:
    """Decode frames of the messages a :class:`SignalMap` names; ignore every other ID.

    Parameters
    ----------
    signal_map, db:
        A map checked against ``db`` (``load_map_and_dbc``).
    max_counter_jump:
        An alive counter may advance by 1..``max_counter_jump`` (frames lost upstream are
        noted in ``DecodedFrame.counter_gap``); 0 (a repeat) or a larger step (out of sequence,
        or a frame older than the last) rejects the frame. The decoder always resynchronises
        on the frame's counter, so one bad counter costs at most one frame.
    """

    def __init__(self, signal_map: SignalMap, db: cantools.database.can.Database, max_counter_jump: int = 7) -> None:
        self.max_counter_jump = max_counter_jump
        self.last_evidence_t = -math.inf  # newest evidence of a second sender on any message [s]
        self.plans: dict[int, _MessagePlan] = {}
        for spec in signal_map.present:
            plan = self._plan(signal_map, db, spec.message)
            sig = schema.SIGNAL_BY_NAME[spec.name]
            plan.signals.append(_SignalPlan(sig.index, spec.signal, spec.parts or None, spec.to_si, spec.sign,
                                            spec.valid, spec.valid_value, sig.min, sig.max))
        if signal_map.gnss is not None:
            self._plan(signal_map, db, signal_map.gnss.message).gnss = signal_map.gnss
        if signal_map.short_frames:
            for plan in self.plans.values():
                plan.min_length = _bytes_needed(plan, signal_map)
        rates: dict[str, float] = {}
        for spec in signal_map.present:
            rates[spec.message] = max(rates.get(spec.message, 0.0), spec.rate_hz)
        for plan in self.plans.values():
            if plan.name in rates:
                plan.injection = InjectionMonitor(rates[plan.name])

    def _plan(self, signal_map: SignalMap, db: cantools.database.can.Database, name: str) -> _MessagePlan:
        msg = db.get_message_by_name(name)
        plan = self.plans.get(msg.frame_id)
        if plan is None:
            plan = _MessagePlan(name, msg.frame_id, bool(msg.is_extended_frame), msg.length, msg, [])
            checks = signal_map.messages.get(name)
            if checks is not None:
                if checks.counter is not None:
                    plan.counter = SplitField.of(msg, checks.counter)
                    plan.counter_modulus = 1 << plan.counter.bits
                if checks.checksum is not None:
                    plan.checksum = SplitField.of(msg, checks.checksum)
                    plan.checksum_fn = checksum_function(checks.checksum_algorithm)
                    plan.checksum_keep = bytes(~b & 0xFF for b in plan.checksum.mask(msg))
                    if len(plan.checksum_keep) == plan.length:
                        plan.checksum_keep_int = int.from_bytes(plan.checksum_keep, "big")
            self.plans[msg.frame_id] = plan
        return plan

    def step(self, msg: can.Message) -> DecodedFrame:
        """Decode one frame; never raises. ``msg.timestamp`` [s] becomes ``t_s``."""
        t_s = float(msg.timestamp)
        if msg.is_error_frame:
            return DecodedFrame(FrameStatus.IGNORED, t_s, kind="error")
        if msg.is_remote_frame:
            return DecodedFrame(FrameStatus.IGNORED, t_s, kind="remote")
        plan = self.plans.get(msg.arbitration_id)
        if plan is None or msg.is_extended_id != plan.is_extended:
            return DecodedFrame(FrameStatus.IGNORED, t_s)
        data = bytes(msg.data)
        n_data = len(data)
        full = n_data == plan.length
        if not full:
            if plan.min_length is None or not plan.min_length <= n_data < plan.length:
                return DecodedFrame(FrameStatus.REJECTED_DLC, t_s, plan.name)
        try:
            payload = data if full else data + bytes(plan.length - n_data)
            decoded = plan.message.decode_simple(payload, decode_choices=False)  # no container dispatch
        except Exception:  # cantools raises several types on malformed data
            return DecodedFrame(FrameStatus.REJECTED_DECODE, t_s, plan.name)
        if plan.checksum is not None:
            try:
                if full and plan.checksum_keep_int is not None:  # the usual case: one AND, not a generator
                    cleared = (int.from_bytes(data, "big") & plan.checksum_keep_int).to_bytes(n_data, "big")
                else:  # short_frames: shorter
                    cleared = bytes(b & k for b, k in zip(data, plan.checksum_keep, strict=False))
                expected = plan.checksum_fn(plan.frame_id, cleared)  # type: ignore[operator]
            except Exception:
                return DecodedFrame(FrameStatus.REJECTED_CHECKSUM, t_s, plan.name)
            if plan.checksum.read(decoded) != expected:
                return DecodedFrame(FrameStatus.REJECTED_CHECKSUM, t_s, plan.name)
        gap = False
        mon = plan.injection
        status = FrameStatus.USED
        if mon is not None:
            mon.rate(t_s, data)
        if plan.counter is not None:
            status, gap = self._counter(plan, plan.counter.read(decoded), t_s)
        suspected = False
        if mon is not None:
            if mon.evidence_t > self.last_evidence_t:
                self.last_evidence_t = mon.evidence_t
            suspected = mon.since_t is not None and mon.suspected(t_s)  # (no suspicion: nothing to end)
        if status is not FrameStatus.USED:
            return DecodedFrame(status, t_s, plan.name, injection=suspected)
        out = DecodedFrame(FrameStatus.USED, t_s, plan.name, counter_gap=gap, injection=suspected)
        n_out_of_range = n_nonfinite = n_invalid = 0
        for sp in plan.signals:
            physical = decoded[sp.signal] if sp.parts is None else sum(decoded[p] * w for p, w in sp.parts)
            value = sp.to_si(physical, decoded[sp.sign] if sp.sign is not None else 0)
            ok = sp.valid is None or int(decoded[sp.valid]) == sp.valid_value
            if not math.isfinite(value):
                out.flagged.append((sp.index, "nonfinite"))
                n_nonfinite += 1
                continue
            if not ok:
                out.flagged.append((sp.index, "invalid_flag"))
                n_invalid += 1
            elif not (sp.lo <= value <= sp.hi):
                out.flagged.append((sp.index, "out_of_range"))
                n_out_of_range += 1
                continue
            out.index.append(sp.index)
            out.value_si.append(float(value))
            out.ok.append(ok)
        if plan.gnss is not None:
            out.gnss = _gnss(plan.gnss, decoded, t_s)
        n_good = len(out.index) - n_invalid
        if n_good == 0 and not (out.gnss is not None and out.gnss.valid):
            if n_invalid or (out.gnss is not None and not plan.signals):
                out.status = FrameStatus.REJECTED_INVALID
            elif n_out_of_range >= n_nonfinite and n_out_of_range:
                out.status = FrameStatus.REJECTED_RANGE
            elif n_nonfinite:
                out.status = FrameStatus.REJECTED_NONFINITE
        return out


    def _counter(self, plan: _MessagePlan, counter: int, t_s: float) -> tuple[FrameStatus, bool]:
        """The alive-counter check: ``(status, gap)``. Two interleaved sequences switch to following the first."""
        mod = plan.counter_modulus
        jump = min(self.max_counter_jump, mod - 2)
        mon = plan.injection
        if mon is not None and mon.since_t is not None and mon.suspected(t_s) and mon.primary is not None:
            d_p = (counter - mon.primary) % mod
            d_s = (counter - mon.secondary) % mod if mon.secondary is not None else 0
            if 1 <= d_s <= 2 and not d_p == 1:
                mon.secondary = counter
                mon.intruder_frames += 1
                mon.evidence(t_s)
                return FrameStatus.REJECTED_INTRUDER, False
            mon.primary = counter
            plan.last_counter = counter
            if d_p == 0 or d_p > jump:
                return FrameStatus.REJECTED_COUNTER, False
            return FrameStatus.USED, d_p > 1
        last, plan.last_counter = plan.last_counter, counter
        prev = None
        if mon is not None:
            prev, mon.prev_counter = mon.prev_counter, last
        if last is None:
            return FrameStatus.USED, False
        delta = (counter - last) % mod
        if delta != 1 and prev is not None and (counter - prev) % mod == 1 and delta != 0:
            # this frame continues the sequence before the last frame: the last one came from someone else
            mon.evidence(t_s)  # type: ignore[union-attr]
            mon.primary, mon.secondary = counter, last  # type: ignore[union-attr]
            return FrameStatus.USED, False
        if delta == 0 or delta > jump:
            return FrameStatus.REJECTED_COUNTER, False
        return FrameStatus.USED, delta > 1

    def injection_summary(self, t_s: float | None = None) -> dict:
        """``{message: {...}}`` for every message that was ever suspected of injection."""
        out = {}
        for plan in self.plans.values():
            mon = plan.injection
            if mon is None or not mon.episodes:
                continue
            out[plan.name] = {"id": f"{plan.frame_id:#x}", "episodes": mon.episodes,
                              "suspected_now": mon.since_t is not None if t_s is None else mon.suspected(t_s),
                              "first_s": mon.first_t, "last_evidence_s": mon.evidence_t,
                              "observed_hz": mon.observed_hz or None,
                              "declared_hz": mon.rate_hz, "intruder_frames_rejected": mon.intruder_frames}
        return out

    def suspicion_possible(self, t_s: float) -> bool:
        """Cheap: could any message be suspected of injection at ``t_s``? (evidence within ``CLEAR_S``)"""
        return t_s - self.last_evidence_t <= CLEAR_S

    def episodes(self) -> int:
        """Suspicion episodes so far, over every message."""
        return sum(p.injection.episodes for p in self.plans.values() if p.injection is not None)

    def untrusted_signals(self, t_s: float) -> dict[int, str]:
        """``{canonical index: reason}`` for signals of messages suspected of injection that have no counter to
        tell the frames apart: their values cannot be trusted at all while the suspicion lasts."""
        out = {}
        for p in self.plans.values():
            mon = p.injection
            if mon is not None and p.counter is None and mon.since_t is not None and mon.suspected(t_s):
                for sp in p.signals:
                    out[sp.index] = (f"injection suspected on {p.name} (ID {p.frame_id:#x}): "
                                     f"{mon.observed_hz:.0f} frames/s, declared {mon.rate_hz:.0f}")
        return out

    def suspected_messages(self, t_s: float) -> list[str]:
        """``"NAME (ID 0x..)"`` for every message suspected of injection at ``t_s``."""
        return [f"{p.name} (ID {p.frame_id:#x})" for p in self.plans.values()
                if p.injection is not None and p.injection.suspected(t_s)]


def _bytes_needed(plan: _MessagePlan, signal_map: SignalMap) -> int:
    """Bytes a payload must have to hold every signal the map reads from this message (and its checks)."""
    names = set()
    for sp in plan.signals:
        names |= {p for p, _ in (sp.parts or ((sp.signal, 1.0),))} | {x for x in (sp.sign, sp.valid) if x}
    names |= {n for f in (plan.counter, plan.checksum) if f is not None for n in f.names}
    g = plan.gnss
    if g is not None:
        names |= {x for x in (g.x, g.y, g.heading, g.valid) if x}
    last_byte = 0
    for name in names:
        sig = plan.message.get_signal_by_name(name)
        if sig.byte_order == "little_endian":
            end_bit = sig.start + sig.length - 1
        else:  # big endian (Motorola): start is the MSB; walk down ``length`` bits in DBC bit order
            byte, bit = divmod(sig.start, 8)
            remaining = sig.length - 1
            while remaining > bit:
                remaining -= bit + 1
                byte, bit = byte + 1, 7
            end_bit = byte * 8 + (bit - remaining)
        last_byte = max(last_byte, end_bit // 8)
    return last_byte + 1


def _gnss(spec, decoded: dict, t_s: float) -> GnssFix:
    x, y = float(decoded[spec.x]), float(decoded[spec.y])
    heading = float(decoded[spec.heading]) if spec.heading is not None else None
    valid = (spec.valid is None or int(decoded[spec.valid]) == 1) and math.isfinite(x) and math.isfinite(y)
    if heading is not None and not math.isfinite(heading):
        heading = None
    return GnssFix(t_s, x, y, heading, valid)
