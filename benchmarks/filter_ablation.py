"""Ablation of the runtime filter's design choices, validation and test in one run (issue 26).

The model runs once per 60 s window (``prml2_edge.evaluation.protocol.run_window``, recording its outputs);
every filter variant then replays those outputs (``ReplayModel``: the model's z never depends on the filter),
so each row differs from the next by one choice only, on the same windows. A variant whose model reads its inputs
less the cue estimator's offsets (``model_inputs_from_cues``) replays the outputs of a second run that read them
so. Variants:

* ``paper filter``: the paper's 8-state EKF on the model's z (``calibration off``);
* ``previous default``: the calibrating filter as shipped before issue 26's redesign (the model's omega_z carries
  the whole CAN yaw-rate offset, its slow error a 0.2 deg/s Gauss-Markov state of 5 s, its variance times the
  metadata's 5 s mean-error inflation);
* ``model omega_z ignored``: the same with the model's omega_z variance times 1e8 (gyro and wheels carry the yaw);
* ``+ offset share 0``: the model's omega_z does not carry the offset, so gyro minus model measures it;
* ``+ slow error 0.3 deg/s, 60 s``: the model's slow error state as measured on validation;
* ``+ fast part inflated 5e4``: step by step the gyro carries the yaw rate;
* ``+ coarse gyro: metadata inflation``: next to a CAN yaw rate measured coarse (>= 0.2 deg/s resolution) the
  model's omega_z variance only times the metadata's 5 s factor: there the quantisation error is slow and the
  model carries the yaw rate step by step;
* ``+ coarse gyro: model held to the reading's interval``: there the model's omega_z is also held within half a
  resolution step and 3 sigma of the reading less the offset estimate (the runtime's default before the gain);
* ``+ gyro gain learned over the unit's earlier drives``: the CAN yaw rate divided by ``1 +`` the gain its
  calibration file learned from GNSS heading on 20 min of the car's earlier drives
  (``prml2_edge.evaluation.unit_history``, ``runtime/yaw_gain.py``; the runtime's default before the cues). Every
  row above has the gain calibration off;
* ``+ the gyro's offset from the other cues while driving``: a_y / v, the rear wheels and the steering, each with an
  offset of its own, tell the CAN yaw rate's offset on straights (``runtime/cue_offset.py``), every drive starting
  the cues' own offsets from their priors. Every row above has it off;
* ``+ the cues' own offsets kept from the unit's earlier drives``: the cue estimator starts from the offsets it
  learned on the same 20 min of the car's earlier drives (``evaluation.unit_history.cue_evidence``; the runtime's
  default).

Every calibrated row also starts from the wheel scale the car's simulated earlier drives taught its calibration file
(``evaluation.unit_history.wheel_scale_evidence``), except ``the default without the wheel scale from the unit's
earlier drives``.

Beside OSD, ``OSD, gyro gain from the unit's earlier drives``: the OSD baseline on the CAN yaw rate divided by the
same learned gain, as a model-free filter with the same calibration file would run.

Bounds, not runtime options: the same windows with the CAN yaw rate divided by ``1 + g``, ``g`` the gyro gain error
the simulator drew for the drive (``sensor_errors.yaw_scale_error``), as a gain calibration that knew it would
correct the gyro cue (the model still reads the raw signal: its recorded outputs are replayed unchanged). Rows: OSD
and the default with ``g`` known exactly, and the default with ``g`` known to 0.3 % (a per-drive draw, seeded by the
drive's name). They say what a gyro gain calibration is worth; nothing in the runtime estimates ``g`` today.

Every calibrated variant starts from the standstill offset the OSD baseline subtracts (a car's calibration file, its
between-drive floor 0.05 deg/s); one row instead from the stop as the runtime's own standstill update would know it
(``evaluation/standstill_restore.py``).
The OSD baseline is tuned on the validation split (``tune_osd``) and is the reference of every ratio and of the
paired intervals (``paired_comparison``: mean of variant - OSD RMSE per window, bootstrap 95 %). Protocols: the
paper's (from the true pose, no GNSS) and the deployment protocol (30 s of GNSS first).

Usage::

    .venv/bin/python benchmarks/filter_ablation.py --data data/bench --model export/default/prml2_edge.onnx \\
        [--splits val test] [--jobs 2] [--max-windows N] [--history-min 20] [--protocols paper deployment]
        [--variant "no wheel scale from GNSS:scale_min_speed_mps=1e9"] [--history-drive-at-mean]
    .venv/bin/python benchmarks/render_tables.py
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from prml2_edge.bench.results import announce, finish
from prml2_edge.data.datasets import load_dataset
from prml2_edge.evaluation import unit_history
from prml2_edge.evaluation.metrics import coverage, coverage_text, dr_summary, paired_comparison, paired_text
from prml2_edge.evaluation.models import RecordingModel, ReplayModel
from prml2_edge.evaluation.protocol import (
    DEPLOYMENT_PREROLL_S,
    InMemorySplits,
    ModelSpec,
    build_model,
    filter_override,
    model_reads_cues,
    run_all,
    run_window,
    split_tasks,
)
from prml2_edge.evaluation.standstill_restore import STANDSTILL_RESTORES
from prml2_edge.evaluation.tuning import tune_osd
from prml2_edge.evaluation.unit_history import HISTORY_MINUTES
from prml2_edge.progress import Progress
from prml2_edge.runtime.yaw_gain import YawGainEstimator
from prml2_edge.schema import SIGNAL_BY_NAME

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "filter_ablation.json"
OSD = "OSD-Baseline"
DEG = np.pi / 180.0
HELD = "+ coarse gyro: model held to the reading's interval"
GAIN = "+ gyro gain learned over the unit's earlier drives"
CUE = "+ the gyro's offset from the other cues while driving"
DEFAULT = "+ the cues' own offsets kept from the unit's earlier drives (the runtime's default)"
OSD_GAIN = "OSD, gyro gain from the unit's earlier drives"
# the standstill's offset as the runtime's own stop leaves it (evaluation/standstill_restore.py), not with the file's
# floor: measured on validation, a wash (docs/ablation.md), so the benchmark keeps the file's floor
STOOD = "the default, the stop's offset as the runtime's standstill update knows it"
# the cue estimator started at the window (the benchmark's way before 2026-12-07): a runtime running since the
# drive's start has fed it the drive's minutes before the window (ModelSpec.cue_drive_so_far, docs/ablation.md)
WINDOW_START_ROW = "the default, the cue estimator from the window's start (before)"
# a coarse gyro's offset from its blocks alone, as before 2026-12-07 (no grid of the intervals its readings allow)
NO_GRID = ("cue_offset_coarse_min_step_radps", float("inf"))
NO_GRID_ROW = "the default, a coarse gyro's offset from its blocks alone (before)"


NO_COARSE = ("coarse_yaw_resolution_radps", float("inf"))  # the coarse-gyro inflation off
NO_HOLD = ("coarse_model_clamp_sigma", None)  # the coarse-gyro hold off
NO_GAIN = ("yaw_gain_calibration", False)  # the learned gyro gain off
NO_CUE = ("cue_offset", False)  # the gyro's offset not told from a_y / v, the wheels and the steering (cue_offset.py)
NO_RESTORE = ("cue_offset_restore", False)  # every drive starts the cues' own offsets from their priors
NO_SLIDE = ("slide_accel_mps2", None)  # the slide monitor off (runtime/slide.py); every other row has it
NO_SLIDE_ROW = "the default without the slide monitor"
NO_LOW_MU = ("low_mu_model_var_scale", 1.0)  # the model's variance not inflated on a low-mu road; every other row is
NO_LOW_MU_ROW = "the default without the low-μ variance (× 10)"
NO_SLIP = ("low_mu_slip_gain", 0.0)  # no along-track slip uncertainty on a low-mu road
NO_SLIP_ROW = "the default without the low-μ slip uncertainty"
REAR_CUE = ("driven_axle", "front")  # the wheel cue from the rear axle on every car (as before: a RWD car's driven one)
REAR_CUE_ROW = "the default with the rear-axle wheel cue on every car"
NO_SCALE_HISTORY_ROW = "the default without the wheel scale from the unit's earlier drives"
QUANT_12 = ("yaw_cue_quant_gain", 12.0)  # the yaw cue's sigma 12 x its step, the default before the course fixes
QUANT_12_ROW = "the default with the yaw cue's sigma 12 × its step (before)"
COURSE_AS_YAW = ("gnss_course_sideslip", False)  # a fix's course fused as the yaw (deployment protocol only)
COURSE_AS_YAW_ROW = "the default fusing the GNSS course as the yaw"
FINE_UNTIL = ("coarse_until_fine_step", False)  # a coarse gyro counts as fine until 200 readings measure it
FINE_UNTIL_ROW = "the default counting a gyro fine until its resolution is measured (before)"
CONFIGURED_RES = ("resolution_from_steps", False)  # until measured, the configured 1.28 deg/s, not the steps seen
CONFIGURED_RES_ROW = "the default taking the configured resolution until it is measured (before)"
GAIN_RESIDUAL = 0.003  # the gain known to 0.3 % (1 sigma)
BOUNDS = {"bound: OSD, the drive's gyro gain known": (OSD, 0.0),
          "bound: the default, the drive's gyro gain known": (HELD, 0.0),
          "bound: the default, the gyro gain known to 0.3 %": (HELD, GAIN_RESIDUAL)}
PREVIOUS = (("model_offset_share", 1.0), ("cal_model_bias_tau_s", 5.0),
            ("cal_model_bias_std_radps", 0.2 * DEG), ("model_omega_var_inflation", None), NO_COARSE, NO_GAIN, NO_CUE)


def variants(model: str) -> dict[str, ModelSpec]:
    base = ModelSpec("PRML2", "onnx", model)
    cal = replace(base, calibration=True)
    prev = dict(PREVIOUS)
    return {"paper filter": base,
            "previous default (+cal, offset share 1, slow error 0.2 °/s 5 s, metadata inflation)":
                replace(cal, filter=PREVIOUS),
            "model ω_z ignored (inflation 1e8)": replace(cal, filter=tuple({**prev, "model_omega_var_inflation": 1e8}
                                                                        .items())),
            "+ offset share 0": replace(cal, filter=tuple({**prev, "model_offset_share": 0.0}.items())),
            "+ slow error 0.3 °/s, 60 s": replace(cal, filter=tuple({**prev, "model_offset_share": 0.0,
                                                                    "cal_model_bias_tau_s": 60.0,
                                                                    "cal_model_bias_std_radps": 0.3 * DEG}.items())),
            "+ fast part inflated 5e4": replace(cal, filter=(NO_COARSE, NO_GAIN, NO_CUE)),
            "+ coarse gyro: metadata inflation": replace(cal, filter=(NO_HOLD, NO_GAIN, NO_CUE)),
            HELD: replace(cal, filter=(NO_GAIN, NO_CUE)),
            GAIN: replace(cal, filter=(NO_CUE,)),
            CUE: replace(cal, filter=(NO_RESTORE,)),
            DEFAULT: cal,
            NO_SLIDE_ROW: replace(cal, filter=(NO_SLIDE,)),
            NO_LOW_MU_ROW: replace(cal, filter=(NO_LOW_MU,)),
            NO_SLIP_ROW: replace(cal, filter=(NO_SLIP,)),
            REAR_CUE_ROW: replace(cal, filter=(REAR_CUE,)),
            NO_SCALE_HISTORY_ROW: replace(cal, wheel_scale_history=False),
            QUANT_12_ROW: replace(cal, filter=(QUANT_12,)),
            COURSE_AS_YAW_ROW: replace(cal, filter=(COURSE_AS_YAW,)),
            FINE_UNTIL_ROW: replace(cal, filter=(FINE_UNTIL,)),
            CONFIGURED_RES_ROW: replace(cal, filter=(CONFIGURED_RES,)),
            STOOD: replace(cal, standstill_restore="runtime"),
            WINDOW_START_ROW: replace(cal, cue_drive_so_far=False),
            NO_GRID_ROW: replace(cal, filter=(NO_GRID,))}


PROTOCOLS = {"paper": 0.0, "deployment": DEPLOYMENT_PREROLL_S}
SNOW_VAL = "snow_val"
DRY_VAL = "dry_val"
RESIM_SEED = 100_000  # added to each drive's seed: new roads, the same car, family, mu and length
# the re-simulated validation splits: which drives of the manifest they take (role, split; the held-out car's not)
RESIMULATED = {SNOW_VAL: ("snow", None), DRY_VAL: ("dry", "test")}


def resimulated(manifest: dict, name: str) -> InMemorySplits:
    """A validation split simulated again from the manifest with other seeds, so that a choice is made without the
    test drives: ``snow_val`` (the snow drives) or ``dry_val`` (the fleet's dry test drives: standstill-calibrated,
    like test, unlike val's real-car drives)."""
    from prml2_edge.data.simulate import simulate_drive

    role, split = RESIMULATED[name]
    heldout = set(manifest.get("recipe", {}).get("heldout", [])) if isinstance(manifest.get("recipe"), dict) else set()
    picked = [d for d in manifest["drives"] if d.get("role") == role and (split is None or d.get("split") == split)
              and d.get("vehicle", "reference") not in heldout]
    return InMemorySplits({name: [simulate_drive(d["minutes"], d["mu"], int(d["seed"]) + RESIM_SEED, d["family"],
                                                 name=f"{d['name']}_val", vehicle=d.get("vehicle", "reference"))
                                  for d in picked]})


def variant_arg(text: str) -> tuple[str, tuple[tuple[str, float], ...], dict]:
    """``--variant "LABEL:FIELD=VALUE[,FIELD=VALUE]"``: the runtime's default with numeric LocalizerConfig fields
    changed (:func:`~prml2_edge.evaluation.protocol.filter_override`), ``standstill_restore=runtime|file`` (how
    the benchmark restores the stop's offset, :mod:`~prml2_edge.evaluation.standstill_restore`) and
    ``cue_drive_so_far=0|1`` (whether the cue estimator has run over the drive before the window), as an extra row
    (a diagnosis replayed on the same recorded outputs)."""
    label, sep, body = text.rpartition(":")
    if not sep or not label:
        raise argparse.ArgumentTypeError(f"{text!r}: want 'LABEL:FIELD=NUMBER[,FIELD=NUMBER]'")
    pairs, spec = [], {}
    try:
        for item in body.split(","):
            name, _, value = item.partition("=")
            if name == "standstill_restore":
                if value not in STANDSTILL_RESTORES:
                    raise ValueError(f"{item!r}: standstill_restore is one of {', '.join(STANDSTILL_RESTORES)}")
                spec[name] = value
            elif name == "cue_drive_so_far":
                if value not in ("0", "1"):
                    raise ValueError(f"{item!r}: cue_drive_so_far is 0 or 1")
                spec[name] = value == "1"
            else:
                pairs.append(filter_override(item))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"--variant {label!r}: {e}") from None
    return label, tuple(pairs), spec


