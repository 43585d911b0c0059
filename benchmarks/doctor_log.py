"""``prml2 doctor --log`` over many simulated drives: does it name the culprit and the fix for each mistake a
user makes in a signal map, and stay quiet on clean logs?

For every shipped map and each of ``--drives`` simulated drives (mixed and lateral families, alternating;
``--minutes`` each; seeds from 7000, not the benchmark recipe's), the drive is encoded with the shipped map
and its DBC (opendbc's for the production maps, from ``../shared/dbc/opendbc``), then checked with:
the right map (a clean log: any failure is a false alarm), and each mistake of
:mod:`prml2_edge.testing.map_mistakes`: the yaw rate, lateral acceleration or steering sign flipped, a
wheel speed in km/h declared as m/s, the yaw-rate message absent from the bus. A mistake counts as caught
when the culprit signal is among the failures with a fix; "only culprit" when nothing else failed.

Usage::

    .venv/bin/python benchmarks/doctor_log.py [--drives 20] [--minutes 1.5] [--maps prml2_onboard,...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from prml2_edge.bench.machine import machine_info
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import SHIPPED_MAPS, load_map_and_dbc, shipped_map_path
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.service.log_doctor import check_log_file, culprits
from prml2_edge.testing.map_mistakes import MISTAKES, drop_message, expected_culprit, wrong_map

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "doctor_log.json"
SHARED = HERE.parent.parent / "shared"
OPENDBC = {"vw_mqb": "vw_mqb.dbc", "hyundai_2015_ccan": "hyundai_2015_ccan.dbc",
           "toyota_rav4_2018": "toyota_new_mc_pt_generated.dbc"}
SEED0 = 7000


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=1.5)
    ap.add_argument("--maps", default=",".join(SHIPPED_MAPS))
    ap.add_argument("--shared", default=str(SHARED))
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    t0 = time.time()
    maps = [m for m in args.maps.split(",") if m]
    results: dict[str, dict] = {}
    cases = []
    with tempfile.TemporaryDirectory(prefix="prml2-doctor-") as tmp:
        tmp = Path(tmp)
        drives = [simulate_drive(args.minutes, 1.0, SEED0 + k, family=("mixed", "lateral")[k % 2])
                  for k in range(args.drives)]
        for name in maps:
            dbc = Path(args.shared) / "dbc" / "opendbc" / OPENDBC[name] if name in OPENDBC else None
            smap, db, _ = load_map_and_dbc(shipped_map_path(name), dbc)
            yaw = next(s for s in smap.signals if s.name == "yaw_rate_radps")
            yaw_id = db.get_message_by_name(yaw.message).frame_id
            maps_for = {m: wrong_map(shipped_map_path(name), m, tmp / f"{name}_{m}.toml") for m in MISTAKES}
            tally = {k: {"caught": 0, "only_culprit": 0, "n": 0} for k in ("clean", *MISTAKES)}
            for k, drive in enumerate(drives):
                log = tmp / f"{name}_{k}.log"
                encode_drive_to_log(drive, log, signal_map_path=shipped_map_path(name), dbc_path=dbc)
                report = check_log_file(log, shipped_map_path(name), dbc)
                found = culprits(report)
                tally["clean"]["n"] += 1
                tally["clean"]["caught"] += int(not found)  # "caught" = no false alarm on a clean log
                tally["clean"]["only_culprit"] += int(not found)
                cases.append({"map": name, "drive": drive.name, "mistake": "clean", "failures": found})
                absent = tmp / f"{name}_{k}_absent.log"
                drop_message(log, absent, yaw_id)
                for mistake in MISTAKES:
                    report = check_log_file(absent if mistake == "message_absent" else log, maps_for[mistake], dbc)
                    found = culprits(report)
                    want = expected_culprit(mistake)
                    hit = any(sig == want and fix for sig, fix in found)
                    only = hit and (all(sig == want for sig, _ in found) or mistake == "message_absent")
                    t = tally[mistake]
                    t["n"] += 1
                    t["caught"] += int(hit)
                    t["only_culprit"] += int(only)
                    cases.append({"map": name, "drive": drive.name, "mistake": mistake, "failures": found})
                log.unlink()
                absent.unlink()
            results[name] = tally
            line = ", ".join(f"{k} {v['caught']}/{v['n']}" for k, v in tally.items())
            print(f"{name:<18} {line}", flush=True)
    out = {"benchmark": "doctor_log", "drives": args.drives, "minutes": args.minutes, "maps": maps,
           "wall_s": time.time() - t0, "machine": machine_info(), "results": results,
           "misses": [c for c in cases if (c["mistake"] == "clean") == bool(c["failures"])
                      or (c["mistake"] != "clean" and expected_culprit(c["mistake"]) not in
                          [s for s, _ in c["failures"]])]}
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"{time.time() - t0:.0f} s; wrote {out_path}")
    misses = out["misses"]
    return 1 if misses else 0


if __name__ == "__main__":
    sys.exit(main())
