"""Encode a drive's onboard signals into a CAN log with a DBC and a signal map.

Each message named by the map is sent at its signals' ``rate_hz`` (zero-order hold of
the 50 Hz samples), with its counter incrementing modulo 2^bits, its checksum computed
by the map's ``checksum_algorithm``, validity bits set to ``valid_value`` (cleared for
a non-finite sample) and VW-style sign bits when the map has ``sign``. Optionally GNSS
fix frames (10 Hz) for the first seconds give the runtime its initial pose.

The output format follows the file extension through python-can's writers
(``can.Logger``): ``.log`` candump, ``.asc``, ``.blf``, ``.csv``, ``.trc`` (and ``.gz``
compressed variants), ``.mf4`` (ASAM MDF4, with asammdf: the ``mf4`` extra).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.can.checksum import checksum_function
from prml2_edge.can.fields import SplitField
from prml2_edge.can.signal_map import SignalSpec, load_map_and_dbc, shipped_map_path
from prml2_edge.errors import ConfigError, require_extra
from prml2_edge.progress import Progress

GNSS_RATE_HZ = 10.0
_SUPPORTED = (".log", ".asc", ".blf", ".csv", ".trc", ".mf4")  # .mf4: python-can's MF4Writer (asammdf)


@dataclass
class _MessagePlan:
    message: object  # cantools Message
    rate_hz: float
    specs: list[SignalSpec]
    counter: SplitField | None
    checksum: SplitField | None
    checksum_fn: object
    checksum_in_byte0: bool
    defaults: dict[str, float]


def _default_value(sig) -> float:
    """Value for a DBC signal the map does not feed: a 'fixed/valid' choice if any, else 0 within range."""
    if sig.choices:
        for raw, name in sig.choices.items():
            if "RTK_FIXED" in str(name).upper():
                return float(raw)
    value = float(sig.initial) if sig.initial is not None else 0.0
    lo, hi = _value_range(sig)
    return min(max(value, lo), hi)


def _raw_range(sig) -> tuple[float, float]:
    """The physical values the signal's bits can hold."""
    scale = float(sig.scale) if sig.scale else 1.0
    offset = float(sig.offset or 0.0)
    lo_raw, hi_raw = (-(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1) if sig.is_signed else \
        (0, (1 << sig.length) - 1)
    a, b = lo_raw * scale + offset, hi_raw * scale + offset
    return min(a, b), max(a, b)


def _value_range(sig) -> tuple[float, float]:
    """The DBC's [min|max] where it lies within what the bits hold, else the bits' range.

    Production DBCs carry placeholder ranges (Toyota's KINEMATICS.YAW_RATE says [0|65535] for a
    10-bit signal with offset -125): such a range is ignored instead of clipping every negative value.
    """
    lo_bits, hi_bits = _raw_range(sig)
    lo, hi = sig.minimum, sig.maximum
    if lo is None or hi is None or lo >= hi:
        return lo_bits, hi_bits
    tol = abs(float(sig.scale or 1.0))
    if lo < lo_bits - tol or hi > hi_bits + tol:
        return lo_bits, hi_bits
    return max(lo, lo_bits), min(hi, hi_bits)


def _quantise_physical(sig, value: float) -> tuple[float, bool]:
    """Clip ``value`` to the DBC signal's range and round it to its resolution; returns (value, clipped)."""
    lo, hi = _value_range(sig)
    clipped = not (lo <= value <= hi)
    value = min(max(value, lo), hi)
    scale = float(sig.scale) if sig.scale else 1.0
    offset = float(sig.offset or 0.0)
    raw = round((value - offset) / scale)
    return raw * scale + offset, clipped


def _split_parts(msg, parts: tuple[tuple[str, float], ...], value: float) -> tuple[dict[str, float], bool]:
    """Split a physical ``value`` over summed signal parts: each part takes what its resolution and range
    can hold of the remainder (Toyota: 1.5 deg steps, then the 0.1 deg fraction). Returns (values, clipped)."""
    out = {}
    rest = value
    clipped = False
    for i, (name, weight) in enumerate(parts):
        sig = msg.get_signal_by_name(name)
        want = rest / weight
        if i < len(parts) - 1:  # leave the finer parts a remainder of at most half a step
            step = abs(float(sig.scale or 1.0))
            want = math.floor(want / step + 0.5) * step
        phys, was_clipped = _quantise_physical(sig, want)
        clipped |= was_clipped and i == len(parts) - 1
        out[name] = phys
        rest -= phys * weight
    return out, clipped


def _writer_for(out_path: Path) -> can.io.generic.MessageWriter:
    suffixes = [s.lower() for s in out_path.suffixes]
    if len(suffixes) > 1 and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    ext = suffixes[-1] if suffixes else ""
    if ext not in _SUPPORTED:
        raise ConfigError(f"{out_path}: unsupported log format {ext or '(no extension)'!r}; "
                          f"use one of {', '.join(_SUPPORTED)} (optionally .gz)")
    if ext == ".mf4":  # python-can's MF4 writer needs asammdf (the mf4 extra)
        require_extra("asammdf", "mf4", f"{out_path}: an ASAM MDF4 log")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    return can.Logger(str(out_path))


def encode_drive_to_log(drive, out_path: str | Path, signal_map_path: str | Path | None = None,
                        dbc_path: str | Path | None = None, gnss_seconds: float = 0.0,
                        progress: bool = False, channel: str = "vcan0") -> dict:
    """Write ``drive``'s onboard signals as CAN frames to ``out_path``.

    Parameters
    ----------
    drive : Drive
        50 Hz onboard signals (N, 9), SI; ``pose_gt`` is needed for GNSS frames.
    out_path : str or Path
        Log file; the format follows the extension (see the module docstring).
    signal_map_path : str or Path, optional
        Signal map TOML (default: the shipped ``prml2_onboard`` map).
    dbc_path : str or Path, optional
        DBC overriding the one the map names.
    gnss_seconds : float
        Send 10 Hz GNSS fix frames (x east m, y north m, course over ground deg clockwise from north)
        for the first ``gnss_seconds`` when the map has ``[gnss]`` and the drive has ``pose_gt``.
    progress : bool
        Progress bar on stderr.
    channel : str
        Channel name written to the log.

    Returns
    -------
    dict
        ``frames`` (total), ``per_message`` counts, ``gnss_frames``, ``clipped`` (values
        outside a DBC signal's range, per signal), ``invalid`` (non-finite samples sent
        with the validity bit cleared), ``duration_s``, ``out``, ``dbc``, ``map``.
    """
    map_path = Path(signal_map_path) if signal_map_path is not None else shipped_map_path("prml2_onboard")
    smap, db, dbc_used = load_map_and_dbc(map_path, dbc_path)
    out_path = Path(out_path)
    n = len(drive.t_s)
    if n == 0:
        raise ConfigError(f"drive {drive.name!r} has no samples to encode")
    t0 = float(drive.t_s[0])
    duration_s = n * schema.DT_S

    plans = [_plan_message(smap, db, name) for name in smap.message_names]
    with_gnss = gnss_seconds > 0 and smap.gnss is not None and drive.pose_gt is not None
    events = _schedule(plans, t0, duration_s, n, min(gnss_seconds, duration_s) if with_gnss else 0.0)
    gnss_frames = 0
    gnss_msg = db.get_message_by_name(smap.gnss.message) if smap.gnss is not None else None
    course_rad = course_over_ground(drive) if with_gnss else None
    counters = [0] * len(plans)
    per_message = {p.message.name: 0 for p in plans}
    clipped: dict[str, int] = {}
    invalid: dict[str, int] = {}
    onboard_rows = np.asarray(drive.onboard, dtype=np.float64).tolist()
    bar = Progress(len(events), desc="encode", unit="frames", enabled=None if progress else False)
    writer = _writer_for(out_path)
    try:
        for i, (ts, pi, si) in enumerate(events):
            if pi < 0:
                data = _encode_gnss(gnss_msg, smap.gnss, drive.pose_gt[si], course_rad[si])
                msg = gnss_msg
                gnss_frames += 1
            else:
                plan = plans[pi]
                msg = plan.message
                data = _encode_onboard(plan, onboard_rows[si], counters[pi], clipped, invalid)
                counters[pi] += 1
                per_message[msg.name] += 1
            writer.on_message_received(can.Message(timestamp=ts, arbitration_id=msg.frame_id,
                                                   is_extended_id=msg.is_extended_frame, data=bytes(data),
                                                   channel=channel))
            if i % 2000 == 1999:
                bar.update(2000)
        bar.update(len(events) % 2000)
    finally:
        writer.stop()
        bar.close()
    return {
        "frames": len(events), "per_message": per_message, "gnss_frames": gnss_frames, "clipped": clipped,
        "invalid": invalid, "duration_s": duration_s, "out": str(out_path), "dbc": str(dbc_used),
        "map": str(map_path),
    }


def _plan_message(smap, db, msg_name: str) -> _MessagePlan:
    """How to build frames of ``msg_name``: the signals the map feeds, integrity checks, defaults for the rest."""
    specs = [s for s in smap.present if s.message == msg_name]
    message = db.get_message_by_name(msg_name)
    checks = smap.messages.get(msg_name)
    counter = SplitField.of(message, checks.counter) if checks else None
    checksum = SplitField.of(message, checks.checksum) if checks else None
    fn = checksum_function(checks.checksum_algorithm) if checks and checks.checksum_algorithm else None
    in_byte0 = False
    if checksum is not None and len(checksum.parts) == 1:
        cs = message.get_signal_by_name(checksum.names[0])
        in_byte0 = cs.start == 0 and cs.length == 8 and cs.byte_order == "little_endian"
    fed = {p for s in specs for p, _ in s.summed_parts} | {s.valid for s in specs if s.valid} | \
        {s.sign for s in specs if s.sign}
    fed |= set(checks.signal_names) if checks else set()
    defaults = {sig.name: _default_value(sig) for sig in message.signals if sig.name not in fed}
    return _MessagePlan(message, max(s.rate_hz for s in specs), specs, counter, checksum, fn, in_byte0, defaults)


def _schedule(plans: list[_MessagePlan], t0: float, duration_s: float, n: int,
              gnss_s: float) -> list[tuple[float, int, int]]:
    """Every frame to send, in time order: ``(timestamp, plan index or -1 for GNSS, sample index)``.

    GNSS fixes go out at :data:`GNSS_RATE_HZ` for the first ``gnss_s`` seconds (none when 0).
    """
    events: list[tuple[float, int, int]] = []
    for pi, plan in enumerate(plans):
        events.extend(_ticks(t0, duration_s, plan.rate_hz, n, pi))
    if gnss_s > 0:
        events.extend(_ticks(t0, gnss_s, GNSS_RATE_HZ, n, -1))
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def _ticks(t0: float, duration_s: float, rate_hz: float, n: int, pi: int) -> list[tuple[float, int, int]]:
    """Send events ``(timestamp, pi, sample index)`` at ``rate_hz`` over ``duration_s`` from ``t0``.

    Each event carries the newest 50 Hz sample at its time (clamped to the drive's ``n`` samples).
    """
    k = np.arange(int(math.floor(duration_s * rate_hz - 1e-9)) + 1)
    t_rel = k / rate_hz
    idx = np.minimum((t_rel / schema.DT_S + 1e-6).astype(np.int64), n - 1)
    return list(zip((t0 + t_rel).tolist(), [pi] * len(k), idx.tolist(), strict=True))


def _encode_onboard(plan: _MessagePlan, row: list[float], count: int, clipped: dict[str, int],
                    invalid: dict[str, int]) -> bytearray:
    """One frame of ``plan.message`` from the onboard sample ``row`` (SI); ``count`` is its alive counter.

    Non-finite values are sent as 0 with the validity bit cleared (counted in ``invalid``), values
    outside a DBC signal's range are clipped (counted in ``clipped``); the checksum is computed last.
    """
    msg = plan.message
    values = dict(plan.defaults)
    for spec in plan.specs:
        v_si = row[schema.SIGNAL_BY_NAME[spec.name].index]
        finite = math.isfinite(v_si)
        if not finite:
            invalid[spec.name] = invalid.get(spec.name, 0) + 1
            v_si = 0.0
        phys, sign_bit = spec.from_si(v_si)
        if spec.parts:
            part_values, was_clipped = _split_parts(msg, spec.parts, phys)
            values.update(part_values)
        else:
            phys, was_clipped = _quantise_physical(msg.get_signal_by_name(spec.signal), phys)
            values[spec.signal] = phys
        if was_clipped:
            clipped[spec.name] = clipped.get(spec.name, 0) + 1
        if spec.sign:
            values[spec.sign] = sign_bit
        if spec.valid:
            values[spec.valid] = spec.valid_value if finite else 1 - spec.valid_value
    if plan.counter:
        plan.counter.write(values, count % (1 << plan.counter.bits))
    if plan.checksum:
        plan.checksum.write(values, 0)
    data = bytearray(msg.encode(values, scaling=True, strict=False))
    if plan.checksum and plan.checksum_fn is not None:
        crc = plan.checksum_fn(msg.frame_id, bytes(data))
        if plan.checksum_in_byte0:
            data[0] = crc
        else:
            plan.checksum.write(values, crc)
            data = bytearray(msg.encode(values, scaling=True, strict=False))
    return data


def course_over_ground(drive) -> np.ndarray:
    """The direction of travel per row [rad, the EKF's convention]: ``psi + atan2(v_y, v_x)`` where the drive has
    ``z_gt`` and moves (a receiver's course; below 0.5 m/s and without ``z_gt``, the yaw)."""
    psi = np.asarray(drive.pose_gt[:, 2], dtype=np.float64)
    z = getattr(drive, "z_gt", None)
    if z is None:
        return psi
    vx, vy = z[:, schema.Z.V_X], z[:, schema.Z.V_Y]
    moving = np.isfinite(vx) & np.isfinite(vy) & (np.hypot(vx, vy) >= 0.5)
    return np.where(moving, schema.course_over_ground(psi, np.where(moving, vx, 1.0), np.where(moving, vy, 0.0)), psi)


def _encode_gnss(msg, gnss, pose_row: np.ndarray, course_rad: float) -> bytes:
    """GNSS fix frame: x east [m], y north [m], course over ground clockwise from north [deg, 0-360) (what a
    receiver on the bus sends: the direction of travel, not the car's yaw)."""
    values = {sig.name: _default_value(sig) for sig in msg.signals}
    x_m, y_m = float(pose_row[0]), float(pose_row[1])
    values[gnss.x], _ = _quantise_physical(msg.get_signal_by_name(gnss.x), x_m)
    values[gnss.y], _ = _quantise_physical(msg.get_signal_by_name(gnss.y), y_m)
    if gnss.heading:
        heading = schema.psi_rad_to_heading_deg(float(course_rad))
        values[gnss.heading], _ = _quantise_physical(msg.get_signal_by_name(gnss.heading), heading)
    if gnss.valid:
        values[gnss.valid] = 1
    return msg.encode(values, scaling=True, strict=False)