def extra_variants(model: str, extra: list) -> dict[str, ModelSpec]:
    """The ``--variant`` rows: the runtime's default (calibration on, gain learned) with their overrides."""
    cal = ModelSpec("PRML2", "onnx", model, calibration=True)
    return {label: replace(cal, filter=pairs, **spec) for label, pairs, spec in extra}


def gain_known(task, gain: float, residual: float):
    """``task`` with its CAN yaw rate divided by ``1 +`` the gain error a calibration would know: the drawn ``gain``
    plus a normal error of std ``residual`` drawn per drive (seeded by its name, so every window of a drive and every
    run agree)."""
    est = gain
    if residual:
        est += float(np.random.default_rng(zlib.crc32(task.drive.encode())).normal(0.0, residual))
    onboard = task.onboard.copy()
    onboard[:, SIGNAL_BY_NAME["yaw_rate_radps"].index] /= 1.0 + est
    return replace(task, onboard=onboard)


def _one_task(args):
    """Worker: the model once on ``task`` per way of reading its inputs (raw, or less the cues' offsets:
    ``model_reads_cues``), every variant on the recorded outputs of its way, then the bounds (``bounds``: name ->
    (spec, gain, residual)); an OSD spec runs itself."""
    specs, task, bounds = args
    recorded: dict[bool, RecordingModel] = {}  # the model's outputs, by whether it read the cues' offsets out

    def run(spec, this_task):
        if spec.kind == "osd":
            return run_window(spec, this_task)
        reads = model_reads_cues(spec)
        if reads not in recorded:
            recorded[reads] = RecordingModel(build_model(spec, task.bias))
            return run_window(spec, this_task, model=recorded[reads])
        return run_window(spec, this_task, model=ReplayModel(recorded[reads].records, recorded[reads].metadata))

    out = {name: run(spec, task) for name, spec in specs.items()}
    for name, (spec, gain, residual) in bounds.items():
        out[name] = run(spec, gain_known(task, gain, residual))
    return out


