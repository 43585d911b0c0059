"""Fuzz benchmark: 10^6 fuzzed frames through the runtime, every one accounted for, nothing raised.

    .venv/bin/python benchmarks/fuzz.py                  # 10^6 frames, ~3 min on 2 cores
    .venv/bin/python benchmarks/fuzz.py --frames 200000

A 6 s simulated drive is encoded with the project DBC and repeated, time moving on with every pass;
each frame is genuine (55 %), mutated (25 %: flipped bits, a changed length, a hostile timestamp) or
a hostile random frame (20 %: any ID, length, payload; error and remote frames), as
:func:`prml2_edge.testing.fuzz.fuzz_stream` builds them (the test suite runs 20 000 of the same).
Frames go straight into ``Pipeline.step`` with the closed-form kinematic model of the tests (the
shipped model would only make it slower: inference does not see the frames). Pass: no exception,
``received == used + ignored + rejected``, every pose finite. Prints and saves JSON with the
rejection reasons, the plausibility flags and the messages suspected of injection (random frames with
known IDs at random times are a second sender).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import can
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--out", default=str(HERE / "results" / "fuzz.json"))
    args = ap.parse_args(argv)

    from runtime_models import make_kinematic_model  # the tests' closed-form ONNX model

    from prml2_edge.bench.machine import machine_info
    from prml2_edge.can.encode import encode_drive_to_log
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.progress import Progress
    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.runtime.initial_pose import InitialPose
    from prml2_edge.runtime.pipeline import Pipeline
    from prml2_edge.runtime.status import PoseStatus
    from prml2_edge.testing.fuzz import fuzz_stream

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        encode_drive_to_log(simulate_drive(0.1, 1.0, 9), root / "d.log", gnss_seconds=1.0)
        frames = list(can.LogReader(str(root / "d.log")))
        model = OnnxModel(make_kinematic_model(root / "k.onnx"))
        pipeline = Pipeline.build(model=model, initial_pose=InitialPose(0.0, 0.0, 0.0))
        bar = Progress(args.frames, desc="fuzz", unit="frame")
        nonfinite = rows = 0
        error = None
        t0 = time.perf_counter()
        try:
            for k, msg in enumerate(fuzz_stream(frames, args.frames, seed=args.seed)):
                for out in pipeline.step(msg):
                    rows += 1
                    if out.status is not PoseStatus.INITIALISING and not np.isfinite(out.x).all():
                        nonfinite += 1
                if k % 10_000 == 0:
                    bar.update(10_000 if k else 1)
            rows += len(pipeline.finish())
        except Exception as exc:  # the benchmark's whole point: report it, do not hide it
            error = f"{type(exc).__name__}: {exc}"
        bar.close()
        wall = time.perf_counter() - t0
    st = pipeline.stats
    summary = pipeline.summary()
    doc = {"command": "benchmarks/fuzz.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "machine": machine_info(), "frames": args.frames, "received": st.received, "used": st.used,
           "ignored": st.ignored, "rejected": st.rejected, "rejected_by_reason": st.rejected_by_reason(),
           "balanced": st.balanced() and st.received == args.frames, "rows": rows, "nonfinite_poses": nonfinite,
           "exception": error, "wall_s": round(wall, 1), "frames_per_s": round(st.received / wall),
           "plausibility_flag_episodes": summary["plausibility"].get("flag_episodes"),
           "injection_suspected": sorted(summary["injection_suspected"]),
           "clock_jumps": st.clock_jumps, "grid_resyncs": pipeline.assembler.resyncs}
    text = json.dumps(doc, indent=2, default=str)
    print(text)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text + "\n")
    ok = error is None and doc["balanced"] and nonfinite == 0
    print(f"fuzz: {st.received} frames, {'PASS' if ok else 'FAIL'}", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
