"""``prml2 doctor --log LOG``: check a signal map and DBC against one recorded drive of the car.

The log is read through the runtime's own decoder and 50 Hz assembler (the same checks the
runtime applies), then reported per canonical signal: frames of its message, measured rate
against the map's ``rate_hz``, range, resolution and validity; every mapped signal never seen
(naming message and ID); and the physics checks of :mod:`prml2_edge.data.signal_checks` (signs and
scales), each failure with the signal to blame and the fix for the map.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.can.signal_map import SignalMap, load_map_and_dbc, resolve_map
from prml2_edge.data.signal_checks import FAIL, PASS, SKIP, WARN, Finding, check_onboard, snap_factor
from prml2_edge.errors import DataError, first_line
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.source import check_log, truncation_problem
from prml2_edge.runtime.status import FrameStatus

RATE_TOL = 0.2  # measured rate within +-20 % of the declared one
MIN_VALID_SHARE = 0.95


@dataclass
class SignalReport:
    """What the log says about one canonical signal."""

    name: str
    result: str  # PASS | WARN | FAIL
    message: str = ""
    frame_id: int | None = None
    frames: int = 0  # frames of its message
    used: int = 0  # values taken from them
    rate_hz: float | None = None  # measured
    declared_hz: float | None = None
    min: float | None = None
    max: float | None = None
    resolution: float | None = None  # smallest step between distinct values [SI]
    valid_share: float | None = None  # share of 50 Hz rows in which it was valid
    problems: list[str] = field(default_factory=list)
    fix: str = ""


@dataclass
class LogReport:
    log: str
    map: str
    dbc: str
    frames: int
    duration_s: float
    signals: list[SignalReport]
    physics: list[Finding]
    problem: str | None = None  # the log is damaged (checked up to the damage)

    @property
    def ok(self) -> bool:
        return self.problem is None and not any(s.result == FAIL for s in self.signals) and \
            not any(f.result == FAIL for f in self.physics)

    def as_dict(self) -> dict:
        return {"ok": self.ok, "log": self.log, "map": self.map, "dbc": self.dbc, "frames": self.frames,
                "duration_s": self.duration_s, "problem": self.problem,
                "signals": [asdict(s) for s in self.signals], "physics": [f.as_dict() for f in self.physics]}


def _scale_fix(spec, factor: float) -> str:
    """The map line that applies ``factor`` to ``spec``'s scale."""
    factor, hint = snap_factor(factor) if factor != -1.0 else (factor, "")
    new = spec.scale * factor
    return f"set scale = {new:.10g} in [signals.{spec.name}]" + (f" ({hint})" if hint else "")


def _resolution(values: np.ndarray) -> float | None:
    u = np.unique(values)
    if len(u) < 2:
        return None
    d = np.diff(u)
    d = d[d > 1e-12]
    return float(np.min(d)) if len(d) else None