def bound_specs(specs: dict[str, ModelSpec], osd_spec: ModelSpec, gains: dict[str, float], task) -> dict:
    """The rows on a corrected gyro for ``task``: name -> (spec, gain, residual): the bounds with the drive's drawn
    gain error, and OSD with the gain its unit's history taught (0 for a coarse gyro: its gain is not learned)."""
    learned = YawGainEstimator(1.0)
    if task.yaw_gain is not None:
        learned.restore(*task.yaw_gain)
    out = {OSD_GAIN: (osd_spec, learned.gain, 0.0)}
    if task.drive in gains:
        out.update({name: (osd_spec if ref == OSD else specs[ref], gains[task.drive], residual)
                    for name, (ref, residual) in BOUNDS.items()})
    return out


def run_split(tasks, specs: dict[str, ModelSpec], jobs: int, label: str, bounds=lambda task: {}) -> dict[str, list]:
    results: dict[str, list] = {name: [] for name in specs}
    bar = Progress(len(tasks), desc=f"ablation {label}", unit="win")
    pairs = [(specs, t, bounds(t)) for t in tasks]
    if jobs <= 1:
        outs = map(_one_task, pairs)
    else:
        import multiprocessing as mp
        pool = ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork" if os.name == "posix" else "spawn"))
        outs = pool.map(_one_task, pairs, chunksize=1)
    for out in outs:
        for name, res in out.items():
            results.setdefault(name, []).append(res)
        bar.update()
    bar.close()
    return results


