"""Replay throughput: a 10-minute drive through the runtime as fast as possible; x real time and RSS.

The drive (seeded simulator) is encoded to a candump log and replayed, in one run, on both schedules:

* **streaming**, exactly as ``prml2 replay`` does: :class:`~prml2_edge.runtime.source.LogReplay` (a
  feeder thread and a python-can virtual bus) -> :func:`~prml2_edge.runtime.pipeline.run_source` ->
  :class:`Pipeline` with the edge model at ``--stride`` (default: the runtime's) (the reference);
* **offline**, as ``prml2 replay --batch`` does (:func:`~prml2_edge.runtime.offline.run_offline`), fp32
  with 2 inference worker processes and in-thread, and with the int8 graph (``bench_models.py``);
  the z RMSE against the drive's ground truth of each precision is reported with the change against fp32.

Then the model alone: per-window time and output difference of batched ``session.run`` calls (a copy of
the graph with a free batch dimension) against one window per call. RSS (``/proc/self/status`` VmRSS)
is sampled every ``--rss-every`` frames; "flat" means it grows by at most ``targets.RSS_GROWTH_FRACTION``
over the second half of the run.

Usage::

    .venv/bin/python benchmarks/replay_throughput.py [--minutes 10] [--threads 1] [--modes ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge.bench.latency import build_pipeline, open_session_model
from prml2_edge.bench.machine import load_average, load_label, machine_info
from prml2_edge.bench.replay_input import simulate_log
from prml2_edge.config import DEFAULT_STRIDE
from prml2_edge.runtime.offline import run_offline
from prml2_edge.runtime.pipeline import Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.schema import STATE_NAMES

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


def cpu_s() -> tuple[float, float]:
    """CPU time so far [s]: (this process, its reaped children: the offline path's inference workers)."""
    t = os.times()
    return t.user + t.system, t.children_user + t.children_system


def cpu_fields(before: tuple[float, float], wall_s: float, duration_s: float) -> dict:
    """CPU seconds of a run (this process and its workers), and what they allow on 2 idle cores: the work
    spread over both cores, but never faster than this process's own share (its main thread is serial)."""
    after = cpu_s()
    own, workers = after[0] - before[0], after[1] - before[1]
    total = own + workers
    bound = max(total / 2.0, own)
    return {"cpu_s": total, "cpu_s_this_process": own, "cpu_s_workers": workers,
            "cpu_ms_per_driven_s": 1e3 * total / duration_s, "cpu_utilisation": total / wall_s,
            "x_realtime_2_idle_cores_from_cpu": duration_s / bound}


def children_rss_mib() -> float:
    """RSS of this process's child processes [MiB] (the offline path's inference workers; Linux)."""
    total = 0.0
    for children in Path("/proc/self/task").glob("*/children"):
        for pid in children.read_text().split():
            try:
                for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) / 1024.0
            except OSError:
                continue
    return total


class _RssProgress:
    """A ``progress`` for :func:`run_source` that samples RSS every ``every`` frames."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.frames = 0
        self.samples: list[tuple[int, float, float]] = []  # (frames, wall s, RSS MiB)
        self.children_peak_mib = 0.0
        self.t0 = time.perf_counter()

    def update(self, n: int = 1) -> None:
        before, self.frames = self.frames, self.frames + n
        if self.frames // self.every > before // self.every:  # crossed a multiple (the offline path counts pieces)
            self.samples.append((self.frames, time.perf_counter() - self.t0, rss_mib()))
            self.children_peak_mib = max(self.children_peak_mib, children_rss_mib())


class _ZSink:
    """The model's z at every step it drove the filter (row index -> z), for the RMSE against the ground truth."""

    def __init__(self) -> None:
        self.k = -1
        self.z: dict[int, np.ndarray] = {}

    def step(self, out) -> None:
        self.k += 1
        if out.model_used and out.z is not None:
            self.z[self.k] = np.asarray(out.z, dtype=np.float64)

    def close(self) -> None:
        pass


def z_rmse(sink: _ZSink, z_gt: np.ndarray) -> dict:
    """RMSE per state of the model's z against the drive's ground truth on the rows the model drove."""
    rows = np.array(sorted(k for k in sink.z if k < len(z_gt)), dtype=np.int64)
    z = np.stack([sink.z[k] for k in rows])
    err = z - z_gt[rows]
    return {"n_rows": int(len(rows)), "rmse": dict(zip(STATE_NAMES, np.sqrt(np.mean(err ** 2, axis=0)).tolist(),
                                                       strict=True))}


