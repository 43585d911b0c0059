"""The runtime pipeline: wires the stages together; ``main()``-level code only builds and drives it.

frame -> :class:`~prml2_edge.runtime.decode.FrameDecoder` -> :class:`~prml2_edge.runtime.assembler.Assembler`
-> 50 Hz rows -> :class:`~prml2_edge.runtime.localizer.StreamingLocalizer` -> sinks.

:meth:`Pipeline.step` takes one ``can.Message`` and never raises on bad data: every frame
is counted once in :class:`~prml2_edge.runtime.stats.FrameStats`. Set-up problems (map vs
DBC, model vs schema, no way to get an initial pose) raise one-line :class:`Prml2Error`\\ s
in :meth:`Pipeline.build`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np

from prml2_edge import schema
from prml2_edge.can.signal_map import SignalMap, load_map_and_dbc, resolve_map
from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.errors import ConfigError
from prml2_edge.runtime.assembler import Assembler
from prml2_edge.runtime.decode import FrameDecoder
from prml2_edge.runtime.inference import OnnxModel, default_model_path
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.latency import LatencyRecorder
from prml2_edge.runtime.localizer import LocalizerConfig, StepOutput, StreamingLocalizer
from prml2_edge.runtime.plausibility import YAW as _YAW_RATE
from prml2_edge.runtime.plausibility import Plausibility, PlausibilityConfig
from prml2_edge.runtime.rows import AssembledRow
from prml2_edge.runtime.stats import FrameStats
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import CalState, EkfState

log = logging.getLogger(__name__)

_NAN_COV = np.full((2, 2), np.nan)
_NAN_CAL = np.full(CalState.DIM, np.nan)


class MemorySink:
    """Keeps every step's time, state, uncertainty and status in memory (tests, demo, evaluation)."""

    def __init__(self) -> None:
        self.t_s: list[float] = []
        self.x: list[np.ndarray] = []
        self.pos_std_m: list[float] = []
        self.status: list[int] = []
        self.model_used: list[bool] = []
        self.gnss_outage: list[bool] = []
        self.pos_cov: list[np.ndarray] = []
        self.cal: list[np.ndarray] = []
        self.standstill: list[bool] = []

    def step(self, out: StepOutput) -> None:
        self.t_s.append(out.t_s)
        self.x.append(out.x)
        self.pos_std_m.append(out.pos_std_m)
        self.status.append(int(out.status))
        self.model_used.append(out.model_used)
        self.gnss_outage.append(out.gnss_outage)
        self.pos_cov.append(out.pos_cov if out.pos_cov is not None else _NAN_COV)
        self.cal.append(out.cal if out.cal is not None else _NAN_CAL)
        self.standstill.append(out.standstill)

    def arrays(self) -> dict[str, np.ndarray]:
        """Per step: ``t_s``, ``x`` (N, 8), ``pos_std_m``, ``status``, ``model_used``, ``gnss_outage`` (N,),
        ``pos_cov`` (N, 2, 2) and ``cal`` (N, 3) (NaN before the start / with calibration off), ``standstill``
        (N,) (a zero-velocity update replaced the model)."""
        return {"t_s": np.asarray(self.t_s), "x": np.asarray(self.x).reshape(-1, EkfState.DIM),
                "pos_std_m": np.asarray(self.pos_std_m), "status": np.asarray(self.status, dtype=np.int8),
                "model_used": np.asarray(self.model_used, dtype=bool),
                "gnss_outage": np.asarray(self.gnss_outage, dtype=bool),
                "pos_cov": np.asarray(self.pos_cov).reshape(-1, 2, 2),
                "cal": np.asarray(self.cal).reshape(-1, CalState.DIM),
                "standstill": np.asarray(self.standstill, dtype=bool)}

    def close(self) -> None:
        pass


@dataclass
class _Window:
    """Counters over one status interval (live mode)."""

    t_wall: float
    frames: int = 0
    rows: int = 0
    e2e_index: int = 0


MISSING_PERIODS = 5.0  # a mapped signal without a value this many of its periods after the first frame is missing
MISSING_MIN_S = 0.25  # ... and at least this long [s]


