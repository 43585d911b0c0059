"""Soak benchmark: a long simulated drive with injected faults, replayed as fast as possible.

    .venv/bin/python benchmarks/soak.py --minutes 60 --json benchmarks/results/soak.json

With ``--checks both`` (the default) the same faulty log is replayed twice, the signal cross-checks
and the GNSS consistency check off (the runtime before them: the reference) and on, and the
end-to-end latency p50/p99 of the two runs is compared (target: p99 no more than 0.3 ms above the
reference). ``--lies`` (default on) adds plausible lies to the fault schedule (a yaw-rate offset, a
stuck steering wheel, a wheel reading 10 % high, a second sender).

Simulates ``--minutes`` of driving, encodes it with the project DBC (GNSS for the first 10 s),
injects one fault every ``--fault-period`` seconds (:func:`prml2_edge.testing.faults.fault_schedule`,
cycling through every fault kind), writes the faulty log and replays it through the runtime's
own path (``LogReplay`` over a python-can virtual bus -> ``Pipeline``). Reports frames/s,
rows/s, the resident set size (RSS) at the start of the replay, at every 10 % and at the end,
the frame accounting and fault counters, the pose status counts, and whether every pose was
finite. Fixed seed; JSON on stdout (and to ``--json``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import can


def rss_mib() -> float:
    """Current resident set size of this process [MiB] (Linux /proc)."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


class _CheckSink:
    """Counts steps and non-finite poses without keeping them (a memory-flat sink)."""

    def __init__(self) -> None:
        self.rows = 0
        self.nonfinite = 0
        self.max_pos_std_m = 0.0

    def step(self, out) -> None:
        self.rows += 1
        if out.x is not None and not all(math.isfinite(v) for v in out.x) and out.status.name != "INITIALISING":
            self.nonfinite += 1
        if math.isfinite(out.pos_std_m):
            self.max_pos_std_m = max(self.max_pos_std_m, out.pos_std_m)

    def close(self) -> None:
        pass