def _load_fields(load0: list[float] | None) -> dict:
    """The 1-min load averages at a run's start and end, and "idle" or "loaded (load X -> Y)" from them."""
    load1 = load_average()
    return {"load_average": [load0, load1], "load": load_label(load0, load1)}


def offline_once(log_path: Path, pose, duration_s: float, model_path: str, threads: int, workers: int,
                 rss_every: int, label: str, stride: int = DEFAULT_STRIDE) -> tuple[dict, _ZSink]:
    """One offline replay (``prml2 replay --batch``): throughput, time per stage, RSS."""
    zs = _ZSink()
    pipeline = Pipeline.build(model=open_session_model(model_path, threads=threads), initial_pose=pose, sinks=[zs],
                              stride=stride)
    progress = _RssProgress(rss_every)
    rss0 = rss_mib()
    load0 = load_average()
    c0 = cpu_s()
    t0 = time.perf_counter()
    res = run_offline(pipeline, log_path, workers=workers, progress=progress)
    wall_s = time.perf_counter() - t0
    cpu = cpu_fields(c0, wall_s, duration_s)
    summ = pipeline.summary()
    rss = [s[2] for s in progress.samples] or [rss0]
    half = rss[len(rss) // 2]
    growth = rss[-1] - half
    per_row = {k: 1e3 * v / max(res.rows, 1) for k, v in res.timing_s.items()}
    return {
        "mode": label, "threads": threads, "workers": workers, "stride": stride, "frames_received": res.frames,
        "source_error": res.problem, "rows": summ["rows"], "inferences": summ["inferences"],
        "frames_balanced": summ["frames"]["balanced"], "wall_s": wall_s, "x_realtime": duration_s / wall_s,
        "rows_per_s": summ["rows"] / wall_s, "per_row_ms": per_row, **_load_fields(load0),
        "model": pipeline.offline["model"], **cpu,
        "rss": {"before_mib": rss0, "start_mib": rss[0], "half_mib": half, "end_mib": rss[-1], "peak_mib": max(rss),
                "workers_peak_mib": progress.children_peak_mib, "second_half_growth_mib": growth,
                "second_half_growth_fraction": growth / half, "flat": growth / half <= targets.RSS_GROWTH_FRACTION},
    }, zs


def replay_once(log_path: Path, pose, duration_s: float, model_path: str, threads: int, rss_every: int,
                stride: int = DEFAULT_STRIDE) -> dict:
    """One replay of the whole log: throughput, where the time per row goes, RSS over the run."""
    pipeline = build_pipeline(open_session_model(model_path, threads=threads), pose, stride=stride)
    progress = _RssProgress(rss_every)
    rss0 = rss_mib()
    load0 = load_average()
    c0 = cpu_s()
    t0 = time.perf_counter()
    with LogReplay(log_path) as source:
        run_source(pipeline, source, progress=progress)
        sent, received, error = source.sent, source.received, source.error
    wall_s = time.perf_counter() - t0
    cpu = cpu_fields(c0, wall_s, duration_s)
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
        "mode": "streaming", "threads": threads, "stride": stride, "frames_sent": sent, "frames_received": received,
        "source_error": error,
        "rows": summ["rows"], "inferences": summ["inferences"], "frames_balanced": summ["frames"]["balanced"],
        "wall_s": wall_s, "x_realtime": duration_s / wall_s, "rows_per_s": summ["rows"] / wall_s,
        "frames_per_s": received / wall_s, "per_row_ms": per_row, **_load_fields(load0),
        "latency": lat, **cpu,
        "rss": {"before_mib": rss0, "start_mib": rss[0], "half_mib": half, "end_mib": rss[-1], "peak_mib": max(rss),
                "second_half_growth_mib": growth, "second_half_growth_fraction": growth / half,
                "flat": growth / half <= targets.RSS_GROWTH_FRACTION,
                "samples": [{"frames": f, "wall_s": round(w, 3), "rss_mib": round(r, 2)}
                            for f, w, r in progress.samples]},
    }