def summarise(results: dict[str, list], osd: list, extra: tuple[str, ...] = ()) -> dict:
    """Per row: RMSE, drift, coverage, paired against OSD (and OSD with the same gain); the ``extra`` rows (the
    ``--variant`` ones) also paired against the default, the choice they would replace."""
    out = {}
    ref = dr_summary(osd)["rmse_mean_m"]
    for name, res in {OSD: osd, **results}.items():
        s = dr_summary(res)
        cov = coverage(res)
        out[name] = {"rmse_mean_m": s["rmse_mean_m"], "drift_mean_pct": s["drift_mean_pct"], "n_windows": len(res),
                     "ratio_to_osd": s["rmse_mean_m"] / ref, "coverage_pct": cov,
                     "paired_vs_osd": None if name == OSD else paired_comparison(osd, res),
                     "per_car": per_car(res, osd)}
        if OSD_GAIN in results and name != OSD_GAIN and name in (DEFAULT, CUE, GAIN, HELD):  # vs OSD, same gain
            out[name]["paired_vs_osd_gain"] = paired_comparison(results[OSD_GAIN], res)
        if (name in extra or name in (CUE, STOOD, WINDOW_START_ROW)) and DEFAULT in results:  # CUE: the step the
            # default took last; STOOD, WINDOW_START_ROW: the benchmark's other ways to start a window
            out[name]["paired_vs_default"] = paired_comparison(results[DEFAULT], res)
    return out


