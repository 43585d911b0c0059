"""``prml2 doctor``'s warm-inference check as a measurement: its p50/p99 over repeated checks, and how often a
check on this box reports p99 over the 20 ms step (and fails).

The check (``prml2_edge.service.doctor.check_model``) loads the model, warms it up and times ``--runs`` single
windows; its verdict is a timing on whatever else the box is doing, so the tests only check that it reports one
(``tests/service/test_service_doctor.py``) and the figure lives here. Each repeat is one full check, as
``prml2 doctor`` runs it (a fresh ONNX Runtime session); the load average is recorded before and after.

Usage::

    .venv/bin/python benchmarks/doctor_inference.py [--repeats 20] [--runs 50] [--model PATH] [--threads N]
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge.bench.machine import load_average, machine_info
from prml2_edge.config import RuntimeConfig, with_overrides
from prml2_edge.service.doctor import DEADLINE_MS, PASS, check_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "doctor_inference.json"
# the check's detail line: "50 runs after warm-up: p50 1.23 ms, p99 4.56 ms on CPUExecutionProvider"
TIMING = re.compile(r"p50 (?P<p50>[0-9.]+) ms, p99 (?P<p99>[0-9.]+) ms on (?P<provider>\S+)")


def one_check(cfg: RuntimeConfig, runs: int) -> dict:
    """One warm-inference check: its result, p50 and p99 [ms] and the provider it ran on."""
    warm = check_model(cfg, runs=runs)[-1]
    m = TIMING.search(warm.detail)
    if warm.name != "warm inference" or m is None:
        raise SystemExit(f"the doctor's model check did not time the model: {warm.name}: {warm.detail}")
    return {"result": warm.result, "p50_ms": float(m["p50"]), "p99_ms": float(m["p99"]), "provider": m["provider"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20, help="full checks to run (default 20)")
    ap.add_argument("--runs", type=int, default=50, help="timed windows per check (default 50, the doctor's)")
    ap.add_argument("--model", help="ONNX model (default: the shipped one, as prml2 doctor)")
    ap.add_argument("--threads", type=int, help="ONNX Runtime intra-op threads (default: the runtime config's)")
    ap.add_argument("--out", default=str(OUT), help=f"result JSON (default {OUT.relative_to(HERE.parent)})")
    args = ap.parse_args(argv)
    cfg = with_overrides(RuntimeConfig(), model={"path": args.model, "threads": args.threads})
    load_before = load_average()
    t0 = time.time()
    checks = []
    for i in range(args.repeats):
        c = one_check(cfg, args.runs)
        checks.append(c)
        print(f"check {i + 1:>3}/{args.repeats}: p50 {c['p50_ms']:6.2f} ms, p99 {c['p99_ms']:6.2f} ms  {c['result']}",
              flush=True)
    p50 = np.array([c["p50_ms"] for c in checks])
    p99 = np.array([c["p99_ms"] for c in checks])
    failed = sum(c["result"] != PASS for c in checks)
    summary = {"p50_ms_median": float(np.median(p50)), "p99_ms_median": float(np.median(p99)),
               "p99_ms_max": float(p99.max()), "checks_over_deadline": failed, "deadline_ms": DEADLINE_MS}
    print(f"{args.repeats} checks of {args.runs} runs on {checks[0]['provider']}: p50 median "
          f"{summary['p50_ms_median']:.2f} ms, p99 median {summary['p99_ms_median']:.2f} ms, max "
          f"{summary['p99_ms_max']:.2f} ms; {failed} over {DEADLINE_MS:.0f} ms (load before {load_before})")
    doc = {"benchmark": "doctor_inference", "model": cfg.model.path or "shipped", "runs": args.runs,
           "repeats": args.repeats, "threads": cfg.model.threads, "wall_s": time.time() - t0,
           "load_average_before": load_before, "load_average_end": load_average(), "machine": machine_info(),
           "summary": summary, "checks": checks}
    print(f"wrote {report.save(doc, args.out, update=False)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