def replay_once(faulty: Path, n_total: int, args, duration_s: float, **build) -> dict:
    """One replay of the faulty log through ``LogReplay`` -> ``Pipeline``: accounting, RSS, latency, checks."""
    from prml2_edge.runtime.pipeline import Pipeline
    from prml2_edge.runtime.source import LogReplay

    sink = _CheckSink()
    pipeline = Pipeline.build(model=args.model, sinks=[sink], **build)
    rss = [("start", 0, rss_mib())]
    marks = {int(n_total * k / 10) for k in range(1, 10)}
    t_wall0 = time.monotonic()
    with LogReplay(faulty) as source:
        while True:
            msg = source.step(0.5)
            if msg is None:
                if source.finished:
                    break
                continue
            pipeline.step(msg)
            if source.received in marks:
                rss.append((f"{round(100 * source.received / n_total)} %", source.received, rss_mib()))
        pipeline.finish()
        error = source.error
    wall_s = time.monotonic() - t_wall0
    rss.append(("end", source.received, rss_mib()))
    pipeline.close()
    summary = pipeline.summary()
    fr = summary["frames"]
    e2e = summary["latency"]["end_to_end"]
    half = [v for a, _, v in rss if a == "50 %"]
    return {
        "model": summary["model"], "replay_wall_s": round(wall_s, 1), "frames": fr["received"],
        "frames_per_s": round(fr["received"] / wall_s), "rows": summary["rows"],
        "rows_per_s": round(summary["rows"] / wall_s, 1), "realtime_factor": round(duration_s / wall_s, 1),
        "e2e_p50_ms": e2e.get("p50_ms"), "e2e_p99_ms": e2e.get("p99_ms"), "e2e_count": e2e.get("count"),
        "plausibility_p99_ms": (summary["latency"].get("plausibility") or {}).get("p99_ms"),
        "rss_mib": [{"at": a, "frames": n, "rss_mib": round(v, 1)} for a, n, v in rss],
        "rss_growth_mib": round(rss[-1][2] - rss[0][2], 1),
        "rss_growth_second_half_mib": round(rss[-1][2] - half[0], 1) if half else None,
        "balanced": fr["balanced"], "used": fr["used"], "ignored": fr["ignored"], "rejected": fr["rejected"],
        "rejected_by_reason": fr["rejected_by_reason"], "error_frames": fr.get("error_frames"),
        "late_applied": fr["late_applied"], "counter_gaps": fr["counter_gaps"],
        "grid_resyncs": summary["grid_resyncs"], "steps_by_status": summary["steps_by_status"],
        "signal_faults": summary.get("signal_faults"),
        "plausibility": {k: summary["plausibility"].get(k) for k in ("flag_episodes", "substituted_rows")},
        "injection_suspected": summary.get("injection_suspected"),
        "gnss_suspect": summary.get("gnss_suspect"),
        "inferences": summary["inferences"], "inference_failures": summary["inference_failures"],
        "model_used_steps": summary["model_used_steps"],
        "ekf_resets": summary["ekf_resets"], "nonfinite_poses": sink.nonfinite,
        "max_pos_std_m": round(sink.max_pos_std_m, 2), "log_error": error,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="simulated driving time [min] (default 60)")
    parser.add_argument("--fault-period", type=float, default=60.0, help="one fault every this many seconds")
    parser.add_argument("--model", help="ONNX model (default: the shipped model)")
    parser.add_argument("--stride", type=int, default=1, help="a new model window every N rows (default 1)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--workdir", help="where the logs go (default: a temporary folder)")
    parser.add_argument("--json", default=str(Path(__file__).resolve().parent / "results" / "soak.json"),
                        help="also write the result here (default benchmarks/results/soak.json)")
    parser.add_argument("--checks", choices=("on", "off", "both"), default="both",
                        help="signal cross-checks and GNSS consistency: on, off, or both one after the other")
    parser.add_argument("--no-lies", dest="lies", action="store_false", help="only the original fault kinds")
    args = parser.parse_args(argv)

    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.can.signal_map import load_dbc
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.resources import project_dbc_path
    from prml2_edge.runtime.localizer import LocalizerConfig
    from prml2_edge.testing.faults import InjectionCounts, fault_schedule, inject

    tmp = tempfile.TemporaryDirectory() if args.workdir is None else None
    work = Path(args.workdir or tmp.name)  # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    drive = simulate_drive(args.minutes, 1.0, args.seed)
    clean = work / "soak_clean.log"
    info = encode_drive_to_log(drive, clean, gnss_seconds=10.0)
    duration_s = len(drive) * 0.02
    del drive
    faults = fault_schedule(duration_s, period_s=args.fault_period, lies=args.lies)
    faulty = work / "soak_faulty.log"
    counts = InjectionCounts()
    db = load_dbc(project_dbc_path())
    with can.LogReader(str(clean)) as reader, can.Logger(str(faulty)) as writer:
        for msg in inject(reader, faults, db, seed=args.seed, counts=counts):
            writer.on_message_received(msg)
    prep_s = time.monotonic() - t0

    from prml2_edge.bench.machine import machine_info
    from prml2_edge.runtime.plausibility import PlausibilityConfig

    runs = {}
    for setting in (("off", "on") if args.checks == "both" else (args.checks,)):
        on = setting == "on"
        runs[setting] = replay_once(faulty, counts.frames_out, args, duration_s,
                                    plausibility=PlausibilityConfig(enabled=on),
                                    localizer_config=LocalizerConfig(stride=args.stride, gnss_consistency=on))
    result = {
        "command": "benchmarks/soak.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": machine_info(), "python": platform.python_version(), "stride": args.stride,
        "drive_minutes": args.minutes, "clean_frames": info["frames"], "faults_scheduled": len(faults),
        "fault_kinds": sorted({f.kind for f in faults}), "injected": counts.as_dict(), "prepare_s": round(prep_s, 1),
        "runs": runs,
    }
    if "on" in runs and "off" in runs:
        d99 = runs["on"]["e2e_p99_ms"] - runs["off"]["e2e_p99_ms"]
        result["e2e_p99_increase_ms"] = round(d99, 3)
        result["e2e_p99_target_met"] = d99 <= 0.3
    ok = all(r["balanced"] and r["nonfinite_poses"] == 0 and r["log_error"] is None for r in runs.values())
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