def car_of(key: str) -> str:
    """The car of a window key ``split/<car>_<split>_<n>@start``."""
    return key.split("/", 1)[1].rsplit("_", 2)[0]


def by_car(res: list) -> dict[str, list]:
    """Window results grouped by their car (:func:`car_of` their key), cars in order."""
    out: dict[str, list] = {}
    for r in res:
        out.setdefault(car_of(r.task_key), []).append(r)
    return dict(sorted(out.items()))


def per_car(res: list, osd: list) -> dict:
    """RMSE [m] and its ratio to OSD's on the same car's windows."""
    mine = by_car(res)
    out = {}
    for car, ref in by_car(osd).items():
        rmse = float(np.mean([r.rmse_m for r in mine[car]]))
        out[car] = {"rmse_mean_m": rmse, "ratio_to_osd": rmse / float(np.mean([r.rmse_m for r in ref])),
                    "paired_vs_osd": paired_comparison(ref, mine[car])}
    return out


def check_replay_is_exact(specs: dict[str, ModelSpec], task) -> float:
    """Largest position difference [m] between the default variant on replayed outputs and on the model itself."""
    spec = specs[DEFAULT]
    rec = RecordingModel(build_model(spec, task.bias))
    direct = run_window(spec, task, model=rec)
    replayed = run_window(spec, task, model=ReplayModel(rec.records, rec.metadata))
    return float(np.max(np.abs(replayed.pose - direct.pose)))