class Pipeline:
    """Decoder -> assembler -> localiser -> sinks, with frame accounting and latency per stage.

    Nothing fails silently: a mapped signal that has no value :data:`MISSING_PERIODS` of its
    periods (at least :data:`MISSING_MIN_S`) after the first frame gets one warning line naming
    the signal, its message and ID (:meth:`missing_signals` lists them for the summary).
    """

    def __init__(self, signal_map: SignalMap, decoder: FrameDecoder, assembler: Assembler,
                 localizer: StreamingLocalizer, sinks: Sequence = (), stats: FrameStats | None = None,
                 latency: LatencyRecorder | None = None, dbc_path: Path | None = None,
                 plausibility: Plausibility | None = None) -> None:
        self.signal_map = signal_map
        self.plausibility = plausibility
        self._episodes_warned = 0  # injection suspicions already warned about (decode.InjectionMonitor)
        self.decoder = decoder
        self.assembler = assembler
        self.localizer = localizer
        self.sinks = list(sinks)
        self.stats = stats if stats is not None else FrameStats()
        self.latency = latency if latency is not None else LatencyRecorder()
        self.dbc_path = dbc_path
        self.calibration_file = None  # a runtime.calibration.CalibrationFile (see use_calibration_file)
        self.last: StepOutput | None = None
        self.rows = 0
        self.bus_silent_rows = 0  # 50 Hz rows flagged bus_silent (no frame for > bus_silent_s)
        self.first_t_s: float | None = None
        self._t_wall0 = time.monotonic()
        self._interval = _Window(self._t_wall0)
        self._last_frame_wall = self._t_wall0
        self.invalid_rows = np.zeros(schema.NUM_SIGNALS, dtype=np.int64)  # rows each signal was invalid in
        self._missing_after_s = np.full(schema.NUM_SIGNALS, np.inf)  # when a signal without a value is missing
        self._where: dict[int, str] = {}  # canonical index -> "message MSG (ID 0x..)"
        for spec in signal_map.present:
            i = schema.SIGNAL_BY_NAME[spec.name].index
            self._missing_after_s[i] = max(MISSING_PERIODS / spec.rate_hz, MISSING_MIN_S)
            plan = next((p for p in decoder.plans.values() if p.name == spec.message), None)
            ident = f", ID {plan.frame_id:#x}" if plan is not None else ""
            self._where[i] = f"{spec.message}.{'+'.join(n for n, _ in spec.summed_parts)}{ident}"
        self._warned_missing = ~np.isfinite(self._missing_after_s)  # absent signals are never missing
        self.gnss_sources: list = []  # objects with due(t_s) -> fixes (runtime.gnss_input), merged by time

    @classmethod
    def build(cls, map: str | Path = "prml2_onboard", dbc: str | Path | None = None,
              model: str | Path | OnnxModel | None = None, threads: int = 1, providers: Sequence[str] = ("cpu",),
              spinning: bool = False,
              fixed_threads: bool = False,
              gnss_course: bool = True,
              stride: int = DEFAULT_STRIDE, async_inference: bool = False, mu: float = 1.0, stale_periods: float = 3.0,
              driven_axle: str = "front", steering_ratio: float = 15.0,
              initial_pose: InitialPose | None = None, sinks: Sequence = (),
              localizer_config: LocalizerConfig | None = None, trt_cache_dir: str = "~/.cache/prml2/trt",
              trt_fp16: bool = False, calibration: bool = True, calibration_file: str | Path | None = None,
              external_gnss: bool = False, plausibility: PlausibilityConfig | None = None) -> Pipeline:
        """Load and cross-check map, DBC and model; refuse mismatches at start-up with what differs.

        ``initial_pose`` None means: take it from the first GNSS fix on the bus, which needs a map
        with a ``[gnss]`` table, or ``external_gnss`` (fixes from ``--gnss``, see :meth:`add_gnss_source`).
        ``plausibility`` configures the cross-checks of the signals (:mod:`~prml2_edge.runtime.plausibility`;
        default on with the car's ``steering_ratio``, ``PlausibilityConfig(enabled=False)`` turns them off).
        ``driven_axle`` ("front", "rear" or "all") and ``steering_ratio`` describe the car: the filter's wheel cue
        comes from the axle that does not drive (:class:`LocalizerConfig`). ``gnss_course``: a fix's angle is the
        course over ground (a receiver's), fused with the sideslip taken out; False: it is the car's yaw.
        """
        signal_map, db, dbc_path = load_map_and_dbc(resolve_map(map), dbc)
        if initial_pose is None and signal_map.gnss is None and not external_gnss:
            raise ConfigError(f"signal map {signal_map.name!r} defines no GNSS fix message, so the initial pose "
                              "cannot come from the bus: give --gnss SOURCE, --initial-pose X,Y,HEADING_DEG or "
                              "--initial-pose-file")
        if not isinstance(model, OnnxModel):
            model = OnnxModel(model if model is not None else default_model_path(), threads=threads,
                              providers=providers, trt_cache_dir=trt_cache_dir, trt_fp16=trt_fp16,
                              spinning=spinning, fixed_threads=fixed_threads)
        cfg = localizer_config or LocalizerConfig(stride=stride, async_inference=async_inference, mu=mu,
                                                  calibration=calibration, driven_axle=driven_axle,
                                                  steering_ratio=steering_ratio, gnss_course_sideslip=gnss_course)
        if plausibility is None:
            plausibility = PlausibilityConfig(steering_ratio=steering_ratio)
        stats = FrameStats()
        latency = LatencyRecorder()
        decoder = FrameDecoder(signal_map, db)
        assembler = Assembler.for_map(signal_map, stale_periods=stale_periods)
        localizer = StreamingLocalizer(model, cfg, initial_pose=initial_pose)
        if localizer.raw_rows_warning:
            log.warning(localizer.raw_rows_warning)
        checks = Plausibility([s.rate_hz for s in signal_map.signals], plausibility, assembler.substituted)
        pipeline = cls(signal_map, decoder, assembler, localizer, sinks, stats, latency, dbc_path, checks)
        if calibration_file is not None and cfg.calibration:
            pipeline.use_calibration_file(calibration_file)
        return pipeline

    def use_calibration_file(self, path: str | Path) -> None:
        """Restore the calibration from ``path`` when it matches this vehicle; save it there every minute of
        drive time and at :meth:`close` (:mod:`prml2_edge.runtime.calibration`)."""
        from prml2_edge.runtime.calibration import CalibrationFile

        dbc = self.dbc_path.name if self.dbc_path else self.signal_map.dbc
        self.calibration_file = CalibrationFile(Path(path), f"{self.signal_map.name} ({dbc})")
        self.calibration_file.check_writable()
        restored = self.calibration_file.load()
        if restored is not None:
            self.localizer.restore_calibration(*restored)
        if self.calibration_file.yaw_gain is not None:
            self.localizer.restore_yaw_gain(*self.calibration_file.yaw_gain)
        if self.calibration_file.cue_offsets is not None:
            self.localizer.restore_cue_offsets(*self.calibration_file.cue_offsets)

    def _save_calibration(self, t_s: float | None) -> None:
        cal = self.localizer.calibration()
        if self.calibration_file is not None and cal is not None:
            self.calibration_file.save(*cal, t_s=t_s, yaw_gain=self.localizer.yaw_gain_state(),
                                       cue_offsets=self.localizer.cue_offset_state())

    @property
    def model(self):
        return self.localizer.model

    def step(self, msg: can.Message, recv_ns: int | None = None) -> list[StepOutput]:
        """One frame in; the 50 Hz outputs it completed out (usually none or one). Never raises on bad data."""
        t0 = time.perf_counter_ns()
        recv_ns = t0 if recv_ns is None else recv_ns
        outs = self._gnss_due(float(msg.timestamp), recv_ns) if self.gnss_sources else []
        frame = self.decoder.step(msg)
        t1 = time.perf_counter_ns()
        status, rows = self.assembler.step(frame, recv_ns)
        t2 = time.perf_counter_ns()
        self.stats.add_frame(status, frame)
        lat = self.latency
        lat.add("decode", t1 - t0)
        lat.add("assemble", t2 - t1)
        self._interval.frames += 1
        self._last_frame_wall = time.monotonic()
        if rows:
            outs += [self._row(self.check(row)) for row in rows]
        return outs

    def check(self, row: AssembledRow) -> AssembledRow:
        """The plausibility stage (between the assembler and :meth:`_row`): flagged and stale signals out,
        the others' prediction in (:mod:`~prml2_edge.runtime.plausibility`)."""
        if self.plausibility is None:
            return row
        t0 = time.perf_counter_ns()
        decoder = self.decoder
        untrusted = None
        if decoder.suspicion_possible(row.t_s):  # (streaming and offline alike pass here, in row order)
            episodes = decoder.episodes()
            if episodes > self._episodes_warned:
                self._episodes_warned = episodes
                log.warning("injection suspected on %s at t=%.2f s: a second sender on the bus (rate or counter "
                            "sequence)", ", ".join(decoder.suspected_messages(row.t_s)), row.t_s)
            untrusted = decoder.untrusted_signals(row.t_s)
        row = self.plausibility.check(row, untrusted)
        self.latency.add("plausibility", time.perf_counter_ns() - t0)
        for i in row.newly_flagged:
            log.warning("%s taken out at t=%.2f s: %s", schema.SIGNAL_NAMES[i], row.t_s,
                        self.plausibility.checks[i].reason)
        return row

    def add_gnss_source(self, source) -> None:
        """Merge fixes from ``source`` (``due(t_s)`` returns those up to frame time ``t_s``) into the stream."""
        self.gnss_sources.append(source)

    def _gnss_due(self, t_s: float, recv_ns: int) -> list[StepOutput]:
        outs = []
        for source in self.gnss_sources:
            for fix in source.due(t_s):
                if fix.valid:
                    self.stats.gnss_fixes += 1
                else:
                    self.stats.gnss_invalid += 1
                outs += [self._row(self.check(row)) for row in self.assembler.add_gnss(fix, recv_ns)]
        return outs

    def finish(self) -> list[StepOutput]:
        """End of stream: emit the last row(s) still held by the assembler."""
        return [self._row(self.check(row)) for row in self.assembler.flush()]

    def missing_signals(self, t_s: float | None = None) -> list[str]:
        """One line per mapped signal that has had no value by ``t_s`` (default: the last row), naming its
        message and ID and what happened to the frames of that message, if any arrived."""
        if self.first_t_s is None:
            return []
        t_s = self.last.t_s if t_s is None and self.last is not None else (t_s or self.first_t_s)
        never = ~np.isfinite(self.assembler.last_t_s) & (t_s - self.first_t_s >= self._missing_after_s)
        lines = []
        for i in np.flatnonzero(never):
            where = self._where[int(i)]
            message = where.split(".", 1)[0]
            rejected = self.stats.rejected_by_message.get(message)
            if rejected:
                seen = "frames of it arrived but were all rejected (" + ", ".join(
                    f"{k} {v}" for k, v in rejected.items()) + ")"
            elif self.stats.by_message.get(message):
                seen = "its message arrived but the value was never valid"
            else:
                seen = "no frame of that message is on this bus"
            lines.append(f"{schema.SIGNAL_NAMES[i]} ({where}): {seen}")
        return lines

    def _warn_missing(self, t_s: float) -> None:
        self._warned_missing |= np.isfinite(self.assembler.last_t_s)  # seen: nothing to warn about, ever
        due = ~self._warned_missing & ~np.isfinite(self.assembler.last_t_s) & \
            (t_s - self.first_t_s >= self._missing_after_s)  # type: ignore[operator]
        if not due.any():
            return
        self._warned_missing |= due
        for line in self.missing_signals(t_s):
            name = line.split(" ", 1)[0]
            if due[schema.SIGNAL_BY_NAME[name].index]:
                log.warning("no value of %s %.2f s after the first frame; check the map's message and the DBC "
                            "against this bus (prml2 doctor --log LOG)", line, t_s - self.first_t_s)

    def _row(self, row: AssembledRow) -> StepOutput:
        self.stats.add_row(row)
        if self.first_t_s is None:
            self.first_t_s = row.t_s
        self.invalid_rows += ~row.valid
        if not self._warned_missing.all():
            self._warn_missing(row.t_s)
        for i, offset, std, t_step in row.offset_jumps:
            if i == _YAW_RATE:
                self.localizer.filter.correct_yaw_cue(offset, std, t_step, row.t_s)
        out = self.localizer.step(row.values, row.valid, row.t_s, row.gnss, row.discontinuity, row.bus_silent,
                                  row.substituted, row.substitute_std)
        out.substituted = row.substituted
        if out.degraded or out.reasons:
            out.reasons = {**(out.reasons or {}), **self._reasons(row)}
        if out.inferred:
            self.latency.add("infer", out.infer_ns)
            self.latency.add("guard", out.guard_ns)
        self.latency.add("filter", out.filter_ns)
        if out.bus_silent:
            self.bus_silent_rows += 1
        t_sinks = time.perf_counter_ns()
        for sink in self.sinks:
            sink.step(out)
        t_done = time.perf_counter_ns()
        self.latency.add("sinks", t_done - t_sinks)
        if row.trigger_ns:
            self.latency.add("end_to_end", t_done - row.trigger_ns)
        self.last = out
        self.rows += 1
        self._interval.rows += 1
        if self.calibration_file is not None and self.calibration_file.due(out.t_s):
            self._save_calibration(out.t_s)
        return out

    def _reasons(self, row: AssembledRow) -> dict[str, str]:
        """Why each invalid signal of ``row`` is out, one line each."""
        checks = self.plausibility.checks if self.plausibility is not None else None
        out = {}
        for i in np.flatnonzero(~row.valid):
            name = schema.SIGNAL_NAMES[i]
            why = checks[i].reason if checks is not None and checks[i].flagged else "stale (no valid frame)"
            if self.plausibility is not None and i in self.plausibility.untrusted:
                why = self.plausibility.untrusted[i]
            if self.assembler.frozen[i]:
                why = "frozen (stuck-sensor check)"
            if row.substituted is not None and row.substituted[i]:
                why += "; the others' prediction stands in"
            out[name] = why
        return out

    def model_never_ran(self, stream: str = "the log") -> str | None:
        """Why the model never ran on this stream (one line), or None when it did; ``stream`` names it
        in the line ("the log" for a replay, "the run" for a live bus)."""
        if self.localizer.n_model_used:
            return None
        if self.stats.received and not self.stats.used:
            return (f"the model never ran: none of the {self.stats.received} frames of {stream} is a message map "
                    f"{self.signal_map.name} reads; check the map and the DBC against this bus (prml2 doctor)")
        missing = self.missing_signals()
        if missing:
            return "the model never ran: " + "; ".join(missing)
        window_s = getattr(self.localizer.model, "window_len", 250) * schema.DT_S
        data_s = (self.last.t_s - self.first_t_s) if self.last is not None and self.first_t_s is not None else 0.0
        if data_s < window_s:
            return (f"the model never ran: {stream} covers {data_s:.1f} s of CAN data, less than the model's "
                    f"{window_s:.0f} s window")
        if self.rows and self.invalid_rows.any():
            worst = np.argsort(-self.invalid_rows)[:3]
            parts = [f"{schema.SIGNAL_NAMES[i]} invalid in {100.0 * self.invalid_rows[i] / self.rows:.0f} % of rows"
                     for i in worst if self.invalid_rows[i]]
            return "the model never ran: no 5 s window had valid inputs (" + ", ".join(parts) + ")"
        return "the model never ran (no inference succeeded; see the latency and inference counts)"

    def close(self) -> None:
        self._save_calibration(self.last.t_s if self.last is not None else None)
        for sink in self.sinks:
            sink.close()
        self.localizer.close()

    # ---- reporting -------------------------------------------------------------------------------

    def status_line(self) -> str:
        """One line for the periodic status: rates, staleness, latency, pose (live mode)."""
        now = time.monotonic()
        win = self._interval
        dt = max(now - win.t_wall, 1e-9)
        e2e = self.latency.stage_summary("end_to_end", since_total=win.e2e_index)
        self._interval = _Window(now, e2e_index=self.latency.total("end_to_end"))
        parts = [f"{win.frames / dt:.0f} frames/s", f"{win.rows / dt:.1f} rows/s"]
        silent_s = now - self._last_frame_wall
        if silent_s > 1.0:
            parts.append(f"BUS SILENT {silent_s:.1f} s")
        out = self.last
        if out is not None:
            invalid = [schema.SIGNALS[i].symbol for i in np.flatnonzero(~out.valid)]
            parts.append("invalid: " + (",".join(invalid) if invalid else "none"))
            suspected = self.decoder.suspected_messages(out.t_s) if self.decoder.suspicion_possible(out.t_s) else []
            if suspected:
                parts.append("INJECTION SUSPECTED " + ", ".join(suspected))
            if self.plausibility is not None:
                flagged = self.plausibility.reasons()
                if flagged:
                    parts.append("OUT " + "; ".join(f"{schema.SIGNAL_BY_NAME[n].symbol}: {r}"
                                                    for n, r in flagged.items()))
            max_age_s = self.assembler.max_signal_age_s()
            if max_age_s is not None:
                parts.append(f"max age {1000.0 * max_age_s:.0f} ms")
        if e2e.get("count"):
            parts.append(f"e2e p50/p99 {e2e['p50_ms']:.2f}/{e2e['p99_ms']:.2f} ms")
        if out is not None:
            if out.status is PoseStatus.INITIALISING:
                parts.append("INITIALISING (waiting for a GNSS fix)")
            else:
                p_x, p_y = out.x[EkfState.POS]
                parts.append(f"pose ({p_x:.1f}, {p_y:.1f}) m +-{out.pos_std_m:.1f} {out.status.name}"
                             + (f" outage {out.outage_s:.0f} s" if out.gnss_outage else ""))
            if out.reasons and "gnss" in out.reasons:
                parts.append(out.reasons["gnss"])
        return " | ".join(parts)

    def _localizer_summary(self, loc: StreamingLocalizer) -> dict:
        """The estimator's and the filter's counters (their own ``summary()``), with the calibration file's."""
        out = loc.summary()
        cal = out.pop("calibration", None) or {"enabled": loc.config.calibration}
        if self.calibration_file is not None:
            cal = {**cal, **self.calibration_file.summary()}
        out["calibration"] = cal
        return out

    def summary(self) -> dict:
        """Everything worth reporting at the end of a run, as plain data."""
        loc = self.localizer
        model = loc.model
        wall_s = time.monotonic() - self._t_wall0
        data_s = (self.last.t_s - self.first_t_s) if (self.last is not None and self.first_t_s is not None) else 0.0
        statuses = {s.name: loc.status_counts[s] for s in PoseStatus if loc.status_counts[s]}
        last = None
        if self.last is not None:
            out = self.last
            p_x, p_y = out.x[EkfState.POS]
            last = {"t_s": out.t_s, "x_m": p_x, "y_m": p_y, "psi_rad": out.x[EkfState.YAW.start],
                    "v_x_mps": out.x[EkfState.VEL.start], "pos_std_m": out.pos_std_m, "status": out.status.name,
                    "outage_s": out.outage_s}
            last = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in last.items()}
        sinks = {type(s).__name__: {k: getattr(s, k) for k in ("rows", "frames", "errors", "last_error")
                                    if hasattr(s, k)} for s in self.sinks}
        assembler = self.assembler.summary()
        return {
            "map": self.signal_map.name, "dbc": str(self.dbc_path) if self.dbc_path else self.signal_map.dbc,
            "model": getattr(model, "describe", lambda: type(model).__name__)(),
            "frames": self.stats.as_dict(),
            "rows": self.rows, "grid_resyncs": assembler["grid_resyncs"], "bus_silent_rows": self.bus_silent_rows,
            "signals_missing": self.missing_signals(),
            "plausibility": self.plausibility.summary() if self.plausibility is not None else {"enabled": False},
            "injection_suspected": self.decoder.injection_summary(self.last.t_s if self.last is not None else None),
            "signal_faults": {"frozen_now": assembler["frozen_now"],
                              "frozen_episodes": {n: c for n, c in zip(schema.SIGNAL_NAMES, self.stats.signal_frozen,
                                                                        strict=True) if c}},
            "steps_by_status": statuses,
            **self._localizer_summary(loc),
            "latency": self.latency.summary(),
            "wall_s": wall_s, "data_s": data_s, "realtime_factor": (data_s / wall_s) if wall_s > 0 else None,
            "last": last, "sinks": sinks,
        }


def run_source(pipeline: Pipeline, source, progress=None, should_stop=lambda: False, on_idle=None,
               timeout_s: float = 0.1) -> None:
    """Drive ``pipeline`` from ``source`` (``step(timeout) -> Message | None``; ``finished`` ends it).

    ``progress`` (a :class:`prml2_edge.progress.Progress`) is advanced per frame; ``on_idle`` is
    called after every frame and every timeout (status lines, watchdog); ``should_stop``
    ends the loop early (signals).
    """
    while not should_stop():
        msg = source.step(timeout_s)
        if msg is not None:
            recv_ns = time.perf_counter_ns()
            pipeline.step(msg, recv_ns)
            if progress is not None:
                progress.update()
        elif getattr(source, "finished", False):
            break
        if on_idle is not None:
            on_idle()
    pipeline.finish()