def free_batch_copy(src: str, dst: Path) -> Path:
    """A copy of the ONNX graph ``src`` with a free batch dimension (needs the onnx package: train extra).

    Every Reshape target of a ``prml2 export`` graph starts with the batch size 1; it becomes -1."""
    import onnx
    from onnx import numpy_helper

    m = onnx.load(src)
    g = m.graph
    for vi in list(g.input) + list(g.output):
        d = vi.type.tensor_type.shape.dim[0]
        d.ClearField("dim_value")
        d.dim_param = "batch"
    consts = {n.output[0]: n for n in g.node if n.op_type == "Constant"}
    inits = {t.name: t for t in g.initializer}
    for n in g.node:
        if n.op_type != "Reshape":
            continue
        holder = consts.get(n.input[1])
        t = holder.attribute[0].t if holder is not None else inits[n.input[1]]
        shape = numpy_helper.to_array(t).copy()
        if shape[0] != 1:
            raise ValueError(f"Reshape {n.name}: target {shape.tolist()} does not start with the batch")
        shape[0] = -1
        t.CopyFrom(numpy_helper.from_array(shape, t.name))
    del g.value_info[:]
    onnx.checker.check_model(m)
    onnx.save(m, str(dst))
    return dst


def batch_calls(model_path: str, log_path: Path, threads_list: list[int], sizes=(1, 8, 32, 128),
                seconds: float = 2.0) -> dict:
    """Per-window model time of ``session.run`` on B windows at once, and the outputs' difference from one
    window per call (real windows of the replayed log)."""
    import onnxruntime as ort

    from prml2_edge.runtime.inference import session_options
    from prml2_edge.runtime.offline import read_chunks

    dst = LOG_DIR / (Path(model_path).stem + "_free_batch.onnx")
    free_batch_copy(model_path, dst)
    # real windows: the first 2 minutes of the log, assembled by the runtime's stages
    from prml2_edge.can.signal_map import load_map_and_dbc, resolve_map
    from prml2_edge.runtime.assembler import Assembler
    from prml2_edge.runtime.decode import FrameDecoder

    smap, db, _ = load_map_and_dbc(resolve_map("prml2_onboard"))
    dec, asm = FrameDecoder(smap, db), Assembler.for_map(smap)
    rows = []
    for frames, _ in read_chunks(log_path):
        for msg in frames:
            rows += asm.step(dec.step(msg))[1]
        if len(rows) > 6000:
            break
    values = np.asarray([r.values for r in rows], dtype=np.float32)
    L = 250
    windows = np.stack([values[i - L + 1:i + 1] for i in range(L - 1, L - 1 + max(sizes))])
    out = {"graph": str(dst), "runs": []}
    for threads in threads_list:
        ref_sess = ort.InferenceSession(model_path, session_options(threads), providers=["CPUExecutionProvider"])
        ref = np.stack([ref_sess.run(None, {"onboard": w[None]})[0][0, -1] for w in windows])
        sess = ort.InferenceSession(str(dst), session_options(threads), providers=["CPUExecutionProvider"])
        for b in sizes:
            x = np.ascontiguousarray(windows[:b])
            got = np.concatenate([sess.run(None, {"onboard": x})[0][:, -1] for _ in range(1)])
            diff = float(np.abs(got - ref[:b]).max())
            n, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                sess.run(None, {"onboard": x})
                n += 1
            ms = 1e3 * (time.perf_counter() - t0) / n / b
            out["runs"].append({"threads": threads, "batch": b, "ms_per_window": ms, "max_abs_diff_vs_1": diff,
                                "bitwise_equal": bool(np.array_equal(got, ref[:b]))})
            print(f"  model alone, {threads} thread(s), {b} window(s) per call: {ms:.3f} ms/window; "
                  f"max |z - z(one per call)| {diff:.2e}{' (bitwise equal)' if diff == 0 else ''}")
    return out


