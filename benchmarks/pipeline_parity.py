"""Does a hot-path change keep the numbers? Every output of the replay pipeline on three drives, against a dump.

Three seeded 120 s simulated drives (GNSS for the first 40 s; the second and third with the soak benchmark's
rotating faults, the third with its plausible lies too), each through the real ``Pipeline`` with calibration on
and off. The shipped model runs once per drive and its outputs are replayed call by call
(``evaluation.models.ReplayModel``), so two commits see the same model outputs and only the code outside the
model can differ. Every step's pose, covariance, calibration state, status and flags, and the run summary
(less what depends on the clock), are written to ``--out``; ``--against`` compares with an earlier dump (made
by the base commit: run it with that commit's package on ``PYTHONPATH``) and exits 1 on any difference.

Usage::

    PYTHONPATH=/path/to/base/worktree python benchmarks/pipeline_parity.py --out base.pkl
    python benchmarks/pipeline_parity.py --out new.pkl --against base.pkl
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from prml2_edge.bench.replay_input import DEFAULT_MAP, read_frames, simulate_log
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.evaluation.models import RecordingModel, ReplayModel
from prml2_edge.runtime.inference import OnnxModel, default_model_path
from prml2_edge.runtime.pipeline import MemorySink, Pipeline
from prml2_edge.testing.faults import fault_schedule, inject

DRIVES = ((0, False, False), (1, True, False), (2, True, True))  # (seed, faults, plausible lies)
_CLOCK_WORDS = ("wall", "latency", "_ms", "realtime", "speed", "cpu")


def _clockless(d):
    """The summary less what depends on the clock (wall time, latency, throughput) and on where the package lies
    (a file path is kept by its name)."""
    if isinstance(d, dict):
        return {k: _clockless(v) for k, v in d.items() if not any(w in k for w in _CLOCK_WORDS)}
    if isinstance(d, str) and "/" in d and Path(d).suffix:
        return Path(d).name
    return d


def drive_frames(seed: int, faults: bool, lies: bool, seconds: float = 120.0):
    """(frames, initial pose) of one seeded drive, with the soak benchmark's faults when asked."""
    with tempfile.TemporaryDirectory(prefix="prml2-parity-") as tmp:
        path, pose, dur = simulate_log(seconds, Path(tmp) / "drive.log", seed, gnss_seconds=40.0)
        frames = read_frames(path)
    if faults:
        _, db, _ = load_map_and_dbc(shipped_map_path(DEFAULT_MAP))
        frames = list(inject(frames, fault_schedule(dur, period_s=20.0, start_s=10.0, lies=lies), db, seed=seed))
    return frames, pose


def dump(onnx: OnnxModel) -> dict:
    """``{(seed, calibration): {"arrays": ..., "summary": ...}}`` for every drive."""
    out = {}
    for seed, faults, lies in DRIVES:
        frames, pose = drive_frames(seed, faults, lies)
        for cal in (True, False):
            pipe = Pipeline.build(model=onnx, initial_pose=pose, calibration=cal)
            rec = RecordingModel(onnx)
            pipe.localizer.estimator.model = rec
            for f in frames:
                pipe.step(f)
            sink = MemorySink()
            pipe = Pipeline.build(model=onnx, initial_pose=pose, sinks=[sink], calibration=cal)
            pipe.localizer.estimator.model = ReplayModel(rec.records, onnx.metadata, onnx.window_len,
                                                         onnx.decoder_len)
            for f in frames:
                pipe.step(f)
            out[(seed, cal)] = {"arrays": sink.arrays(),
                                "summary": json.dumps(_clockless(pipe.summary()), sort_keys=True, default=str)}
            print(f"drive {seed} (faults {faults}, lies {lies}), calibration {cal}: {len(sink.t_s)} steps", flush=True)
    return out


def compare(ref: dict, new: dict) -> float | None:
    """Largest absolute difference over every array (None: something other than a number differs)."""
    worst: float | None = 0.0
    for key in ref:
        for name, a in ref[key]["arrays"].items():
            a, b = a.astype(float), new[key]["arrays"][name].astype(float)
            if a.shape != b.shape or not np.array_equal(np.isnan(a), np.isnan(b)):
                print(f"{key} {name}: shapes or missing values differ")
                worst = None
                continue
            d = float(np.nanmax(np.abs(a - b))) if a.size and not np.isnan(a).all() else 0.0
            if d:
                print(f"{key} {name}: max |difference| {d:.3g}")
            worst = None if worst is None else max(worst, d)
        if ref[key]["summary"] != new[key]["summary"]:
            print(f"{key}: the run summary differs")
            worst = None
    return worst


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="write this run's outputs here (pickle)")
    ap.add_argument("--against", default=None, help="an earlier --out to compare with")
    args = ap.parse_args(argv)
    if args.against is not None and not Path(args.against).is_file():
        print(f"pipeline_parity: {args.against}: no such dump; make it first with --out (at the base commit)",
              file=sys.stderr)
        return 1
    warnings.simplefilter("ignore")
    out = dump(OnnxModel(default_model_path(), threads=1))
    Path(args.out).write_bytes(pickle.dumps(out))
    if args.against is None:
        return 0
    worst = compare(pickle.loads(Path(args.against).read_bytes()), out)
    print("identical" if worst == 0.0 else f"DIFFERENT (max |difference| {worst})")
    return 0 if worst == 0.0 else 1


if __name__ == "__main__":
    sys.exit(main())
