"""Fault injection on a CAN frame stream, for the reliability tests and the soak benchmark.

Each :class:`Fault` is active on ``[t_start_s, t_end_s)`` of *frame time* and rewrites the
stream as a car's bus can: drop a message (sensor or ECU lost), freeze a signal at one value
(stuck sensor; counter and checksum stay right), corrupt checksums, repeat counters
(duplicated frames), shift timestamps (logger clock jumps), insert error frames or a burst
of random frames (electrical noise, a hostile node), silence the whole bus, or send a value
outside the schema's physical range. :func:`inject` applies a list of faults lazily, so an
hour-long log never has to be held in memory, and counts what it did in
:class:`InjectionCounts`.

Frames are ``can.Message``; payload edits re-encode with the DBC and recompute the
``prml2_crc8`` checksum, so an edited frame is a well-formed frame with a wrong *value*.
This module only builds test input; the runtime never imports it.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import can
import cantools
import numpy as np

from prml2_edge.can.checksum import checksum_function

KINDS = ("drop_message", "freeze_signal", "checksum", "duplicate", "time_shift", "error_frames", "random_burst",
         "bus_silent", "out_of_range")
# plausible lies (the reliability benchmark): values a healthy-looking sensor or a second sender could send
LIES = ("offset", "scale", "stuck", "intruder", "gnss_walk")


@dataclass(frozen=True)
class Fault:
    """One fault on frame time ``[t_start_s, t_end_s)`` [s].

    ``kind`` (one of :data:`KINDS`): ``drop_message`` (frames of ``message`` removed),
    ``freeze_signal`` (``signal`` of ``message`` held at ``value``, physical DBC units),
    ``checksum`` (byte 0 of ``message`` frames flipped), ``duplicate`` (every frame sent twice),
    ``time_shift`` (timestamps shifted by ``value`` seconds, negative = backwards),
    ``error_frames`` (``count`` error frames at ``t_start_s``), ``random_burst`` (``count``
    random frames over the interval), ``bus_silent`` (every frame removed), ``out_of_range``
    (``signal`` of ``message`` set to ``value``, physical DBC units).

    Plausible lies (:data:`LIES`): ``offset`` (``signal`` of ``message`` plus ``value``, physical DBC
    units), ``scale`` (times ``value``), ``stuck`` (held at the value of its first frame in the
    interval; a dropout to zero is ``freeze_signal`` with ``value`` 0), ``intruder`` (a second
    sender: every frame of ``message`` is followed, half a period later, by the frame of that message
    sent ``value`` seconds earlier, replayed as it was: its own counter and checksum), ``gnss_walk``
    (the ``GNSS_FIX`` position walks away linearly to ``value`` metres at ``t_end_s`` in the direction
    ``count`` degrees clockwise from north, and stays there).
    """

    kind: str
    t_start_s: float
    t_end_s: float
    message: str | None = None
    signal: str | None = None
    value: float = 0.0
    count: int = 0

    def __post_init__(self) -> None:
        if self.kind not in KINDS + LIES:
            raise ValueError(f"unknown fault kind {self.kind!r}; known: {', '.join(KINDS + LIES)}")
        if not self.t_end_s >= self.t_start_s:
            raise ValueError(f"fault {self.kind}: t_end_s {self.t_end_s} < t_start_s {self.t_start_s}")

    def active(self, t_s: float) -> bool:
        return self.t_start_s <= t_s < self.t_end_s


@dataclass
class InjectionCounts:
    """What :func:`inject` did, per fault kind: frames dropped, edited and added."""

    dropped: dict[str, int] = field(default_factory=dict)
    edited: dict[str, int] = field(default_factory=dict)
    added: dict[str, int] = field(default_factory=dict)
    frames_out: int = 0

    def _add(self, table: dict[str, int], kind: str, n: int = 1) -> None:
        table[kind] = table.get(kind, 0) + n

    def as_dict(self) -> dict:
        return {"dropped": dict(self.dropped), "edited": dict(self.edited), "added": dict(self.added),
                "frames_out": self.frames_out}


class _Recoder:
    """Re-encode project-DBC frames with one signal changed and a correct ``prml2_crc8`` checksum."""

    def __init__(self, db: cantools.database.can.Database) -> None:
        self.db = db
        self.crc = checksum_function("prml2_crc8")

    def get(self, msg: can.Message, signal: str) -> float:
        m = self.db.get_message_by_frame_id(msg.arbitration_id)
        return float(m.decode(bytes(msg.data), decode_choices=False)[signal])

    def set(self, msg: can.Message, signal: str, value: float, **more: float) -> can.Message:
        m = self.db.get_message_by_frame_id(msg.arbitration_id)
        values = m.decode(bytes(msg.data), decode_choices=False)
        values[signal] = value
        values.update(more)
        data = bytearray(m.encode(values, scaling=True, strict=False))
        if any(s.name == "CHECKSUM" for s in m.signals):
            data[0] = self.crc(m.frame_id, bytes(data))
        return _copy(msg, data=bytes(data))


def _copy(msg: can.Message, **changes) -> can.Message:
    fields = {"timestamp": msg.timestamp, "arbitration_id": msg.arbitration_id, "is_extended_id": msg.is_extended_id,
              "is_remote_frame": msg.is_remote_frame, "is_error_frame": msg.is_error_frame, "channel": msg.channel,
              "dlc": None, "data": bytes(msg.data), "is_fd": msg.is_fd, "is_rx": msg.is_rx}
    fields.update(changes)
    if fields["dlc"] is None:
        fields.pop("dlc")
    return can.Message(**fields)


def random_frame(rng: np.random.Generator, t_s: float, known_ids: list[int]) -> can.Message:
    """One hostile frame: a random or a known ID, random DLC (also wrong for the ID) and payload.

    One in eight is an error frame and one in sixteen a remote frame; IDs are extended one time
    in eight. Timestamps are ``t_s`` [s].
    """
    r = rng.random()
    if r < 0.125:
        return can.Message(timestamp=t_s, is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True,
                           data=bytes(8), channel="vcan0")
    extended = rng.random() < 0.125
    if rng.random() < 0.5 and known_ids:
        arb = int(rng.choice(known_ids))
        extended = False
    else:
        arb = int(rng.integers(0, 1 << 29 if extended else 1 << 11))
    dlc = int(rng.integers(0, 9))
    if r < 0.1875:
        return can.Message(timestamp=t_s, arbitration_id=arb, is_extended_id=extended, is_remote_frame=True,
                           dlc=dlc, channel="vcan0")
    data = rng.integers(0, 256, dlc, dtype=np.uint8).tobytes()
    return can.Message(timestamp=t_s, arbitration_id=arb, is_extended_id=extended, data=data, channel="vcan0")


def inject(frames: Iterable[can.Message], faults: list[Fault], db: cantools.database.can.Database,
           seed: int = 0, counts: InjectionCounts | None = None) -> Iterator[can.Message]:
    """Apply ``faults`` to ``frames`` (in time order); yields the faulty stream lazily.

    Counts go to ``counts`` (pass one to read them afterwards). Random frames use ``seed``.
    """
    rng = np.random.default_rng(seed)
    counts = counts if counts is not None else InjectionCounts()
    recoder = _Recoder(db)
    ids = {m.name: m.frame_id for m in db.messages}
    queue = _one_shot_frames(faults, rng, sorted(ids.values()), counts)
    stuck_at: dict[int, float] = {}  # fault index -> the value a stuck signal holds
    intruders = _Intruders(faults, ids)
    for msg in frames:
        t = float(msg.timestamp)
        out: list[can.Message] = []
        while queue and queue[-1].timestamp <= t:
            out.append(queue.pop())
        msg, copies = _apply_faults(msg, t, faults, ids, recoder, counts, stuck_at)
        out.extend([msg] * copies)
        if copies > 1:
            counts._add(counts.added, "duplicate", copies - 1)
        out += intruders.frames_after(msg, t, counts)
        counts.frames_out += len(out)
        yield from out


def _one_shot_frames(faults: list[Fault], rng: np.random.Generator, known_ids: list[int],
                     counts: InjectionCounts) -> list[can.Message]:
    """The frames the one-shot insertions add (error frames, random bursts), each at its own time; newest first,
    so that ``pop()`` takes the oldest."""
    queue: list[can.Message] = []
    for f in faults:
        if f.kind in ("error_frames", "random_burst"):
            span = max(f.t_end_s - f.t_start_s, 0.0)
            for j in range(f.count):
                t_j = f.t_start_s + span * j / max(f.count, 1)
                queue.append(can.Message(timestamp=t_j, is_error_frame=True, arbitration_id=0x20000004,
                                         is_extended_id=True, data=bytes(8), channel="vcan0")
                             if f.kind == "error_frames" else random_frame(rng, t_j, known_ids))
            counts._add(counts.added, f.kind, f.count)
    queue.sort(key=lambda m: m.timestamp, reverse=True)
    return queue


def _apply_faults(msg: can.Message, t: float, faults: list[Fault], ids: dict[str, int], recoder: _Recoder,
                  counts: InjectionCounts, stuck_at: dict[int, float]) -> tuple[can.Message, int]:
    """The faults active at ``t`` applied to one frame, in order: (the frame as edited, how many times it is sent:
    0 when a fault drops it, 2 while ``duplicate`` is active)."""
    copies = 1
    for f in faults:
        if not f.active(t) or f.kind in ("error_frames", "random_burst"):
            continue
        if f.kind == "bus_silent" or (f.kind == "drop_message" and msg.arbitration_id == ids.get(f.message)):
            counts._add(counts.dropped, f.kind)
            return msg, 0
        if f.kind in ("freeze_signal", "out_of_range") and msg.arbitration_id == ids.get(f.message):
            msg = recoder.set(msg, f.signal, f.value)  # type: ignore[arg-type]
            counts._add(counts.edited, f.kind)
        elif f.kind == "checksum" and msg.arbitration_id == ids.get(f.message) and len(msg.data) > 0:
            data = bytearray(msg.data)
            data[0] ^= 0x5A
            msg = _copy(msg, data=bytes(data))
            counts._add(counts.edited, f.kind)
        elif f.kind == "time_shift":
            msg = _copy(msg, timestamp=msg.timestamp + f.value)
            counts._add(counts.edited, f.kind)
        elif f.kind == "duplicate":
            copies = 2
        elif f.kind in ("offset", "scale", "stuck") and msg.arbitration_id == ids.get(f.message):
            fi = faults.index(f)
            now = recoder.get(msg, f.signal)  # type: ignore[arg-type]
            value = now + f.value if f.kind == "offset" else now * f.value if f.kind == "scale" else \
                stuck_at.setdefault(fi, now)
            msg = recoder.set(msg, f.signal, value)  # type: ignore[arg-type]
            counts._add(counts.edited, f.kind)
        elif f.kind == "gnss_walk" and msg.arbitration_id == ids.get("GNSS_FIX"):
            frac = min((t - f.t_start_s) / max(f.t_end_s - f.t_start_s, 1e-9), 1.0)
            d = f.value * frac
            az = np.radians(f.count)
            x, y = recoder.get(msg, "GNSS_POS_X"), recoder.get(msg, "GNSS_POS_Y")
            msg = recoder.set(msg, "GNSS_POS_X", x + d * np.sin(az), GNSS_POS_Y=y + d * np.cos(az))
            counts._add(counts.edited, f.kind)
    return msg, copies


class _Intruders:
    """The ``intruder`` faults: a second sender replaying a message's frames from ``value`` s ago."""

    def __init__(self, faults: list[Fault], ids: dict[str, int]) -> None:
        self.faults = faults
        self.ids = ids
        self.recorded: dict[int, list[can.Message]] = {}  # fault index -> frames of its message, to replay
        self.period: dict[int, float] = {}
        self.last_t: dict[int, float] = {}

    def frames_after(self, msg: can.Message, t: float, counts: InjectionCounts) -> list[can.Message]:
        """Record ``msg`` (sent or dropped) for the intruders on its message; the replayed frames that follow it."""
        out = []
        for fi, f in enumerate(self.faults):
            if f.kind != "intruder" or msg.arbitration_id != self.ids.get(f.message):
                continue
            rec = self.recorded.setdefault(fi, [])
            rec.append(msg)
            if msg.arbitration_id in self.last_t:
                self.period[fi] = t - self.last_t[msg.arbitration_id]
            self.last_t[msg.arbitration_id] = t
            replay = None
            while rec and rec[0].timestamp <= t - f.value:
                replay = rec.pop(0)  # the newest frame at least f.value s old, once each
            if f.active(t) and replay is not None:
                out.append(_copy(replay, timestamp=t + 0.5 * self.period.get(fi, 0.0)))
                counts._add(counts.added, f.kind)
        return out