def measure(args: argparse.Namespace) -> dict:
    dataset = load_dataset(args.data)
    specs = variants(args.model) | extra_variants(args.model, args.variant)
    val = split_tasks(dataset, "val", max_windows=args.max_windows)
    osd_spec = tune_osd(ModelSpec(OSD, "osd"), val, jobs=args.jobs)
    gains = {d.name: float(d.meta["sensor_errors"]["yaw_scale_error"]) for d in dataset.drives
             if "yaw_scale_error" in d.meta.get("sensor_errors", {})}
    extra = {n: resimulated(dataset.manifest, n) for n in RESIMULATED if n in args.splits}
    doc = {"data": str(args.data), "model": str(args.model), "osd_q_scale": osd_spec.q_scale,
           "history_min": args.history_min, "history_drive_draw": unit_history.DRIVE_DRAW, "splits": {}}
    for split in args.splits:
        for protocol, pre in ((p, PROTOCOLS[p]) for p in args.protocols):
            source = extra.get(split, dataset)
            tasks = split_tasks(source, split, max_windows=args.max_windows, preroll_s=pre,
                                history_min=args.history_min)
            if not tasks:
                continue
            if "replay_exact_max_m" not in doc:
                doc["replay_exact_max_m"] = check_replay_is_exact(specs, tasks[0])
            osd = run_all([osd_spec], tasks, jobs=args.jobs)[OSD]
            res = run_split(tasks, specs, args.jobs, split,
                            bounds=lambda t: bound_specs(specs, osd_spec, gains, t))
            if any(len(r) != len(tasks) for r in res.values()):  # a drive without its drawn gain: no bound rows
                res = {n: r for n, r in res.items() if len(r) == len(tasks)}
            extra_rows = tuple(label for label, *_ in args.variant)
            doc["splits"][f"{split} / {protocol}"] = summarise(res, osd, extra=extra_rows)
    return doc


def markdown(doc: dict) -> list[str]:
    out = [f"60 s position RMSE [m] (× OSD), drift, 2σ / 3σ coverage; model `{Path(doc['model']).name}` on "
           f"`{doc['data']}`. Paired: mean of (variant − OSD) RMSE per window with its bootstrap 95 % interval.", "",
           "| split / protocol | filter | RMSE m (× OSD) | drift % | paired vs OSD m | 2σ / 3σ % | windows |",
           "|---|---|---|---:|---|---|---:|"]
    for key, rows in doc["splits"].items():
        for name, r in rows.items():
            paired = paired_text(r["paired_vs_osd"])
            c = coverage_text(r["coverage_pct"])
            out.append(f"| {key} | {name} | {r['rmse_mean_m']:.2f} ({r['ratio_to_osd']:.2f}×) | "
                       f"{r['drift_mean_pct']:.2f} | {paired} | {c} | {r['n_windows']} |")
    out += car_table(doc) + same_gain_table(doc) + against_default_table(doc)
    out += ["", f"Replay check: the default filter on replayed outputs against the model itself, largest position "
            f"difference {doc.get('replay_exact_max_m', float('nan')):.1e} m. OSD Q scale {doc['osd_q_scale']:g} "
            f"(tuned on val). {doc['wall_s']:.0f} s."]
    return out


def same_gain_table(doc: dict) -> list[str]:
    """The filters against OSD given the same learned gain (what the model adds beyond the calibration file)."""
    rows = [(key, name, r) for key, split in doc["splits"].items() for name, r in split.items()
            if "paired_vs_osd_gain" in r]
    if not rows:
        return []
    out = ["", "Against OSD with the same learned gyro gain (mean of (filter − OSD with gain) RMSE per window [m], "
           "95 %):", "", "| split / protocol | filter | RMSE m | OSD with the gain m | ratio | paired m |",
           "|---|---|---:|---:|---:|---|"]
    for key, name, r in rows:
        ref = doc["splits"][key][OSD_GAIN]["rmse_mean_m"]
        out.append(f"| {key} | {name} | {r['rmse_mean_m']:.2f} | {ref:.2f} | {r['rmse_mean_m'] / ref:.2f}× | "
                   f"{paired_text(r['paired_vs_osd_gain'])} |")
    return out


