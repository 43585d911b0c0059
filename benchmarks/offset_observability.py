"""Could the CAN yaw rate's offset be told from the other onboard cues, without GNSS or a stop? (issue 26)

The robustness target (``benchmarks/robustness.py``) asks a model to drift no more with a ±0.4 °/s gyro offset than
without one, with no standstill, no GNSS and calibration off. This measures what the signals allow. On the same
drives (the benchmark recipe's dry test drives, fleet and held-out car, re-simulated without standstill, the gyro
offset set to +0.4 °/s, every other sensor error as drawn), three more yaw-rate cues are formed from the CAN signals a
model reads:

* ``a_y / v``: lateral acceleration over the rear-axle speed;
* ``rear wheels``: (v_rr − v_rl) / track;
* ``steering``: kinematic single track, v tan(δ_sw / ratio) / wheelbase.

Each is compared with the truth on straight, moving rows (|ω_z| < 1 °/s by the truth, v > 5 m/s: no understeer and
no slip to model, so what is left is the cue's own offset-like error, drawn per drive like the gyro's), per window
of T seconds: the RMS over windows of the mean error [°/s], i.e. what that cue would say the gyro's offset is,
next to the offset (0.4 °/s).

Then the cues together: each cue's error has its own shape in speed (a lateral-acceleration offset c gives c / v, a
wheel-radius difference k gives k v, a steering offset d gives about d v), the gyro's offset b none, so over a window
whose speed varies b is separable: b̂ from the stacked least squares of gyro − cue = b + (cue's term) on the same
straight rows. Reported: the RMS of b̂ − b per window length, and the share of windows with no usable fit (fewer than
``MIN_ROWS`` straight moving rows, or speeds that do not vary enough to separate the terms). The straights are
picked by the truth: an upper bound for a model, which has to find them itself.

Usage::

    .venv/bin/python benchmarks/offset_observability.py [--cars reference,van_fwd] [--json PATH]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.bench.results import announce, finish
from prml2_edge.data.simulate.fleet import CARS as FLEET
from prml2_edge.data.simulate.fleet import get_car

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robustness import recipe_drives, resimulate  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "offset_observability.json"
OFFSET_DPS = 0.4
WINDOWS_S = (5.0, 60.0, 300.0)
STRAIGHT_DPS = 1.0
MIN_SPEED_MPS = 5.0
MIN_ROWS = 50  # 1 s of straight moving rows
MAX_CONDITION = 100.0  # a window whose speed barely varies cannot separate the cues' terms from the offset
_SIG = schema.SIGNAL_BY_NAME
_YAW, _AY, _STEER = (_SIG[n].index for n in ("yaw_rate_radps", "lat_accel_mps2", "steering_wheel_angle_rad"))
_RL, _RR = schema.WHEEL_SPEED_INDICES[2], schema.WHEEL_SPEED_INDICES[3]
CUES = ("a_y / v", "rear wheels", "steering")


def cue_rates(drive) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """``(speed (n,), {cue: yaw rate (n,)}, gyro (n,))`` from a drive's CAN signals [m/s, rad/s]."""
    p = get_car(drive.meta.get("vehicle", "reference")).params
    on = drive.onboard
    v = 0.5 * (on[:, _RL] + on[:, _RR])
    with np.errstate(divide="ignore", invalid="ignore"):
        cues = {"a_y / v": on[:, _AY] / v,
                "rear wheels": (on[:, _RR] - on[:, _RL]) / p.track_m,
                "steering": v * np.tan(on[:, _STEER] / p.steering_ratio) / p.wheelbase_m}
    return v, cues, on[:, _YAW]


def _regressors(cue: str, v: np.ndarray) -> np.ndarray:
    """The shape in speed of each cue's offset-like error (the column beside the gyro's constant)."""
    return 1.0 / v if cue == "a_y / v" else v