def _run_modes(args, modes: list[str], bm: dict, log_path: Path, pose, duration_s: float, z_gt: np.ndarray):
    """Every replay mode asked for, in order: (runs, z sinks by offline mode, the batched-call result or None)."""
    runs, zsinks, batch = [], {}, None
    for mode in modes:
        if mode == "streaming":
            for n in [int(t) for t in args.threads.split(",")]:
                r = replay_once(log_path, pose, duration_s, bm["fp32"], n, args.rss_every, args.stride)
                runs.append(r)
                rss = r["rss"]
                print(f"streaming, {n} thread(s): replayed {args.minutes:g} min ({r['frames_sent']} frames, "
                      f"{r['rows']} rows) in {r['wall_s']:.1f} s: {r['x_realtime']:.1f} x real time; RSS "
                      f"{rss['start_mib']:.0f} -> {rss['half_mib']:.0f} -> {rss['end_mib']:.0f} MiB; CPU "
                      f"{r['cpu_ms_per_driven_s']:.1f} ms per driven s (2 idle cores would give "
                      f"{r['x_realtime_2_idle_cores_from_cpu']:.1f} x); per row [ms]: "
                      + ", ".join(f"{k} {v:.3f}" for k, v in r["per_row_ms"].items()) + f"; {r['load']}")
        elif mode.startswith("offline"):
            workers = int(mode.removeprefix("offline").split("-")[0])
            precision = "int8" if mode.endswith("-int8") else "fp32"
            r, zs = offline_once(log_path, pose, duration_s, bm[precision], 1, workers, args.rss_every, mode,
                                 args.stride)
            r["precision"] = precision
            r["z"] = z_rmse(zs, z_gt)
            zsinks[mode] = zs
            runs.append(r)
            rss = r["rss"]
            print(f"{mode} ({precision}, {workers} worker(s)): {r['wall_s']:.1f} s: {r['x_realtime']:.1f} x real time; "
                  f"RSS {rss['start_mib']:.0f} -> {rss['end_mib']:.0f} MiB (peak {rss['peak_mib']:.0f}; worker "
                  f"processes {rss['workers_peak_mib']:.0f} MiB); CPU {r['cpu_ms_per_driven_s']:.1f} ms per driven s "
                  f"(2 idle cores would give {r['x_realtime_2_idle_cores_from_cpu']:.1f} x); "
                  "per row [ms]: " + ", ".join(f"{k} {v:.3f}" for k, v in r["per_row_ms"].items()) + f"; {r['load']}")
        elif mode == "batch":
            batch = batch_calls(bm["fp32"], log_path, [1, 2])
        else:
            raise SystemExit(f"unknown mode {mode!r}")
    return runs, zsinks, batch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="drive length [min]")
    ap.add_argument("--model", default="edge", help="edge or paper (benchmarks/bench_models.py)")
    ap.add_argument("--threads", default="1", help="onnxruntime intra-op thread counts, one streaming replay each")
    ap.add_argument("--modes", default="streaming,offline2,offline1,offline2-int8,batch",
                    help="comma separated: streaming, offline2 / offline1 (fp32, 2 worker processes / in-thread), "
                         "offline2-int8, batch (the model alone, batched calls)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stride", type=int, default=DEFAULT_STRIDE,
                    help=f"a new model window every N 50 Hz steps (default {DEFAULT_STRIDE}, the runtime's)")
    ap.add_argument("--checkpoint", default=None, help="trained checkpoint to export and use (see bench_models.py)")
    ap.add_argument("--rss-every", type=int, default=5000, help="frames between RSS samples")
    ap.add_argument("--out", default=str(HERE / "results" / "replay.json"))
    args = ap.parse_args(argv)

    t_start = time.time()
    machine = machine_info()
    print(f"machine: {machine.get('cpu_model')}, {machine.get('cores_usable')} usable cores, flags "
          f"{' '.join(machine.get('flags') or [])}; load average at start {machine.get('load_average')}")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bm = prepared_paths(args.model, seed=args.seed, checkpoint=args.checkpoint)  # torch stays out of this process
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    log_path = LOG_DIR / f"replay_{args.minutes:g}min_s{args.seed}.log"
    log_path, pose, duration_s = simulate_log(args.minutes * 60.0, log_path, seed=args.seed)
    from prml2_edge.data.simulate import simulate_drive

    z_gt = simulate_drive(args.minutes, 1.0, args.seed, "mixed").z_gt  # the drive simulate_log encoded
    runs, zsinks, batch = _run_modes(args, modes, bm, log_path, pose, duration_s, z_gt)
    fp32 = next((r for r in runs if r.get("precision") == "fp32"), None)
    for r in runs:
        if r.get("precision") == "int8" and fp32 is not None:
            r["z_rmse_change"] = {k: v / fp32["z"]["rmse"][k] - 1.0 for k, v in r["z"]["rmse"].items()}
            print(f"{r['mode']}: z RMSE change vs fp32: "
                  + ", ".join(f"{k} {100 * v:+.2f} %" for k, v in r["z_rmse_change"].items()))
    stream = next((r for r in runs if r["mode"] == "streaming"), None)
    if stream is not None:
        for r in runs:
            r["x_vs_streaming"] = r["x_realtime"] / stream["x_realtime"]
    end = _load_fields(machine.get("load_average"))
    print(f"load average at end {end['load_average'][1]}: {end['load']}")
    doc = {
        "benchmark": "replay",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t_start)),
        "machine": machine, "load_average_end": end["load_average"][1], "load": end["load"],
        "model": args.model, "model_source": bm["source"], "torch_imported": "torch" in sys.modules,
        "drive_minutes": args.minutes, "data_s": duration_s, "log": str(log_path), "runs": runs,
        "batch_calls": batch,
    }
    out = report.save(doc, args.out)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
