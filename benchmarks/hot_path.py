"""Where the time goes outside the model: the runtime pipeline per 50 Hz step with the model replayed.

A seeded simulated drive (GNSS fixes for its first ``--gnss-s`` seconds) is encoded to CAN frames; the
shipped ONNX model runs once over it and its outputs are recorded; then fresh pipelines replay those
outputs call by call (``evaluation.models.ReplayModel``: the model costs nothing), so everything measured
is decode, assemble, plausibility, window, guard, filter and sinks, on exactly the frames and model
outputs of the real run. Two views:

* per row with an inference, p50/p99 of each stage from the pipeline's own
  :class:`~prml2_edge.runtime.latency.LatencyRecorder` (decode and assemble summed over the row's frames) and of
  their sum (:func:`prml2_edge.bench.latency.measure_steps`), best of ``--repeat`` replays by that sum's p50, and
  the per-row overhead ``end_to_end - infer`` (what a row's result waits for outside the model);
* ``--profile N``: cProfile's top ``N`` functions by own time, and calls per row (load-independent).

Usage::

    .venv/bin/python benchmarks/hot_path.py [--seconds 60] [--profile 25] [--json out.json]

The load average is printed before and after; figures taken above 0.3 per core are labelled "loaded".
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

from prml2_edge.bench.latency import OUTSIDE_STAGES, OUTSIDE_TARGET_MS, measure_steps
from prml2_edge.bench.machine import load_average, load_label, machine_info
from prml2_edge.bench.replay_input import read_frames, simulate_log
from prml2_edge.evaluation.models import RecordingModel, ReplayModel
from prml2_edge.runtime.inference import OnnxModel, default_model_path
from prml2_edge.runtime.pipeline import MemorySink, Pipeline


def drive_and_records(seconds: float, seed: int, gnss_s: float):
    """(frames, initial pose, the model's recorded outputs, its metadata) of one seeded drive."""
    with tempfile.TemporaryDirectory(prefix="prml2-hot-") as tmp:
        path, pose, _ = simulate_log(seconds, Path(tmp) / "drive.log", seed, gnss_seconds=gnss_s)
        frames = read_frames(path)
    onnx = OnnxModel(default_model_path(), threads=1)
    pipe = Pipeline.build(model=onnx, initial_pose=pose)
    rec = RecordingModel(onnx)
    pipe.localizer.estimator.model = rec
    for f in frames:
        pipe.step(f)
    return frames, pose, rec.records, onnx


def replay_pipeline(records, onnx, pose) -> Pipeline:
    """A fresh pipeline (a memory sink, as the demo has) whose model replays ``records``."""
    pipe = Pipeline.build(model=onnx, initial_pose=pose, sinks=[MemorySink()])
    pipe.localizer.estimator.model = ReplayModel(records, onnx.metadata, onnx.window_len, onnx.decoder_len)
    return pipe


def run(frames, records, onnx, pose, every_row: bool = False) -> tuple[Pipeline, dict]:
    """One replay; per row with an inference (or every row): each stage outside the model and their sum,
    p50/p99 [ms]."""
    pipe = replay_pipeline(records, onnx, pose)
    summ = measure_steps(pipe, frames, every_row=every_row).summary()
    out = {s: summ["outside_stage_ms"][s] for s in OUTSIDE_STAGES}
    out["outside_the_model"] = summ["outside_ms"]
    out["row_overhead"] = summ["overhead_ms"]  # end_to_end - infer: what a row's result waits for
    return pipe, out


def profile_lines(frames, records, onnx, pose, top: int, rows: int) -> list[str]:
    """cProfile's ``top`` functions by own time over one replay, with calls per row."""
    pipe = replay_pipeline(records, onnx, pose)
    prof = cProfile.Profile()
    prof.enable()
    for f in frames:
        pipe.step(f)
    prof.disable()
    buf = io.StringIO()
    stats = pstats.Stats(prof, stream=buf).sort_stats("tottime")
    total_calls = sum(v[1] for v in stats.stats.values())  # type: ignore[attr-defined]
    stats.print_stats(top)
    lines = [f"{len(frames)} frames, {rows} rows; {total_calls} function calls = {total_calls / rows:.0f} per row"]
    keep = False
    for line in buf.getvalue().splitlines():
        keep = keep or line.lstrip().startswith("ncalls")
        if keep and line.strip():
            lines.append(line.rstrip())
    return lines


def print_view(best: dict, title: str, label: str) -> None:
    """One view's table: each stage's p50/p99 and their per-row sum against the target."""
    print(f"{title} ({best['outside_the_model']['count']} rows; decode and assemble summed over the row's frames), "
          "best of the replays:")
    print(f"{'stage':<18} {'p50 ms':>8} {'p99 ms':>8}")
    for name in (*OUTSIDE_STAGES, "outside_the_model", "row_overhead"):
        print(f"{name:<18} {best[name]['p50']:>8.4f} {best[name]['p99']:>8.4f}")
    o = best["outside_the_model"]
    print(f"outside the model p50 / p99: {o['p50']:.3f} / {o['p99']:.3f} ms against {OUTSIDE_TARGET_MS['p50']} / "
          f"{OUTSIDE_TARGET_MS['p99']} ms ({label})")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="drive length [s]")
    ap.add_argument("--gnss-s", type=float, default=20.0, help="GNSS fixes on the bus for the first seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="timed replays; the best (lowest p50 sum) is reported")
    ap.add_argument("--profile", type=int, default=0, metavar="N", help="print cProfile's top N functions")
    ap.add_argument("--json", default=None, help="write the figures here")
    args = ap.parse_args(argv)
    frames, pose, records, onnx = drive_and_records(args.seconds, args.seed, args.gnss_s)
    load0, t0 = load_average(), time.time()
    print(f"load average at start {load0}", flush=True)
    best: dict[str, dict | None] = {"inference_rows": None, "every_row": None}
    for _ in range(args.repeat):  # the two views interleaved, so both see the same load
        for view in best:
            pipe, fig = run(frames, records, onnx, pose, every_row=view == "every_row")
            if best[view] is None or fig["outside_the_model"]["p50"] < best[view]["outside_the_model"]["p50"]:
                best[view] = fig
    prof = profile_lines(frames, records, onnx, pose, args.profile, pipe.rows) if args.profile else []
    load1 = load_average()
    label = load_label(load0, load1)
    print(f"load average at end {load1}: {label}")
    print_view(best["inference_rows"], "per row with an inference (the rows that wait for the model: the worst)", label)
    print_view(best["every_row"], "per 50 Hz step, every row", label)
    for line in prof:
        print(line)
    if args.json:
        doc = {"benchmark": "hot_path", "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t0)),
               "settings": vars(args), "machine": machine_info(), "load_average": [load0, load1], "load": label,
               "rows": pipe.rows, "frames": len(frames), "stages": best["inference_rows"],
               "stages_every_row": best["every_row"], "profile": prof,
               "targets_ms": OUTSIDE_TARGET_MS}
        Path(args.json).write_text(json.dumps(doc, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