def joint_offset(v: np.ndarray, cues: dict[str, np.ndarray], gyro: np.ndarray) -> float | None:
    """b̂: gyro − cue = b + (the cue's own term) for every cue, stacked, least squares; None where not separable."""
    n, k = len(v), len(CUES)
    a = np.zeros((n * k, 1 + k))
    y = np.empty(n * k)
    for j, c in enumerate(CUES):
        rows = slice(j * n, (j + 1) * n)
        a[rows, 0] = 1.0
        a[rows, 1 + j] = _regressors(c, v)
        y[rows] = gyro - cues[c]
    scale = np.abs(a).max(axis=0)
    if np.linalg.cond(a / scale) > MAX_CONDITION:
        return None
    return float(np.linalg.lstsq(a, y, rcond=None)[0][0])


def windows(drive, window_s: float):
    """Per window of ``window_s``: the straight moving rows' (v, cues, gyro), or None with too few rows."""
    v, cues, gyro = cue_rates(drive)
    w_true = drive.z_gt[:, schema.Z.OMEGA_Z]
    ok = (np.abs(w_true) < math.radians(STRAIGHT_DPS)) & (v > MIN_SPEED_MPS)
    ok &= np.all([np.isfinite(c) for c in cues.values()], axis=0)
    n = int(round(window_s / schema.DT_S))
    for s in range(0, len(v) - n + 1, n):
        sel = np.flatnonzero(ok[s:s + n]) + s
        yield (v[sel], {c: x[sel] - w_true[sel] for c, x in cues.items()}, gyro[sel] - w_true[sel]) \
            if len(sel) >= MIN_ROWS else None


def measure(drives: list, offset_rad: float) -> dict:
    """Per window length: each cue's RMS mean error and the joint offset estimate's RMS error [deg/s]."""
    out = {}
    for window_s in WINDOWS_S:
        per_cue: dict[str, list[float]] = {c: [] for c in CUES}
        joint, n_win, n_none = [], 0, 0
        for d in drives:
            for w in windows(d, window_s):
                n_win += 1
                if w is None:
                    n_none += 1
                    continue
                v, err, gyro_err = w
                for c in CUES:
                    per_cue[c].append(float(np.mean(err[c])))
                # gyro − cue = (gyro error + ω) − (cue error + ω): the truth cancels, as it would for a model
                b = joint_offset(v, {c: err[c] for c in CUES}, gyro_err)
                if b is None:
                    n_none += 1
                else:
                    joint.append(b - offset_rad)
        rms = lambda x: math.degrees(math.sqrt(np.mean(np.square(x)))) if x else float("nan")  # noqa: E731
        out[f"{window_s:g} s"] = {"windows": n_win, "without_fit": n_none,
                                  "cue_mean_error_rms_dps": {c: rms(per_cue[c]) for c in CUES},
                                  "joint_offset_error_rms_dps": rms(joint), "joint_fits": len(joint)}
    return out


def markdown(doc: dict) -> list[str]:
    lines = ["| window | windows (no fit) | " + " | ".join(f"{c}: RMS mean error °/s" for c in CUES)
             + f" | joint fit of the {doc['offset_dps']:g} °/s offset: RMS error °/s |",
             "|---|---:|" + "---:|" * (len(CUES) + 1)]
    for w, r in doc["windows"].items():
        cue = " | ".join(f"{r['cue_mean_error_rms_dps'][c]:.2f}" for c in CUES)
        lines.append(f"| {w} | {r['windows']} ({r['without_fit']}) | {cue} | {r['joint_offset_error_rms_dps']:.2f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cars", default=None, help="comma-separated cars (default: every car of the recipe)")
    ap.add_argument("--json", default=str(OUT))
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    specs = recipe_drives(args.cars.split(",") if args.cars else None)
    drives = [resimulate(s, OFFSET_DPS, None) for g in ("test", "heldout") for s in specs[g]]
    if not drives:
        ap.error(f"no test drive of --cars {args.cars!r} in the benchmark recipe; its fleet is {', '.join(FLEET)}")
    machine = announce("offset_observability")
    doc = {"machine": machine, "args": vars(args), "offset_dps": OFFSET_DPS,
           "drives": [d.name for d in drives], "straight_below_dps": STRAIGHT_DPS, "min_speed_mps": MIN_SPEED_MPS,
           "windows": measure(drives, math.radians(OFFSET_DPS))}
    finish(doc, args.json, markdown, t0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