def check_log_file(log: str | Path, map_name: str | Path = "prml2_onboard", dbc: str | Path | None = None,
                   max_frames: int | None = None) -> LogReport:
    """Read ``log`` through ``map_name``/``dbc`` and check every canonical signal and the physics between them."""
    path = check_log(log)
    smap, db, dbc_path = load_map_and_dbc(resolve_map(map_name), dbc)
    decoder = FrameDecoder(smap, db)
    assembler = Assembler.for_map(smap)
    by_id = {fid: plan.name for fid, plan in decoder.plans.items()}
    times: dict[str, list[float]] = {plan.name: [] for plan in decoder.plans.values()}
    rejected: dict[str, dict[str, int]] = {}
    values: list[list[float]] = [[] for _ in range(schema.NUM_SIGNALS)]
    rows_v, rows_ok = [], []
    n = 0
    t_first = t_last = 0.0
    problem = None
    try:
        with can.LogReader(str(path)) as reader:
            for msg in reader:
                if n == 0:
                    t_first = msg.timestamp
                t_last = msg.timestamp
                n += 1
                name = by_id.get(msg.arbitration_id)
                frame = decoder.step(msg)
                if name is not None and not msg.is_error_frame and not msg.is_remote_frame:
                    times[name].append(msg.timestamp)
                    if frame.status.is_rejected:
                        reason = frame.status.name.removeprefix("REJECTED_").lower()
                        rejected.setdefault(name, {})[reason] = rejected.get(name, {}).get(reason, 0) + 1
                for i, v, ok in zip(frame.index, frame.value_si, frame.ok, strict=True):
                    if ok and frame.status is FrameStatus.USED:
                        values[i].append(v)
                _, rows = assembler.step(frame)
                for row in rows:
                    rows_v.append(row.values)
                    rows_ok.append(row.valid)
                if max_frames is not None and n >= max_frames:
                    break
    except Exception as exc:  # a damaged log: report what came before the damage
        problem = f"{path}: cannot read CAN log after {n} frames ({first_line(exc, 200)})"
    if problem is None:
        cut = truncation_problem(path)
        if cut is not None:
            problem = f"{path}: CAN log cut short after {n} frames ({cut})"
    if n == 0:
        raise DataError(problem or f"{path}: CAN log holds no frames")
    for row in assembler.flush():
        rows_v.append(row.values)
        rows_ok.append(row.valid)
    duration = max(t_last - t_first, 1e-9)
    onboard = np.asarray(rows_v).reshape(-1, schema.NUM_SIGNALS)
    valid = np.asarray(rows_ok, dtype=bool).reshape(-1, schema.NUM_SIGNALS)

    reports = [_signal_report(smap, spec, times, rejected, values, valid, duration, decoder)
               for spec in smap.signals]
    present = tuple(not s.absent and bool(values[i]) for i, s in enumerate(smap.signals))
    physics = check_onboard(onboard, valid, present) if len(onboard) else []
    by_name = {s.name: s for s in smap.signals}
    physics = [_with_map_fix(f, by_name[f.signal]) for f in physics]
    return LogReport(str(path), smap.name, str(dbc_path), n, duration, reports, physics, problem)


def _with_map_fix(f: Finding, spec) -> Finding:
    if f.result != FAIL or f.scale_factor is None:
        return f
    return Finding(f.check, f.signal, f.result, f.detail, _scale_fix(spec, f.scale_factor), f.scale_factor, f.r,
                   f.gain)


def _signal_report(smap: SignalMap, spec, times, rejected, values, valid, duration, decoder) -> SignalReport:
    i = schema.SIGNAL_BY_NAME[spec.name].index
    if spec.absent:
        unit = schema.SIGNALS[i].unit
        fed = (f"{spec.substitute:g} {unit} + {spec.substitute_per_mps2:g} {unit} per m/s^2 of wheel deceleration"
               if spec.substitute_kind == "wheel_deceleration" else f"{spec.substitute:g} {unit}")
        return SignalReport(spec.name, PASS, problems=[f"absent on this car: the runtime feeds {fed} (substitute)"])
    plan = next(p for p in decoder.plans.values() if p.name == spec.message)
    rep = SignalReport(spec.name, PASS, spec.message, plan.frame_id, len(times[spec.message]),
                       len(values[i]), declared_hz=spec.rate_hz)
    ident = f"{spec.message} (ID {plan.frame_id:#x})"
    if rep.frames == 0:
        rep.result = FAIL
        rep.problems.append(f"never seen: no frame of {ident} in the log")
        rep.fix = f"this bus does not carry {ident}: check the DBC is this car's and the map's message name"
        return rep
    t = np.asarray(times[spec.message])
    rep.rate_hz = (len(t) - 1) / max(t[-1] - t[0], 1e-9) if len(t) > 1 else None
    if rep.used == 0:
        rep.result = FAIL
        why = ", ".join(f"{k} {v}" for k, v in (rejected.get(spec.message) or {}).items()) or "values never valid"
        rep.problems.append(f"{rep.frames} frames of {ident}, none usable ({why})")
        rep.fix = _rejection_fix(rejected.get(spec.message) or {})
        return rep
    v = np.asarray(values[i])
    rep.min, rep.max = float(v.min()), float(v.max())
    rep.resolution = _resolution(v)
    rep.valid_share = float(valid[:, i].mean()) if len(valid) else None
    if rep.rate_hz is not None and abs(rep.rate_hz / spec.rate_hz - 1.0) > RATE_TOL:
        rep.result = WARN
        rep.problems.append(f"measured {rep.rate_hz:.1f} Hz, the map declares {spec.rate_hz:g} Hz")
        rep.fix = f"set rate_hz = {rep.rate_hz:.1f} (staleness is judged against it)"
    if rejected.get(spec.message):
        share = sum(rejected[spec.message].values()) / rep.frames
        if share > 0.05:
            rep.result = FAIL
            rep.problems.append(f"{100 * share:.0f} % of its frames rejected (" + ", ".join(
                f"{k} {n}" for k, n in rejected[spec.message].items()) + ")")
            rep.fix = _rejection_fix(rejected[spec.message])
    if rep.valid_share is not None and rep.valid_share < MIN_VALID_SHARE and rep.result != FAIL:
        rep.result = WARN
        rep.problems.append(f"valid in {100 * rep.valid_share:.0f} % of the 50 Hz rows")
    return rep


