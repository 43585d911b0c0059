"""How much of an uncalibrated CAN yaw-rate offset the runtime's filter learns while driving, with no GNSS and no
standstill (issue 26).

Without a stop or a fix, the calibrating filter can learn the gyro's offset only from the gyro against the other
yaw-rate opinions it fuses: today the model's ω_z. That works only as far as the model does not pass the offset
through. This runs the runtime's default filter (``ModelSpec(calibration=True)``: the calibration file's gyro gain
and wheel scale from the car's earlier drives, no standstill offset to start from) over each whole re-simulated
drive of ``benchmarks/robustness.py`` (the recipe's dry validation or test drives, no standstill, the CAN yaw-rate
offset set to ``--offset-dps``), from the true start pose, with no fixes, and reads the filter's offset estimate
(``CalState.YAW_RATE_OFFSET``) after 0.5, 1, 2, 3 and 5 minutes. Reported: per drive, and per car the mean learned
share of the offset (1: all of it; 0: none) at each mark. The drive's own drawn offset (σ 0.05 °/s) is replaced,
so the truth is exactly ``--offset-dps`` plus the slow drift (σ 0.02 °/s).

This is the yardstick a multi-cue offset filter (the gyro against the wheels, a_y / v and the steering, each with
its own error state) would be judged on: ``benchmarks/offset_observability.py`` says what the signals allow over
these spans (0.32 °/s left of 0.4 over 60 s, 0.07 over 5 min, from the truth's straights).

Usage::

    .venv/bin/python benchmarks/offset_learning.py [--split val] [--offset-dps 0.4] [--model M.onnx]
        [--filter FIELD=VALUE ...] [--cars reference,city_fwd] [--minutes 3] [--workers 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from robustness import MODEL, filter_arg, recipe_drives, resimulate

from prml2_edge import schema
from prml2_edge.bench.results import announce, finish
from prml2_edge.data.simulate.fleet import CARS as FLEET
from prml2_edge.evaluation.protocol import InMemorySplits, ModelSpec, localizer_for, split_tasks, start_state
from prml2_edge.evaluation.unit_history import HISTORY_MINUTES
from prml2_edge.progress import Progress
from prml2_edge.schema import CalState

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "offset_learning.json"
MARKS_MIN = (0.5, 1.0, 2.0, 3.0, 5.0, 8.0)


def learn(args: tuple) -> dict:
    """Worker: one re-simulated drive through the runtime's filter with no fixes; the offset estimate at the marks."""
    spec, drive_spec, offset_dps, minutes, extend = args
    drive = resimulate(drive_spec, offset_dps, minutes, extend)
    rows = len(drive.t_s)
    window_s = (rows - schema.WINDOW_LEN) * schema.DT_S  # one window: the whole drive after the model's history
    task = split_tasks(InMemorySplits({"run": [drive]}), "run", window_s=window_s, history_min=HISTORY_MINUTES)[0]
    loc, _ = localizer_for(spec, task)
    traj = loc.run_arrays(task.onboard, start_state(task), start_index=task.history, gnss={})
    offset = CalState.NAMES.index("yaw_rate_offset_radps")  # traj.cal holds the three calibration states
    learned = np.degrees(traj.cal[task.history:, offset])
    marks = {f"{m:g}": float(learned[int(m * 60 / schema.DT_S) - 1]) for m in MARKS_MIN
             if int(m * 60 / schema.DT_S) <= len(learned)}
    return {"drive": drive.name, "car": drive_spec["vehicle"], "offset_dps": offset_dps, "learned_dps": marks,
            "minutes": rows * schema.DT_S / 60}


def summarise(drives: list[dict]) -> dict:
    """Per car and over all: the mean learned share of the offset at each mark (drives that reach it)."""
    out = {}
    for car in sorted({d["car"] for d in drives}) + ["all"]:
        mine = [d for d in drives if car in ("all", d["car"])]
        out[car] = {m: float(np.mean([d["learned_dps"][m] / d["offset_dps"] for d in mine if m in d["learned_dps"]]))
                    for m in (f"{x:g}" for x in MARKS_MIN) if any(m in d["learned_dps"] for d in mine)}
    return out


