"""Where the model-free baseline's 60 s error comes from: each cue replaced by the truth, the gyro's error taken apart.

OSD's equations (wheel-speed mean as v_x, no v_y, the CAN yaw rate less its standstill offset) are integrated
directly over every 60 s window of the paper protocol (from the true pose, no GNSS), once as they are (the
reference, measured in the same run) and once with one part of them made perfect:

* ``true ω_z`` / ``true v_x`` / ``true v_y``: the simulator's truth in place of that cue;
* ``no gyro offset`` / ``no gyro scale`` / ``neither``: the CAN yaw rate less the offset left after the standstill
  calibration, less the drive's drawn gain error (``meta.json["sensor_errors"]["yaw_scale_error"]``), or both
  (the offset left is the window's mean of gyro minus truth minus the scale part);
* ``gyro slow error removed``: the gyro's error less its 10 s moving mean (only its fast part left).

A learned localiser beats OSD where it supplies what a perfect row here supplies; a row that barely moves the
error names a job the model has no reason to do. Then, per drive, **what could tell the gyro's gain** without GNSS:
the gain error left by a least-squares fit of the standstill-calibrated CAN yaw rate over the whole drive (moving
above 5 m/s and turning above 3 °/s) against ``a_y / v`` and against the rear wheels' difference over the car's
geometric track (less a fitted ``radius difference x v``), next to the drawn gain itself (what assuming 0 leaves).
Fitted over the whole drive, after the fact: an upper bound for an online estimate. And with GNSS: the same
calibrated yaw rate integrated over 10 s baselines against the GNSS heading's change over each (10 Hz fixes, 2 deg
white noise, only while moving, as ``simulated_fixes``; a constant offset left fitted beside the gain), over the
drive's first 2 and 5 minutes: how much driving a gain calibration would need.

Simulated drives only (their truth); a real car's budget differs (its lateral accelerometer reads roll, its gyro
gain is a property of the unit, not of the drive).

Usage::

    .venv/bin/python benchmarks/error_budget.py --data data/bench2 [--splits val test snow heldout]
"""

from __future__ import annotations

import argparse
import sys
import time
import zlib
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.machine import machine_info
from prml2_edge.bench.results import finish
from prml2_edge.data.datasets import load_dataset
from prml2_edge.data.simulate.fleet import CARS
from prml2_edge.evaluation.consumer_gnss import GNSS_HEADING_MIN_SPEED_MPS, GNSS_HEADING_STD_DEG, GNSS_RATE_HZ
from prml2_edge.evaluation.osd import drive_bias
from prml2_edge.evaluation.protocol import split_tasks

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "error_budget.json"
_WHEELS = list(schema.WHEEL_SPEED_INDICES)
_YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
_AY = schema.SIGNAL_BY_NAME["lat_accel_mps2"].index
_RL, _RR = _WHEELS[2], _WHEELS[3]
_SLOW_S = 10.0
GNSS_BASELINE_S = 10.0
GNSS_MINUTES = (2.0, 5.0)
CASES = ("OSD (reference)", "true ω_z", "true v_x", "true v_y", "true ω_z and v", "no gyro offset",
         "no gyro scale", "neither", "gyro slow error removed")


def integrate(omega: np.ndarray, vx: np.ndarray, vy: np.ndarray, pose0: np.ndarray) -> np.ndarray:
    """Planar dead reckoning (n, 2) from ``pose0`` = (x, y, psi), forward Euler at the schema's rate."""
    dt = schema.DT_S
    psi = pose0[2] + np.concatenate([[0.0], np.cumsum(omega[:-1]) * dt])
    c, s = np.cos(psi), np.sin(psi)
    d = np.stack([vx * c - vy * s, vx * s + vy * c], axis=1)
    return pose0[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(d[:-1], axis=0) * dt])


def window_cases(task, yaw_scale: float) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every case's (omega, v_x, v_y) over one window."""
    o = task.onboard[task.history + task.preroll:]
    g = o[:, _YAW] - task.bias.yaw_rate_radps
    v, zero = o[:, _WHEELS].mean(axis=1), np.zeros(len(o))
    w, vx, vy = task.z_gt[:, schema.Z.OMEGA_Z], task.z_gt[:, schema.Z.V_X], task.z_gt[:, schema.Z.V_Y]
    unscaled = g - yaw_scale * w
    offset = float(np.mean(unscaled - w))
    k = int(round(_SLOW_S / schema.DT_S))
    slow = np.convolve(g - w, np.ones(k) / k, mode="same")
    return {"OSD (reference)": (g, v, zero), "true ω_z": (w, v, zero), "true v_x": (g, vx, zero),
            "true v_y": (g, v, vy), "true ω_z and v": (w, vx, vy), "no gyro offset": (g - offset, v, zero),
            "no gyro scale": (unscaled, v, zero), "neither": (unscaled - offset, v, zero),
            "gyro slow error removed": (g - slow, v, zero)}


