"""Fleet replay: ``prml2 fleet`` over simulated logs, one of them corrupt, on a 2-worker local Dask cluster.

``--logs`` drives (seeded simulator, ``--minutes`` each; GNSS for the first 10 s, an outage, GNSS again for
the last 2 s) are encoded as candump logs, one of them cut in the middle of a line (a logger that died).
``prml2 fleet LOGS --out DIR --workers 2`` runs twice. Checked and saved (JSON with machine info): the
first run replays every good log and lists the corrupt one with its reason, each log's frame count
equals the log's own (``scan_log``), the totals add up; the second run skips every finished log (and
tries the corrupt one again). Wall time of both runs, x real time of the fleet.

Usage::

    .venv/bin/python benchmarks/fleet_replay.py [--logs 50] [--minutes 1] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from prml2_edge.bench.machine import load_average, machine_info
from prml2_edge.bench.replay_input import simulate_fleet_log
from prml2_edge.runtime.source import scan_log

sys.path.insert(0, str(Path(__file__).resolve().parent))
import report  # noqa: E402

HERE = Path(__file__).resolve().parent
WORK = HERE.parent / "out" / "bench" / "fleet"


def run_fleet(logs: list[Path], out: Path, workers: int) -> tuple[float, int, dict, str]:
    cmd = [str(Path(sys.executable).parent / "prml2"), "fleet", *map(str, logs), "--out", str(out),
           "--workers", str(workers)]
    env = {**os.environ, "PRML2_NO_PROGRESS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    doc = json.loads((out / "fleet_summary.json").read_text())
    return wall, proc.returncode, doc, proc.stdout + proc.stderr


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=int, default=50)
    ap.add_argument("--minutes", type=float, default=1.0, help="length of each drive [min]")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default=str(HERE / "results" / "fleet.json"))
    args = ap.parse_args(argv)

    t_start = time.time()
    machine = machine_info()
    print(f"machine: {machine.get('cpu_model')}, {machine.get('cores_usable')} usable cores; load {load_average()}")
    logs_dir = WORK / "logs"
    logs_dir.mkdir(parents=True, exist_ok=True)
    logs = []
    families = ("mixed", "lateral", "longitudinal")
    for i in range(args.logs):
        path = logs_dir / f"car{i:03d}.log"
        if not path.is_file() or i == args.logs // 2:  # the corrupt one is made again, then cut
            simulate_fleet_log(args.minutes * 60.0, path, seed=1000 + i, family=families[i % 3])
        logs.append(path)
    corrupt = logs[args.logs // 2]
    data = corrupt.read_bytes()
    corrupt.write_bytes(data[: len(data) // 2 - 5])  # cut mid-line
    frames = {str(p.resolve()): scan_log(p)[0] for p in logs}
    out = WORK / "run"
    if out.exists():
        import shutil

        shutil.rmtree(out)
    load0 = load_average()
    wall1, rc1, doc1, text1 = run_fleet(logs, out, args.workers)
    wall2, rc2, doc2, text2 = run_fleet(logs, out, args.workers)
    rows1 = doc1["logs"]
    ok = [r for r in rows1 if r["status"] == "ok"]
    failed = [r for r in rows1 if r["status"] == "failed"]
    checks = {
        "first run: every good log replayed": len(ok) == len(logs) - 1,
        "first run: the corrupt log listed with its reason": [Path(r["log"]).name for r in failed] == [corrupt.name]
        and "cut short" in failed[0]["reason"],
        "first run: exit status 1 (one log failed)": rc1 == 1,
        "frames per log equal the log's own": all(r["frames"] == frames[r["log"]] for r in ok),
        "totals: frames add up": doc1["totals"]["frames"] == sum(r["frames"] for r in ok),
        "totals: hours add up": abs(doc1["totals"]["hours"] - sum(r["hours"] for r in ok)) < 1e-9,
        "every frame accounted for (balanced)": all(r["extra"]["balanced"] for r in ok),
        "drift measured on every good log (GNSS after the outage)": all(r["drift_events"] >= 1 for r in ok),
        "second run: the finished logs skipped": [r["status"] for r in doc2["logs"]].count("skipped") == len(logs) - 1,
        "second run: the corrupt log tried again and listed": [Path(r["log"]).name for r in doc2["logs"]
                                                              if r["status"] == "failed"] == [corrupt.name],
    }
    data_h = doc1["totals"]["hours"]
    for name, good in checks.items():
        print(f"{'ok ' if good else 'FAIL'} {name}")
    print(f"first run: {len(logs)} logs ({data_h:.2f} h of driving) in {wall1:.1f} s on {args.workers} workers: "
          f"{3600.0 * data_h / wall1:.1f} x real time (cluster start included); second run {wall2:.1f} s")
    print("\n".join(text1.strip().splitlines()[-4:]))
    doc = {"benchmark": "fleet", "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(t_start)),
           "machine": machine, "load_average": [load0, load_average()], "logs": len(logs),
           "minutes_each": args.minutes, "workers": args.workers, "corrupt": corrupt.name,
           "first_run": {"wall_s": wall1, "rc": rc1, "totals": doc1["totals"],
                         "x_realtime": 3600.0 * data_h / wall1,
                         "failed": [{"log": Path(r["log"]).name, "reason": r["reason"]} for r in failed]},
           "second_run": {"wall_s": wall2, "rc": rc2, "totals": doc2["totals"]},
           "checks": checks, "all_checks_passed": all(checks.values())}
    path = report.save(doc, args.out, update=False)
    print(f"wrote {path}")
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