def markdown(doc: dict) -> list[str]:
    marks = [f"{m:g}" for m in MARKS_MIN]
    out = [f"Share of a {doc['offset_dps']:+g} °/s CAN yaw-rate offset the filter has learned after each span of "
           f"driving with no GNSS and no stop (model `{Path(doc['model']).name}`, {doc['split']} drives; "
           f"1 = all of it).", "",
           "| car | " + " | ".join(f"{m} min" for m in marks) + " |", "|---|" + "---:|" * len(marks)]
    for car, row in doc["by_car"].items():
        name = f"**{car}**" if car == "all" else car
        out.append(f"| {name} | " + " | ".join(f"{row[m]:.2f}" if m in row else "–" for m in marks) + " |")
    reach = [sum(m in d["learned_dps"] for d in doc["drives"]) for m in marks]
    out.append("| drives that reach it | " + " | ".join(str(n) for n in reach) + " |")
    if len(set(reach) - {0}) > 1:
        out += ["", "A later mark averages only the drives that last that long, so a column may differ from the one "
                "before it by which drives it holds, not by learning."]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(MODEL), help="ONNX model the filter fuses (default: the shipped one)")
    ap.add_argument("--offset-dps", type=float, default=0.4, help="the CAN yaw-rate offset [deg/s]")
    ap.add_argument("--split", choices=("val", "test"), default="val", help="the recipe's dry drives of this split")
    ap.add_argument("--cars", default=None, help="comma-separated cars (default: the whole fleet)")
    length = ap.add_mutually_exclusive_group()
    length.add_argument("--minutes", type=float, default=None, help="cut every drive to at most this long [min]")
    length.add_argument("--drive-minutes", type=float, default=None,
                        help="re-simulate every drive this long instead (its seed driven on; the recipe's val "
                             "drives last 3-4 min, the offset takes minutes to learn)")
    ap.add_argument("--filter", action="append", default=[], type=filter_arg, metavar="FIELD=VALUE",
                    help="a LocalizerConfig field of the runtime's filter changed (repeatable)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=str(OUT))
    args = ap.parse_args(argv)
    if args.offset_dps == 0:
        ap.error("--offset-dps 0 leaves nothing to learn: give the offset to put on the gyro, e.g. 0.4")
    if not Path(args.model).is_file():
        ap.error(f"no model file {args.model}: give the .onnx that prml2 export wrote")
    cars = args.cars.split(",") if args.cars else None
    specs = recipe_drives(cars)["test" if args.split == "test" else "val"]
    if not specs:
        ap.error(f"no {args.split} drive of --cars {args.cars!r} in the benchmark recipe; its fleet is "
                 f"{', '.join(FLEET)}")
    t0 = time.monotonic()
    machine = announce("offset_learning")
    spec = ModelSpec("PRML2", "onnx", str(args.model), calibration=True, filter=tuple(args.filter))
    if args.drive_minutes is not None and not args.drive_minutes > 0.5:
        ap.error(f"--drive-minutes {args.drive_minutes:g} reaches no mark: give more than 0.5 (the first)")
    extend = args.drive_minutes is not None
    jobs = [(spec, s, args.offset_dps, args.drive_minutes if extend else args.minutes, extend) for s in specs]
    bar = Progress(len(jobs), desc="offset learning", unit="drive")
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        drives = []
        for d in pool.map(learn, jobs):
            drives.append(d)
            bar.update()
    bar.close()
    doc = {"machine": machine, "args": vars(args), "model": str(args.model), "split": args.split,
           "offset_dps": args.offset_dps, "drives": drives, "by_car": summarise(drives)}
    finish(doc, args.json, markdown, t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