def measure_split(dataset, split: str) -> dict:
    """Mean 60 s RMSE per case, its ratio to the reference, and per car the reference and the scale-free case."""
    scales = {d.name: float(d.meta.get("sensor_errors", {}).get("yaw_scale_error", 0.0)) for d in dataset.drives}
    cars = {d.name: str(d.meta.get("vehicle", "?")) for d in dataset.drives}
    rmse: dict[str, list[float]] = {c: [] for c in CASES}
    per_car: dict[str, dict[str, list[float]]] = {}
    car_scales: dict[str, list[float]] = {}
    for task in split_tasks(dataset, split):
        car_scales.setdefault(cars[task.drive], []).append(scales[task.drive])
        for case, (w, vx, vy) in window_cases(task, scales[task.drive]).items():
            err = integrate(w, vx, vy, task.pose_gt[0]) - task.pose_gt[:, :2]
            r = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
            rmse[case].append(r)
            per_car.setdefault(cars[task.drive], {}).setdefault(case, []).append(r)
    ref = float(np.mean(rmse[CASES[0]]))
    return {"n_windows": len(rmse[CASES[0]]),
            "cases": {c: {"rmse_mean_m": float(np.mean(v)), "ratio": float(np.mean(v)) / ref} for c, v in rmse.items()},
            "per_car": {car: {c: float(np.mean(v)) for c, v in d.items()} for car, d in per_car.items()},
            "yaw_scale_error_rms_pct": {car: 100.0 * float(np.sqrt(np.mean(np.square(v))))
                                        for car, v in car_scales.items()}}


def gain_evidence(drive) -> dict[str, float] | None:
    """The drive's drawn gyro gain error and what a fit against ``a_y / v`` and the rear pair leaves of it [%]."""
    ob, car = drive.onboard, CARS.get(str(drive.meta.get("vehicle")))
    drawn = drive.meta.get("sensor_errors", {}).get("yaw_scale_error")
    if car is None or drawn is None:
        return None
    bias = drive_bias(ob, ob)
    g, v = ob[:, _YAW] - bias.yaw_rate_radps, ob[:, _WHEELS].mean(axis=1)
    m = (v > 5.0) & (np.abs(g) > 3.0 * schema.DEG_TO_RAD)
    if m.sum() < 500:
        return None
    ref = (ob[m, _AY] - bias.lat_accel_mps2) / v[m]
    k_ay = float(np.sum(g[m] * ref) / np.sum(ref * ref)) - 1.0
    # rear pair: rr - rl = track * omega + eps * v, omega = g / (1 + k)  ->  fit (track / (1 + k), eps)
    (c, _), *_ = np.linalg.lstsq(np.stack([g[m], v[m]], axis=1), ob[m, _RR] - ob[m, _RL], rcond=None)
    k_rear = car.params.track_m / float(c) - 1.0
    gnss = {f"GNSS {m:g} min": 100.0 * (gnss_gain_fit(drive, g, m) - drawn) for m in GNSS_MINUTES}
    return {"drawn": 100.0 * drawn, "a_y / v": 100.0 * (k_ay - drawn), "rear pair": 100.0 * (k_rear - drawn), **gnss}