def against_default_table(doc: dict) -> list[str]:
    """The ``--variant`` rows against the runtime's default on the same windows (what choosing them would change)."""
    rows = [(key, name, r) for key, split in doc["splits"].items() for name, r in split.items()
            if "paired_vs_default" in r]
    if not rows:
        return []
    out = ["", "The extra variants against the default (mean of (variant − default) RMSE per window [m], 95 %):", "",
           "| split / protocol | variant | RMSE m | the default m | paired m | variant better on |",
           "|---|---|---:|---:|---|---:|"]
    for key, name, r in rows:
        p = r["paired_vs_default"]
        out.append(f"| {key} | {name} | {r['rmse_mean_m']:.2f} | {doc['splits'][key][DEFAULT]['rmse_mean_m']:.2f} | "
                   f"{paired_text(p)} | {100 * (1 - p['reference_wins']):.0f} % |")
    return out


def car_table(doc: dict) -> list[str]:
    """Per car: OSD's RMSE and the default's and the previous default's ratio to it, paired interval [m]. The
    default is the row the run named so (a JSON of an earlier run renders with its own default)."""
    names = list(next(iter(doc["splits"].values())))
    prev = next(n for n in names if n.startswith("previous default"))
    default = next(n for n in names if n.endswith("(the runtime's default)"))
    known = "bound: the default, the drive's gyro gain known"
    extra = [n for n in (OSD_GAIN, known) if n in names]  # absent in older runs
    heads = {OSD_GAIN: " OSD, learned gain |", known: " the default, gain known |"}
    out = ["", "Per car, 60 s RMSE × OSD on the same car's windows (paired difference to OSD [m], 95 %):", "",
           "| split / protocol | car | OSD m | the default | previous default |" + "".join(heads[n] for n in extra),
           "|---|---|---:|---|---|" + "---|" * len(extra)]
    for key, rows in doc["splits"].items():
        for car, ref in rows[OSD]["per_car"].items():
            cells = []
            for name in (default, prev, *extra):
                if name not in rows:  # a row run on some splits only (the bounds: not on snow_val)
                    cells.append("–")
                    continue
                c = rows[name]["per_car"][car]
                lo, hi = c["paired_vs_osd"]["rmse_diff_ci95_m"]
                cells.append(f"{c['ratio_to_osd']:.2f}× [{lo:+.1f}, {hi:+.1f}]")
            out.append(f"| {key} | {car} | {ref['rmse_mean_m']:.1f} | " + " | ".join(cells) + " |")
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(HERE.parent / "data" / "bench"))
    p.add_argument("--model", default=str(HERE.parent / "export" / "default" / "prml2_edge.onnx"))
    p.add_argument("--splits", nargs="+", default=["val", "test"],
                   help=f"val, test, snow, heldout, {SNOW_VAL} or {DRY_VAL} (the snow drives, or the fleet's dry test "
                        "drives, simulated again with other seeds: validation splits like snow and test)")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--max-windows", type=int, default=None, help="at most N windows per drive segment")
    p.add_argument("--history-min", type=float, default=HISTORY_MINUTES,
                   help="minutes of the car's earlier drives behind its calibration file's gyro gain (0: none)")
    p.add_argument("--history-drive-at-mean", action="store_true",
                   help="the car's earlier drives vary about the evaluated drive's gain and cue offsets (before "
                        "2026-12-07; default: the drive is one draw about its car, unit_history.DRIVE_DRAW)")
    p.add_argument("--variant", action="append", default=[], type=variant_arg, metavar="LABEL:FIELD=VALUE,...",
                   help="an extra row: the default with these LocalizerConfig fields changed (repeatable)")
    p.add_argument("--protocols", nargs="+", choices=tuple(PROTOCOLS), default=list(PROTOCOLS),
                   help="which protocols to run (default both)")
    p.add_argument("--out", default=str(OUT), help=f"result JSON (default {OUT.relative_to(HERE.parent)})")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    unit_history.DRIVE_DRAW = not args.history_drive_at_mean  # before any history is simulated (split_tasks)
    doc = {"machine": announce("filter_ablation"), **measure(args)}
    finish(doc, args.out, markdown, t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
