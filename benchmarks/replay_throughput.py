"""Replay throughput: a 10-minute drive through the runtime as fast as possible; x real time and RSS.

The drive (seeded simulator) is encoded to a candump log and replayed exactly as ``prml2 replay``
does: :class:`~prml2_edge.runtime.source.LogReplay` (a feeder thread and a python-can virtual bus)
-> :func:`~prml2_edge.runtime.pipeline.run_source` -> :class:`Pipeline` with the edge model,
stride 1. RSS (``/proc/self/status`` VmRSS) is sampled every ``--rss-every`` frames; "flat" means
it grows by at most ``targets.RSS_GROWTH_FRACTION`` over the second half of the run.

Usage::

    .venv/bin/python benchmarks/replay_throughput.py [--minutes 10] [--threads 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from prml2_edge.bench.latency import build_pipeline, open_session_model
from prml2_edge.bench.machine import load_average, machine_info
from prml2_edge.bench.replay_input import simulate_log
from prml2_edge.runtime.pipeline import run_source
from prml2_edge.runtime.source import LogReplay

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402
import targets  # noqa: E402
from paths import prepared_paths  # noqa: E402

HERE = Path(__file__).resolve().parent
LOG_DIR = HERE.parent / "out" / "bench"


def rss_mib() -> float:
    """Resident set size of this process [MiB] (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


class _RssProgress:
    """A ``progress`` for :func:`run_source` that samples RSS every ``every`` frames."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.frames = 0
        self.samples: list[tuple[int, float, float]] = []  # (frames, wall s, RSS MiB)
        self.t0 = time.perf_counter()

    def update(self, n: int = 1) -> None:
        self.frames += n
        if self.frames % self.every == 0:
            self.samples.append((self.frames, time.perf_counter() - self.t0, rss_mib()))


def replay_once(log_path: Path, pose, duration_s: float, model_path: str, threads: int, rss_every: int) -> dict:
    """One replay of the whole log: throughput, where the time per row goes, RSS over the run."""
    pipeline = build_pipeline(open_session_model(model_path, threads=threads), pose)
    progress = _RssProgress(rss_every)
    rss0 = rss_mib()
    load0 = load_average()
    t0 = time.perf_counter()
    with LogReplay(log_path) as source:
        run_source(pipeline, source, progress=progress)
        sent, received, error = source.sent, source.received, source.error
    wall_s = time.perf_counter() - t0
    summ = pipeline.summary()
    rows = max(summ["rows"], 1)
    lat = summ["latency"]
    frames_per_row = received / rows
    per_row = {"infer": lat["infer"].get("mean_ms", 0.0) * summ["inferences"] / rows,
               "guard": lat["guard"].get("mean_ms", 0.0) * summ["inferences"] / rows,
               "filter": lat["filter"].get("mean_ms", 0.0),
               "decode": lat["decode"].get("mean_ms", 0.0) * frames_per_row,
               "assemble": lat["assemble"].get("mean_ms", 0.0) * frames_per_row}
    per_row["other (bus, feeder thread, Python loop)"] = 1e3 * wall_s / rows - sum(per_row.values())
    rss = [s[2] for s in progress.samples] or [rss0]
    half = rss[len(rss) // 2]
    growth = rss[-1] - half
    return {
        "threads": threads, "stride": 1, "frames_sent": sent, "frames_received": received, "source_error": error,
        "rows": summ["rows"], "inferences": summ["inferences"], "frames_balanced": summ["frames"]["balanced"],
        "wall_s": wall_s, "x_realtime": duration_s / wall_s, "rows_per_s": summ["rows"] / wall_s,
        "frames_per_s": received / wall_s, "per_row_ms": per_row, "load_average": [load0, load_average()],
        "latency": lat,
        "rss": {"before_mib": rss0, "start_mib": rss[0], "half_mib": half, "end_mib": rss[-1], "peak_mib": max(rss),
                "second_half_growth_mib": growth, "second_half_growth_fraction": growth / half,
                "flat": growth / half <= targets.RSS_GROWTH_FRACTION,
                "samples": [{"frames": f, "wall_s": round(w, 3), "rss_mib": round(r, 2)}
                            for f, w, r in progress.samples]},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="drive length [min]")
    ap.add_argument("--model", default="edge", help="edge or paper (benchmarks/bench_models.py)")
    ap.add_argument("--threads", default="1,2", help="onnxruntime intra-op thread counts, one replay each")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint", default=None, help="trained checkpoint to export and use (see bench_models.py)")
    ap.add_argument("--rss-every", type=int, default=5000, help="frames between RSS samples")
    ap.add_argument("--out", default=str(HERE / "results" / "replay.json"))
    args = ap.parse_args(argv)

    t_start = time.time()
    machine = machine_info()
    bm = prepared_paths(args.model, seed=args.seed, checkpoint=args.checkpoint)  # torch stays out of this process
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    log_path = LOG_DIR / f"replay_{args.minutes:g}min_s{args.seed}.log"
    log_path, pose, duration_s = simulate_log(args.minutes * 60.0, log_path, seed=args.seed)
    runs = []
    for n in [int(t) for t in args.threads.split(",")]:
        r = replay_once(log_path, pose, duration_s, bm["fp32"], n, args.rss_every)
        runs.append(r)
        rss = r["rss"]
        print(f"{n} thread(s): replayed {args.minutes:g} min ({r['frames_sent']} frames, {r['rows']} rows) in "
              f"{r['wall_s']:.1f} s: {r['x_realtime']:.1f} x real time; RSS {rss['start_mib']:.0f} -> "
              f"{rss['half_mib']:.0f} -> {rss['end_mib']:.0f} MiB; per row [ms]: "
              + ", ".join(f"{k} {v:.3f}" for k, v in r["per_row_ms"].items()))
    doc = {
        "benchmark": "replay",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t_start)),
        "machine": machine, "load_average_end": load_average(),
        "model": args.model, "model_source": bm["source"], "torch_imported": "torch" in sys.modules,
        "drive_minutes": args.minutes, "data_s": duration_s, "log": str(log_path), "runs": runs,
    }
    out = report.save(doc, args.out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