def gnss_gain_fit(drive, gyro: np.ndarray, minutes: float) -> float:
    """The gyro gain error [1] a fit of ``gyro`` (the calibrated yaw rate) against GNSS heading changes over
    10 s baselines in the drive's first ``minutes`` finds; noise seeded by the drive's name."""
    n = min(len(gyro), int(minutes * 60.0 * schema.SAMPLE_RATE_HZ))
    every = int(round(schema.SAMPLE_RATE_HZ / GNSS_RATE_HZ))
    rng = np.random.default_rng(zlib.crc32(drive.name.encode()))
    fix = np.arange(0, n, every)
    noise = np.radians(rng.normal(0.0, GNSS_HEADING_STD_DEG, len(fix)))
    heading = np.interp(np.arange(n), fix, np.unwrap(drive.pose_gt[fix, 2] + noise))  # heading changes < pi per fix
    phi = np.concatenate([[0.0], np.cumsum(gyro[: n - 1]) * schema.DT_S])
    step = int(GNSS_BASELINE_S * schema.SAMPLE_RATE_HZ)
    a = np.arange(0, n - step, step)
    speed = np.hypot(drive.z_gt[:n, 0], drive.z_gt[:n, 1])
    moving = (speed[a] >= GNSS_HEADING_MIN_SPEED_MPS) & (speed[a + step] >= GNSS_HEADING_MIN_SPEED_MPS)
    cols = np.stack([phi[a + step] - phi[a], np.full(len(a), GNSS_BASELINE_S)], axis=1)[moving]
    if len(cols) < 3:
        return float("nan")
    # heading change = gyro change / (1 + k) - offset x time / (1 + k); the noisy GNSS side is the regressand
    (c, _), *_ = np.linalg.lstsq(cols, heading[a + step][moving] - heading[a][moving], rcond=None)
    return 1.0 / float(c) - 1.0 if c > 0 else float("nan")


def gain_rows(dataset, split: str) -> dict[str, float]:
    """Rms over the split's drives of the drawn gain and of each fit's error [%]."""
    names = {d.name for d, _, _ in dataset.segments(split)}
    ev = [e for d in dataset.drives if d.name in names and (e := gain_evidence(d)) is not None]
    return {"n_drives": len(ev), **{k: float(np.sqrt(np.nanmean([e[k] ** 2 for e in ev])))
                                    for k in (ev[0] if ev else {})}}


def markdown(doc: dict) -> list[str]:
    splits = list(doc["splits"])
    out = ["OSD's equations integrated over the 60 s windows (paper protocol), mean RMSE [m] (× the reference):", "",
           "| case | " + " | ".join(f"{s} ({doc['splits'][s]['n_windows']})" for s in splits) + " |",
           "|---|" + "---|" * len(splits)]
    for case in CASES:
        row = (doc["splits"][s]["cases"][case] for s in splits)
        cells = [f"{c['rmse_mean_m']:.2f} ({c['ratio']:.2f}×)" for c in row]
        out.append(f"| {case} | " + " | ".join(cells) + " |")
    out += ["", "Per car: the reference, the drive's gyro gain known, and the drawn gain error (rms over the windows):",
            "", "| split | car | OSD m | no gyro scale m | gain error rms % |", "|---|---|---:|---:|---:|"]
    for s in splits:
        for car, d in sorted(doc["splits"][s]["per_car"].items()):
            out.append(f"| {s} | {car} | {d[CASES[0]]:.2f} | {d['no gyro scale']:.2f} | "
                       f"{doc['splits'][s]['yaw_scale_error_rms_pct'][car]:.2f} |")
    out += ["", "What could tell the gyro's gain: rms over the drives [%] of the drawn gain error (assuming 0) and of "
            "what a whole-drive fit leaves; with GNSS heading, what a fit over the drive's first minutes leaves:", "",
            "| split | drives | drawn | a_y / v fit | rear pair fit |"
            + "".join(f" GNSS, first {m:g} min |" for m in GNSS_MINUTES),
            "|---|---:|---:|---:|---:|" + "---:|" * len(GNSS_MINUTES)]
    for s in splits:
        e = doc["splits"][s]["gain_evidence"]
        if e["n_drives"]:
            gnss = "".join(f" {e[f'GNSS {m:g} min']:.2f} |" if f"GNSS {m:g} min" in e else " – |" for m in GNSS_MINUTES)
            out.append(f"| {s} | {e['n_drives']} | {e['drawn']:.2f} | {e['a_y / v']:.2f} | {e['rear pair']:.2f} |"
                       + gnss)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(HERE.parent / "data" / "bench"))
    p.add_argument("--splits", nargs="+", default=["val", "test", "snow", "heldout"])
    p.add_argument("--out", default=str(OUT), help=f"result JSON (default {OUT.relative_to(HERE.parent)})")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    dataset = load_dataset(args.data)
    doc = {"machine": machine_info(), "data": str(args.data),
           "splits": {s: {**measure_split(dataset, s), "gain_evidence": gain_rows(dataset, s)}
                                                       for s in args.splits}}
    finish(doc, args.out, markdown, t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