def _rejection_fix(reasons: dict[str, int]) -> str:
    if not reasons:
        return "check the quality bit the map names (valid, valid_value)"
    top = max(reasons, key=reasons.get)
    return {"dlc": "payload length differs from the DBC: a different DBC version, or set short_frames = true in [map]",
            "checksum": "checksum mismatch: check checksum_algorithm in [messages.*] (or leave the checksum out)",
            "counter": "alive counter out of sequence: check the counter signal in [messages.*]",
            "invalid": "the quality bit says invalid: check valid / valid_value",
            "range": "values outside the physical range: check scale and offset",
            }.get(top, f"frames rejected ({top})")


def format_report(report: LogReport) -> str:
    """The report as a table for people."""
    lines = [f"log {report.log}: {report.frames} frames, {report.duration_s:.1f} s; map {report.map} on "
             f"{Path(report.dbc).name}"]
    if report.problem:
        lines.append(f"FAIL {report.problem}")
    head = f"{'signal':<26} {'result':<6} {'message (ID)':<28} {'frames':>7} {'Hz (map)':>13} {'range':>21} " \
           f"{'step':>9} {'valid':>6}"
    lines += ["", head, "-" * len(head)]
    for s in report.signals:
        where = f"{s.message} ({s.frame_id:#x})" if s.frame_id is not None else "absent"
        rate = f"{s.rate_hz:.1f} ({s.declared_hz:g})" if s.rate_hz is not None else \
            (f"- ({s.declared_hz:g})" if s.declared_hz else "-")
        rng = f"{s.min:.3g}..{s.max:.3g}" if s.min is not None else "-"
        step = f"{s.resolution:.3g}" if s.resolution is not None else "-"
        valid = f"{100 * s.valid_share:.0f} %" if s.valid_share is not None else "-"
        lines.append(f"{s.name:<26} {s.result:<6} {where:<28} {s.frames:>7} {rate:>13} {rng:>21} {step:>9} {valid:>6}")
        for p in s.problems:
            lines.append(f"{'':<26} {'':<6} {p}")
        if s.fix and s.result != PASS:
            lines.append(f"{'':<26} {'':<6} fix: {s.fix}")
    lines += ["", "physics checks (signs and scales):"]
    for f in report.physics:
        lines.append(f"  {f.result:<5} {f.check} ({f.signal}): {f.detail}")
        if f.result == FAIL and f.fix:
            lines.append(f"        -> {f.signal}: {f.fix}")
    n_fail = sum(s.result == FAIL for s in report.signals) + sum(f.result == FAIL for f in report.physics)
    n_warn = sum(s.result == WARN for s in report.signals) + sum(f.result in (WARN, SKIP) for f in report.physics)
    lines.append("")
    lines.append("OK: the map reads this log as the physics expects" if report.ok else
                 f"{n_fail} problem(s) to fix" + (f", {n_warn} warning(s)/unchecked" if n_warn else ""))
    return "\n".join(lines)


def culprits(report: LogReport) -> list[tuple[str, str]]:
    """``(signal, fix)`` for every failure: what a user would change in the map."""
    out = [(s.name, s.fix) for s in report.signals if s.result == FAIL]
    out += [(f.signal, f.fix) for f in report.physics if f.result == FAIL]
    return out

