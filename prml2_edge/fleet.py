"""Fleet replay: many recorded CAN logs on a Dask distributed cluster, one task per log (``prml2 fleet``).

Each task replays one log on the offline schedule (:mod:`prml2_edge.runtime.offline`, inference in the
task's own thread: the cluster's parallelism is one log per worker) and writes, under
``OUT/logs/<name>/``, the trajectory (``pose.tum``) and the run's summary (``summary.json``, written
last and atomically: its presence marks the log finished). A log that cannot be read, is cut short or
fails in the runtime leaves ``failed.json`` with its one-line reason instead; the other logs go on.
A second run skips every log whose ``summary.json`` matches the file (size and modification time)
and retries the failed ones. The client collects one row per log into ``OUT/fleet_summary.csv`` and
``.json``: hours, frames, rejected frames, the share of 50 Hz steps the model drove, the drift at
GNSS re-acquisition (where the log has GNSS after an outage) and each failure's reason.

The cluster is a :class:`dask.distributed.LocalCluster` of this machine's cores (worker processes,
one thread each, bound to 127.0.0.1, no dashboard) unless an existing scheduler's address is given;
there every worker needs ``prml2-edge`` installed and ``OUT`` and the logs on a shared path.
Dask is the ``fleet`` extra (``pip install 'prml2-edge[fleet]'``); this module imports it only in
:func:`run_fleet`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from prml2_edge import schema
from prml2_edge.errors import first_line
from prml2_edge.schema import EkfState

SUMMARY = "summary.json"
FAILED = "failed.json"
MIN_OUTAGE_S = 5.0  # a GNSS fix after at least this long without one measures the dead-reckoning drift
COLUMNS = ("log", "status", "hours", "frames", "rejected", "model_driven_pct", "drift_pct", "drift_events",
           "wall_s", "x_realtime", "reason")


@dataclass
class LogResult:
    """One row of the fleet summary (``status``: ``ok``, ``skipped`` (finished before) or ``failed``)."""

    log: str
    status: str
    hours: float | None = None
    frames: int | None = None
    rejected: int | None = None
    model_driven_pct: float | None = None
    drift_pct: float | None = None  # mean over GNSS re-acquisitions: error / distance since the last fix
    drift_events: int = 0
    wall_s: float | None = None
    x_realtime: float | None = None
    reason: str = ""
    out_dir: str = ""
    extra: dict = field(default_factory=dict)


def log_key(path: str | Path) -> str:
    """The folder name of a log's outputs: its stem and a hash of its absolute path (two drives' 'log.asc')."""
    p = Path(path).resolve()
    return f"{p.name}-{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"


def file_id(path: str | Path) -> dict:
    st = Path(path).stat()
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


class GnssDrift:
    """Dead-reckoning drift measured by the log's own GNSS: at every valid fix after an outage of at least
    ``min_outage_s``, the distance between the pose of the row before it and the fix, over the distance
    driven since the last fix (the estimated speed integrated). The previous row's pose is 20 ms older
    than the fix (at 15 m/s, 0.3 m of the error)."""

    def __init__(self, min_outage_s: float = MIN_OUTAGE_S) -> None:
        self.min_outage_s = float(min_outage_s)
        self.events: list[dict] = []
        self._prev = None
        self._dist = 0.0

    def __call__(self, row, out) -> None:
        prev = self._prev
        fix = row.gnss
        if prev is not None and math.isfinite(prev.x[0]):
            self._dist += float(math.hypot(*prev.x[EkfState.VEL])) * schema.DT_S
            if fix is not None and fix.valid and prev.gnss_outage and prev.outage_s >= self.min_outage_s \
                    and self._dist > 1.0:
                err = math.hypot(prev.x[0] - fix.x_m, prev.x[1] - fix.y_m)
                self.events.append({"t_s": row.t_s, "outage_s": prev.outage_s, "distance_m": self._dist,
                                    "error_m": err, "drift_pct": 100.0 * err / self._dist})
        if out.gnss_fused:
            self._dist = 0.0
        self._prev = out

    def summary(self) -> dict:
        pct = [e["drift_pct"] for e in self.events]
        return {"events": self.events, "mean_drift_pct": (sum(pct) / len(pct)) if pct else None}


def _write_json(path: Path, doc: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2, default=lambda o: o.item() if hasattr(o, "item") else str(o)) + "\n")
    os.replace(tmp, path)  # atomic: a summary.json is never half written


def finished(log: str | Path, out_dir: str | Path) -> dict | None:
    """The summary of a log finished before (same file), else None."""
    path = Path(out_dir) / SUMMARY
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    try:
        same = doc.get("input") == file_id(log)
    except OSError:
        return None
    return doc if same else None


def _row_from(log: str, doc: dict, status: str, out_dir: Path) -> LogResult:
    s = doc["summary"]
    fr = s["frames"]
    rows = max(int(s["rows"]), 1)
    drift = doc.get("gnss_drift") or {}
    wall = doc.get("wall_s")
    return LogResult(log, status, hours=s["data_s"] / 3600.0, frames=fr["received"], rejected=fr["rejected"],
                     model_driven_pct=100.0 * s["model_used_steps"] / rows, drift_pct=drift.get("mean_drift_pct"),
                     drift_events=len(drift.get("events") or []), wall_s=wall,
                     x_realtime=(s["data_s"] / wall) if wall else None, out_dir=str(out_dir),
                     extra={"rejected_by_reason": fr["rejected_by_reason"], "balanced": fr["balanced"]})


def replay_one(log: str, out_root: str, build: dict) -> dict:
    """The task: replay ``log`` offline into ``out_root/logs/<key>/``; a :class:`LogResult` as a dict.

    Never raises for a bad log or a runtime error: the reason goes into the result and ``failed.json``.
    ``build`` holds :meth:`Pipeline.build`'s keyword arguments (plain data).
    """
    from prml2_edge.runtime.offline import run_offline
    from prml2_edge.runtime.pipeline import Pipeline
    from prml2_edge.runtime.sinks import TumSink
    from prml2_edge.runtime.source import scan_log

    logging.getLogger("prml2_edge").setLevel(logging.WARNING)  # one line per log in the summary, not per worker
    out_dir = Path(out_root) / "logs" / log_key(log)
    t0 = time.perf_counter()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / FAILED).unlink(missing_ok=True)
        n_frames, _, _, problem = scan_log(log)
        if problem is not None:
            raise ValueError(problem)
        sink = TumSink(out_dir / "pose.tum")
        drift = GnssDrift()
        try:
            pipeline = Pipeline.build(**build, sinks=[sink])
        except BaseException:
            sink.close()  # a long-lived cluster worker must not keep the file open
            raise
        try:
            result = run_offline(pipeline, log, workers=1, on_row=drift)
        finally:
            pipeline.close()
        if result.problem is not None:
            raise ValueError(result.problem)
        wall = time.perf_counter() - t0
        doc = {"input": file_id(log), "wall_s": wall, "summary": pipeline.summary(), "offline": pipeline.offline,
               "gnss_drift": drift.summary(), "outputs": {"tum": "pose.tum"}}
        _write_json(out_dir / SUMMARY, doc)
        return asdict(_row_from(log, doc, "ok", out_dir))
    except Exception as exc:  # every failure is this log's, in one line; the fleet goes on
        reason = first_line(exc, 300)
        try:
            (out_dir / SUMMARY).unlink(missing_ok=True)
            _write_json(out_dir / FAILED, {"input": str(log), "reason": reason})
        except OSError:
            pass
        return asdict(LogResult(log, "failed", reason=reason, wall_s=time.perf_counter() - t0, out_dir=str(out_dir)))


def write_table(results: list[LogResult], out_root: Path) -> dict:
    """``fleet_summary.csv`` and ``fleet_summary.json`` under ``out_root``; returns the totals."""
    import csv

    ok = [r for r in results if r.status in ("ok", "skipped")]
    hours = sum(r.hours or 0.0 for r in ok)
    steps = sum((r.hours or 0.0) * r.model_driven_pct for r in ok if r.model_driven_pct is not None)
    drifts = [r.drift_pct for r in ok if r.drift_pct is not None]
    totals = {"logs": len(results), "ok": sum(r.status == "ok" for r in results),
              "skipped": sum(r.status == "skipped" for r in results),
              "failed": sum(r.status == "failed" for r in results), "hours": hours,
              "frames": sum(r.frames or 0 for r in ok), "rejected": sum(r.rejected or 0 for r in ok),
              "model_driven_pct": (steps / hours) if hours else None,
              "drift_pct": (sum(drifts) / len(drifts)) if drifts else None}
    out_root.mkdir(parents=True, exist_ok=True)
    with open(out_root / "fleet_summary.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for r in results:
            w.writerow(["" if getattr(r, c) is None else getattr(r, c) for c in COLUMNS])
    _write_json(out_root / "fleet_summary.json", {"totals": totals, "logs": [asdict(r) for r in results]})
    return totals


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def table_lines(results: list[LogResult], totals: dict) -> list[str]:
    """The summary table for the terminal."""
    lines = [f"{'log':<40} {'status':<8} {'hours':>7} {'frames':>9} {'rejected':>8} {'model %':>7} {'drift %':>7}"
             f"  reason"]
    for r in results:
        lines.append(f"{Path(r.log).name[:40]:<40} {r.status:<8} {_fmt(r.hours, '.3f'):>7} {_fmt(r.frames, 'd'):>9} "
                     f"{_fmt(r.rejected, 'd'):>8} {_fmt(r.model_driven_pct, '.1f'):>7} {_fmt(r.drift_pct, '.2f'):>7}"
                     f"  {r.reason}")
    lines.append(f"total: {totals['logs']} logs ({totals['ok']} replayed, {totals['skipped']} finished before, "
                 f"{totals['failed']} failed), {totals['hours']:.2f} h, {totals['frames']} frames, "
                 f"{totals['rejected']} rejected, model drove {_fmt(totals['model_driven_pct'], '.1f')} % of the "
                 f"steps, "
                 f"drift at GNSS re-acquisition {_fmt(totals['drift_pct'], '.2f')} %")
    return lines


def run_fleet(logs: list[str], out_root: str | Path, build: dict, address: str | None = None,
              workers: int | None = None, progress=None) -> tuple[list[LogResult], dict]:
    """Replay ``logs`` on a Dask cluster (``address``, or a local one of ``workers`` processes), skipping the
    logs finished before; one :class:`LogResult` per log (in the order given) and the totals."""
    from dask.distributed import Client, LocalCluster, as_completed

    for name in ("distributed", "tornado", "bokeh"):  # the cluster's own chatter; failures reach the table
        logging.getLogger(name).setLevel(logging.ERROR)
    out_root = Path(out_root)
    (out_root / "logs").mkdir(parents=True, exist_ok=True)
    results: dict[int, LogResult] = {}
    todo = []
    for i, log in enumerate(logs):
        out_dir = out_root / "logs" / log_key(log)
        doc = finished(log, out_dir) if Path(log).is_file() else None
        if doc is not None:
            results[i] = _row_from(log, doc, "skipped", out_dir)
            if progress is not None:
                progress.update()
        else:
            todo.append(i)
    if todo:
        cluster = None
        if address is None:
            n = workers or max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1)
            cluster = LocalCluster(n_workers=min(n, len(todo)), threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR,
                                   scheduler_kwargs={"dashboard": False})
        try:
            with Client(cluster if cluster is not None else address) as client:
                futures = {client.submit(replay_one, str(logs[i]), str(out_root), build, key=f"prml2-log-{i}-"
                                         f"{log_key(logs[i])}", pure=False): i for i in todo}
                failed = 0
                for fut in as_completed(futures):
                    i = futures[fut]
                    try:
                        res = LogResult(**fut.result())
                    except Exception as exc:  # the task never raises; this is the worker dying under it
                        res = LogResult(str(logs[i]), "failed", reason=f"worker lost: {first_line(exc, 200)}")
                    results[i] = res
                    failed += res.status == "failed"
                    if progress is not None:
                        progress.set_postfix(f"{failed} failed" if failed else "")
                        progress.update()
        finally:
            if cluster is not None:
                cluster.close()
    ordered = [results[i] for i in range(len(logs))]
    return ordered, write_table(ordered, out_root)
