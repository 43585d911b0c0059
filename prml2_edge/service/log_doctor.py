"""``prml2 doctor --log LOG``: check a signal map and DBC against one recorded drive of the car.

The log is read with the runtime's own log loop (:func:`~prml2_edge.runtime.offline.read_chunks`), decoder
and 50 Hz assembler (the same checks the runtime applies), then reported per canonical signal: frames of
its message, measured rate against the map's ``rate_hz``, range, resolution and validity; every mapped
signal never seen (naming message and ID); and the physics checks of :mod:`prml2_edge.data.signal_checks`
(signs and scales), each failure with the signal to blame and the fix for the map.

The verdict (:attr:`LogReport.verdict`, exit status :data:`EXIT_CODES`): ``FAIL`` (1) when anything is to
fix (a damaged log, a signal never seen or mostly rejected, a physics check failed); else ``NOT VERIFIED``
(3) when a physics check could not run on this drive (too little turning, too few moving rows: the line
names the signals and the driving that would verify them); ``OK`` (0) only when every check ran and passed.
"""

from __future__ import annotations

from contextlib import closing
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.can.signal_map import SignalMap, load_map_and_dbc, resolve_map
from prml2_edge.data.signal_checks import (
    FAIL,
    MIN_TURN_S,
    PASS,
    ROTATION_SIGNALS,
    SKIP,
    WARN,
    Finding,
    check_onboard,
    resolution,
    snap_factor,
)
from prml2_edge.errors import DataError
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.offline import read_chunks
from prml2_edge.runtime.source import check_log, truncation_problem
from prml2_edge.runtime.status import FrameStatus

OK, NOT_VERIFIED = "OK", "NOT VERIFIED"
EXIT_CODES = {OK: 0, FAIL: 1, NOT_VERIFIED: 3}  # prml2 doctor --log; 2 stays argparse's usage error
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
    def verdict(self) -> str:
        """``FAIL`` (something to fix), ``NOT VERIFIED`` (a physics check could not run) or ``OK`` (all ran, passed)."""
        if self.problem is not None or any(s.result == FAIL for s in self.signals) or \
                any(f.result == FAIL for f in self.physics):
            return FAIL
        return NOT_VERIFIED if self.unverified else OK

    @property
    def ok(self) -> bool:
        return self.verdict == OK

    @property
    def unverified(self) -> list[Finding]:
        """The physics checks that could not run on this log (SKIP)."""
        return [f for f in self.physics if f.result == SKIP]

    def as_dict(self) -> dict:
        return {"ok": self.ok, "verdict": self.verdict, "exit_code": EXIT_CODES[self.verdict],
                "summary": summary_line(self), "unverified": [f.signal for f in self.unverified],
                "log": self.log, "map": self.map, "dbc": self.dbc, "frames": self.frames,
                "duration_s": self.duration_s, "problem": self.problem,
                "signals": [asdict(s) for s in self.signals], "physics": [f.as_dict() for f in self.physics]}


def _scale_fix(spec, factor: float) -> str:
    """The map line that applies ``factor`` to ``spec``'s scale."""
    factor, hint = snap_factor(factor) if factor != -1.0 else (factor, "")
    new = spec.scale * factor
    return f"set scale = {new:.10g} in [signals.{spec.name}]" + (f" ({hint})" if hint else "")


@dataclass
class _Tally:
    """What the log's frames say, gathered as they stream through the decoder and the assembler."""

    times: dict[str, list[float]]  # message -> frame timestamps
    rejected: dict[str, dict[str, int]] = field(default_factory=dict)  # message -> reason -> frames
    values: list[list[float]] = field(default_factory=lambda: [[] for _ in range(schema.NUM_SIGNALS)])
    rows_v: list = field(default_factory=list)
    rows_ok: list = field(default_factory=list)
    n: int = 0
    t_first: float = 0.0
    t_last: float = 0.0

    def add_rows(self, rows) -> None:
        for row in rows:
            self.rows_v.append(row.values)
            self.rows_ok.append(row.valid)


def _read(path: Path, decoder: FrameDecoder, assembler: Assembler, max_frames: int | None) -> tuple[_Tally, str | None]:
    """Every frame of the log through ``decoder`` and ``assembler`` (the runtime's one log-reading loop,
    :func:`~prml2_edge.runtime.offline.read_chunks`); the problem of a damaged log, or None."""
    by_id = {fid: plan.name for fid, plan in decoder.plans.items()}
    tally = _Tally({plan.name: [] for plan in decoder.plans.values()})
    problem = None
    with closing(read_chunks(path)) as chunks:
        for frames, problem in chunks:
            for msg in frames if max_frames is None else frames[:max_frames - tally.n]:
                _take(tally, msg, by_id.get(msg.arbitration_id), decoder, assembler)
            if max_frames is not None and tally.n >= max_frames:
                problem = None  # any damage lies past the frames asked for
                break
    if problem is None:
        cut = truncation_problem(path)
        if cut is not None:
            problem = f"{path}: CAN log cut short after {tally.n} frames ({cut})"
    return tally, problem