def fault_schedule(duration_s: float, period_s: float = 60.0, start_s: float = 20.0, lies: bool = False) -> list[Fault]:
    """A rotating schedule over ``duration_s`` [s]: one fault every ``period_s``, cycling through :data:`KINDS`
    (and, with ``lies``, plausible lies too).

    Used by the soak benchmark: wheel speeds absent 2 s, yaw rate frozen 3 s while the car
    turns, front wheel checksums broken 1 s, every frame duplicated 1 s, timestamps 0.5 s
    backwards for 2 s, 50 error frames, 500 random frames over 0.5 s, bus silent 1 s, yaw rate
    out of range 1 s; with ``lies``: yaw rate +3 deg/s for 5 s, steering stuck 5 s, front-left wheel
    x1.1 for 5 s, a second sender replaying the rear wheel speeds of 20 s before for 3 s.
    """
    kinds = KINDS + (("offset", "stuck", "scale", "intruder") if lies else ())
    plan = []
    t = start_s
    i = 0
    while t + 5.0 < duration_s:
        kind = kinds[i % len(kinds)]
        plan.append({
            "drop_message": Fault("drop_message", t, t + 2.0, message="WHEEL_SPEEDS_FRONT"),
            "freeze_signal": Fault("freeze_signal", t, t + 3.0, message="ESP_YAW_LAT", signal="YAW_RATE", value=5.0),
            "checksum": Fault("checksum", t, t + 1.0, message="WHEEL_SPEEDS_FRONT"),
            "duplicate": Fault("duplicate", t, t + 1.0),
            "time_shift": Fault("time_shift", t, t + 2.0, value=-0.5),
            "error_frames": Fault("error_frames", t, t + 0.2, count=50),
            "random_burst": Fault("random_burst", t, t + 0.5, count=500),
            "bus_silent": Fault("bus_silent", t, t + 1.0),
            "out_of_range": Fault("out_of_range", t, t + 1.0, message="ESP_YAW_LAT", signal="YAW_RATE", value=200.0),
            "offset": Fault("offset", t, t + 5.0, message="ESP_YAW_LAT", signal="YAW_RATE", value=3.0),
            "stuck": Fault("stuck", t, t + 5.0, message="STEERING_ANGLE", signal="STEERING_WHEEL_ANGLE"),
            "scale": Fault("scale", t, t + 5.0, message="WHEEL_SPEEDS_FRONT", signal="WHEEL_SPEED_FL", value=1.1),
            "intruder": Fault("intruder", t, t + 3.0, message="WHEEL_SPEEDS_REAR", value=20.0),
        }[kind])
        t += period_s
        i += 1
    return plan
