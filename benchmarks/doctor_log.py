"""``prml2 doctor --log`` over many simulated drives: does it name the culprit and the fix for each mistake a
user makes in a signal map, stay quiet on clean logs, and say NOT VERIFIED (never OK) where a drive cannot
check a sign?

For every shipped map and each of ``--drives`` simulated drives (``mixed``, ``lateral``, ``highway`` (gentle
bends, never stops) and a dead-straight highway drive, in turn; ``--minutes`` each; seeds from 7000, not the
benchmark recipe's), the drive is encoded with the shipped map and its DBC (opendbc's for the production maps,
from ``../shared/dbc/opendbc``), then checked with the right map and with each mistake of
:mod:`prml2_edge.testing.map_mistakes`: the yaw rate, lateral acceleration or steering sign flipped, a wheel
speed in km/h declared as m/s, the yaw-rate message absent from the bus. Outcomes:

* clean log: ``ok`` (verdict OK), ``not_verified`` (NOT VERIFIED: a check had too little to go on) or
  ``false_alarm`` (FAIL);
* a mistake: ``caught`` (the culprit among the failures with a fix and nothing else failing; for the absent
  message, what depends on it may fail too), ``caught_with_others``, ``not_verified`` (the culprit's check
  could not run and the verdict is NOT VERIFIED) or ``missed`` (OK, or a FAIL that does not name the culprit).

A straight drive must come out ``not_verified`` for the clean log and every sign mistake. The run fails (exit
1) on any false alarm, miss, or a straight drive called anything but NOT VERIFIED.

Usage::

    .venv/bin/python benchmarks/doctor_log.py [--drives 20] [--minutes 1.5] [--maps prml2_onboard,...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import write_json
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import SHIPPED_MAPS, load_map_and_dbc, shipped_map_path
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.service.log_doctor import NOT_VERIFIED, OK, LogReport, check_log_file, culprits
from prml2_edge.testing.map_mistakes import MISTAKES, drop_message, expected_culprit, straight_drive, wrong_map

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "doctor_log.json"
SHARED = HERE.parent.parent / "shared"
OPENDBC = {"vw_mqb": "vw_mqb.dbc", "hyundai_2015_ccan": "hyundai_2015_ccan.dbc",
           "toyota_rav4_2018": "toyota_new_mc_pt_generated.dbc"}
SEED0 = 7000
FAMILIES = ("mixed", "lateral", "highway", "straight")
OUTCOMES = ("ok", "not_verified", "false_alarm", "caught", "caught_with_others", "missed")


def outcome(report: LogReport, mistake: str) -> str:
    """What ``doctor --log`` made of ``mistake`` ("clean": none) on one log (one of :data:`OUTCOMES`)."""
    if mistake == "clean":
        return {OK: "ok", NOT_VERIFIED: "not_verified"}.get(report.verdict, "false_alarm")
    want = expected_culprit(mistake)
    found = culprits(report)
    if any(sig == want and fix for sig, fix in found):
        alone = all(sig == want for sig, _ in found) or mistake == "message_absent"
        return "caught" if alone else "caught_with_others"
    if report.verdict == NOT_VERIFIED and want in [f.signal for f in report.unverified]:
        return "not_verified"
    return "missed"


def is_miss(case: dict) -> bool:
    if case["family"] == "straight" and (case["mistake"] == "clean" or case["mistake"].startswith("flip_")):
        return case["outcome"] != "not_verified"
    return case["outcome"] in ("false_alarm", "missed")


def _drives(n: int, minutes: float) -> list:
    out = []
    for k in range(n):
        family = FAMILIES[k % len(FAMILIES)]
        drive = straight_drive(minutes, SEED0 + k) if family == "straight" else \
            simulate_drive(minutes, 1.0, SEED0 + k, family=family)
        out.append((family, drive))
    return out


def _check_map(name: str, drives: list, shared: Path, tmp: Path) -> list[dict]:
    """Every drive encoded with map ``name``, checked clean and with each mistake: one case per check."""
    dbc = shared / "dbc" / "opendbc" / OPENDBC[name] if name in OPENDBC else None
    smap, db, _ = load_map_and_dbc(shipped_map_path(name), dbc)
    yaw = next(s for s in smap.signals if s.name == "yaw_rate_radps")
    yaw_id = db.get_message_by_name(yaw.message).frame_id
    maps_for = {m: wrong_map(shipped_map_path(name), m, tmp / f"{name}_{m}.toml") for m in MISTAKES}
    cases = []
    for k, (family, drive) in enumerate(drives):
        log, absent = tmp / f"{name}_{k}.log", tmp / f"{name}_{k}_absent.log"
        encode_drive_to_log(drive, log, signal_map_path=shipped_map_path(name), dbc_path=dbc)
        drop_message(log, absent, yaw_id)
        for mistake in ("clean", *MISTAKES):
            used_map = shipped_map_path(name) if mistake == "clean" else maps_for[mistake]
            report = check_log_file(absent if mistake == "message_absent" else log, used_map, dbc)
            cases.append({"map": name, "drive": drive.name, "family": family, "mistake": mistake,
                          "verdict": report.verdict, "outcome": outcome(report, mistake),
                          "failures": culprits(report), "unverified": [f.signal for f in report.unverified]})
        log.unlink()
        absent.unlink()
    return cases


def _tally(cases: list[dict]) -> dict:
    tally: dict[str, dict[str, int]] = {}
    for c in cases:
        t = tally.setdefault(c["mistake"], {"n": 0})
        t["n"] += 1
        t[c["outcome"]] = t.get(c["outcome"], 0) + 1
    return tally


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int, default=20, help="drives per map (families in turn: "
                    f"{', '.join(FAMILIES)})")
    ap.add_argument("--minutes", type=float, default=1.5)
    ap.add_argument("--maps", default=",".join(SHIPPED_MAPS))
    ap.add_argument("--shared", default=str(SHARED))
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    t0 = time.time()
    maps = [m for m in args.maps.split(",") if m]
    results: dict[str, dict] = {}
    cases: list[dict] = []
    drives = _drives(args.drives, args.minutes)
    with tempfile.TemporaryDirectory(prefix="prml2-doctor-") as tmp:
        for name in maps:
            found = _check_map(name, drives, Path(args.shared), Path(tmp))
            cases += found
            results[name] = _tally(found)
            line = "; ".join(f"{k}: " + ", ".join(f"{o} {v[o]}" for o in OUTCOMES if o in v)
                             for k, v in results[name].items())
            print(f"{name:<18} {line}", flush=True)
    misses = [c for c in cases if is_miss(c)]
    out = {"benchmark": "doctor_log", "drives": args.drives, "minutes": args.minutes, "families": FAMILIES,
           "maps": maps, "outcomes": OUTCOMES, "wall_s": time.time() - t0, "machine": machine_info(),
           "results": results, "misses": misses}
    out_path = write_json(out, args.out)
    print(f"{time.time() - t0:.0f} s; {len(misses)} miss(es); wrote {out_path}")
    return 1 if misses else 0


if __name__ == "__main__":
    sys.exit(main())