def _take(tally: _Tally, msg: can.Message, name: str | None, decoder: FrameDecoder, assembler: Assembler) -> None:
    """One frame: its timestamp, why it was rejected, the values it gave and the rows it completed."""
    if tally.n == 0:
        tally.t_first = msg.timestamp
    tally.t_last = msg.timestamp
    tally.n += 1
    frame = decoder.step(msg)
    if name is not None and not msg.is_error_frame and not msg.is_remote_frame:
        tally.times[name].append(msg.timestamp)
        if frame.status.is_rejected:
            reason = frame.status.name.removeprefix("REJECTED_").lower()
            counts = tally.rejected.setdefault(name, {})
            counts[reason] = counts.get(reason, 0) + 1
    if frame.status is FrameStatus.USED:
        for i, v, ok in zip(frame.index, frame.value_si, frame.ok, strict=True):
            if ok:
                tally.values[i].append(v)
    tally.add_rows(assembler.step(frame)[1])


def check_log_file(log: str | Path, map_name: str | Path = "prml2_onboard", dbc: str | Path | None = None,
                   max_frames: int | None = None) -> LogReport:
    """Read ``log`` through ``map_name``/``dbc`` and check every canonical signal and the physics between them."""
    path = check_log(log)
    smap, db, dbc_path = load_map_and_dbc(resolve_map(map_name), dbc)
    decoder = FrameDecoder(smap, db)
    assembler = Assembler.for_map(smap)
    tally, problem = _read(path, decoder, assembler, max_frames)
    if tally.n == 0:
        raise DataError(problem or f"{path}: CAN log holds no frames")
    tally.add_rows(assembler.flush())
    duration = max(tally.t_last - tally.t_first, 1e-9)
    onboard = np.asarray(tally.rows_v).reshape(-1, schema.NUM_SIGNALS)
    valid = np.asarray(tally.rows_ok, dtype=bool).reshape(-1, schema.NUM_SIGNALS)

    reports = [_signal_report(smap, spec, tally.times, tally.rejected, tally.values, valid, duration, decoder)
               for spec in smap.signals]
    present = tuple(not s.absent and bool(tally.values[i]) for i, s in enumerate(smap.signals))
    steps = [next((r.resolution for r in reports if r.name == name), None) for name in schema.SIGNAL_NAMES]
    physics = check_onboard(onboard, valid, present, steps) if len(onboard) else []
    by_name = {s.name: s for s in smap.signals}
    physics = [_with_map_fix(f, by_name[f.signal]) for f in physics]
    return LogReport(str(path), smap.name, str(dbc_path), tally.n, duration, reports, physics, problem)


def _with_map_fix(f: Finding, spec) -> Finding:
    if f.result != FAIL or f.scale_factor is None:
        return f
    return replace(f, fix=_scale_fix(spec, f.scale_factor))


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
    rep.resolution = resolution(v)
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
    lines += ["", summary_line(report)]
    return "\n".join(lines)


_SPOKEN = {"yaw_rate_radps": "yaw rate", "lat_accel_mps2": "lateral acceleration",
           "steering_wheel_angle_rad": "steering", "speedometer_mps": "speedometer",
           **{n: n.removesuffix("_mps").replace("_", " ") for n in schema.WHEEL_SPEED_NAMES}}


def summary_line(report: LogReport) -> str:
    """The verdict in one line: OK, what is to fix, or which signals this log could not verify and what driving
    would."""
    verdict = report.verdict
    if verdict == OK:
        return "OK: the map reads this log as the physics expects (every check ran and passed)"
    n_warn = sum(s.result == WARN for s in report.signals) + sum(f.result == WARN for f in report.physics)
    skipped = report.unverified
    if verdict == FAIL:
        n_fail = sum(s.result == FAIL for s in report.signals) + sum(f.result == FAIL for f in report.physics) + \
            (report.problem is not None)
        rest = [f"{n_warn} warning(s)"] * bool(n_warn) + [f"{len(skipped)} not verified"] * bool(skipped)
        return f"FAIL: {n_fail} problem(s) to fix" + (f", {', '.join(rest)}" if rest else "")
    names = ", ".join(dict.fromkeys(_SPOKEN.get(f.signal, f.signal) for f in skipped))
    return f"NOT VERIFIED: {names} ({_needs(skipped)})"


def _needs(skipped: list[Finding]) -> str:
    """What driving would let the skipped checks run, in one phrase."""
    turning = [f for f in skipped if f.signal in ROTATION_SIGNALS and f.evidence is not None]
    other = list(dict.fromkeys(f.needs or f.detail for f in skipped if f not in turning))
    parts = []
    if turning:
        thr = max(f.evidence.threshold_dps for f in turning)
        have = min(f.evidence.turning_s for f in turning)
        parts.append(f"drive curves of at least {thr:.2g} deg/s of yaw rate, {MIN_TURN_S:g} s of them in all; "
                     f"this log has {have:.1f} s")
    parts += [f"drive {n}" if n[:1].isdigit() or n.startswith("at least") else n for n in other]
    return "; ".join(parts)


def culprits(report: LogReport) -> list[tuple[str, str]]:
    """``(signal, fix)`` for every failure: what a user would change in the map."""
    out = [(s.name, s.fix) for s in report.signals if s.result == FAIL]
    out += [(f.signal, f.fix) for f in report.physics if f.result == FAIL]
    return out

