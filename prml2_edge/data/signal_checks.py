"""Physics checks of the onboard signals: signs and scales a moving car gives for free (NumPy only).

Each check compares a signal with a reference that other signals make, on the 50 Hz rows where
both are valid and the car moves:

* the four wheel speeds against their median (a wheel in km/h declared as m/s reads 3.6 x);
* the speedometer against the mean wheel speed (it reads 0-10 % above them, never below);
* the yaw rate against the rear wheel-speed difference over the track, ``(v_rr - v_rl) / track``;
* the lateral acceleration against speed x yaw rate (``a_y = v_x * psi_dot`` in a steady turn);
* the steering wheel angle against the yaw rate at low speed (both left positive: a kinematic
  turn has ``psi_dot = v * delta_sw / (i_s * L)`` with ``i_s * L`` about 25-70 m).

A sign check uses the correlation ``r`` of the signal with its reference; a scale check the
least-squares gain. A failure names the signal, what it disagrees with and by how much, and the
fix as a factor for the map's ``scale`` (``scale_factor``, -1 for a flipped sign). The
references are chosen so that each failure has one culprit: the wheels are checked first
against each other, the yaw rate against the wheels, and the lateral acceleration and the
steering against the yaw rate corrected by what its own check found.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from prml2_edge import schema

PASS, WARN, FAIL, SKIP = "PASS", "WARN", "FAIL", "SKIP"
TRACK_M = 1.6  # nominal track width [m]; passenger cars 1.4-1.8
TRACK_RANGE_M = (1.1, 2.3)
MOVING_MPS = 3.0
MIN_ROWS = 100  # rows (2 s) a check needs
MIN_SIGN_R = 0.5  # |r| a sign check needs to decide
SPEEDO_RATIO = (0.95, 1.15)  # speedometer / mean wheel speed
LAT_GAIN = (0.75, 1.3)  # a_y / (v psi_dot)
STEER_GAIN_M = (15.0, 120.0)  # i_s * L [m]: v * delta_sw / psi_dot at low speed
WHEEL_TOL = 0.12  # a wheel's ratio to the median of the four

_I = {name: s.index for name, s in schema.SIGNAL_BY_NAME.items()}
WHEELS = schema.WHEEL_SPEED_INDICES
UNIT_FACTORS = ((1 / 3.6, "km/h -> m/s"), (3.6, "m/s -> km/h"), (0.44704, "mph -> m/s"),
                (math.pi / 180, "deg -> rad"), (180 / math.pi, "rad -> deg"), (schema.G_MPS2, "g -> m/s^2"),
                (1 / schema.G_MPS2, "m/s^2 -> g"), (0.1, "x 0.1"), (10.0, "x 10"))


@dataclass(frozen=True)
class Finding:
    """One physics check: ``signal`` is the culprit (canonical name) when ``result`` is FAIL."""

    check: str
    signal: str
    result: str  # PASS | WARN | FAIL | SKIP
    detail: str
    fix: str = ""
    scale_factor: float | None = None  # multiply the map's scale by this (-1: flip the sign)
    r: float | None = None
    gain: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def unit_hint(factor: float) -> str:
    """The unit conversion a scale factor looks like ("km/h -> m/s"), or ""."""
    return snap_factor(factor)[1]


def snap_factor(factor: float) -> tuple[float, str]:
    """``(exact factor, name)`` of the unit conversion ``factor`` looks like (within 8 %), else ``(factor, "")``."""
    for f, name in UNIT_FACTORS:
        if abs(abs(factor) / f - 1.0) < 0.08:
            return math.copysign(f, factor), name
    return factor, ""


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    sa, sb = float(np.std(a)), float(np.std(b))
    if len(a) < 3 or sa == 0.0 or sb == 0.0:
        return math.nan
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))


def _gain(y: np.ndarray, x: np.ndarray) -> float:
    """Least-squares gain of ``y = gain * x`` (through the origin)."""
    den = float(np.dot(x, x))
    return float(np.dot(x, y) / den) if den > 0 else math.nan


def _fit(y: np.ndarray, x: np.ndarray, *nuisance: np.ndarray) -> tuple[float, float]:
    """Gain of ``y`` on ``x`` with an offset and ``nuisance`` regressors fitted beside it, and the correlation
    of ``x`` with ``y`` once the offset and nuisance parts are removed: ``(gain, r)``."""
    cols = [x, np.ones_like(x), *nuisance]
    coef, *_ = np.linalg.lstsq(np.stack(cols, axis=1), y, rcond=None)
    rest = y - np.stack(cols[1:], axis=1) @ coef[1:]
    return float(coef[0]), _corr(rest, x)


def _smooth(x: np.ndarray, n: int = 25) -> np.ndarray:
    """Moving average over ``n`` rows (0.5 s at 50 Hz) along axis 0: quantisation and noise out."""
    if len(x) < n:
        return x
    k = np.ones(n) / n
    if x.ndim == 1:
        return np.convolve(x, k, mode="same")
    return np.stack([np.convolve(x[:, j], k, mode="same") for j in range(x.shape[1])], axis=1)


def check_onboard(onboard: np.ndarray, valid: np.ndarray | None = None,
                  present: tuple[bool, ...] | None = None) -> list[Finding]:
    """Run every physics check on (N, 9) 50 Hz onboard rows (SI, canonical order).

    ``valid`` (N, 9) marks usable values (default all); ``present`` (9,) False for signals the
    map does not read (absent): checks on them are skipped.
    """
    o = np.asarray(onboard, dtype=np.float64)
    ok = np.ones(o.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    ok = ok & np.isfinite(o)
    have = np.ones(schema.NUM_SIGNALS, dtype=bool) if present is None else np.asarray(present, dtype=bool)
    o = _smooth(np.where(ok, o, 0.0))
    findings: list[Finding] = []

    wheels_ok = ok[:, WHEELS].all(axis=1)
    v_med = np.median(o[:, WHEELS], axis=1)
    moving = wheels_ok & (v_med > MOVING_MPS)
    wheel_factor = np.ones(4)
    for j, w in enumerate(WHEELS):
        name = schema.SIGNAL_NAMES[w]
        rows = moving & ok[:, w]
        if rows.sum() < MIN_ROWS:
            findings.append(Finding("wheels against each other", name, SKIP, "too few moving rows"))
            continue
        ratio = float(np.median(o[rows, w] / v_med[rows]))
        if abs(ratio - 1.0) > WHEEL_TOL:
            factor = 1.0 / ratio
            wheel_factor[j] = factor
            hint = unit_hint(factor)
            findings.append(Finding("wheels against each other", name, FAIL,
                                    f"{name} reads {ratio:.3f} x the median of the four wheels",
                                    f"multiply its scale by {factor:.4g}" + (f" ({hint})" if hint else ""), factor,
                                    gain=ratio))
        else:
            findings.append(Finding("wheels against each other", name, PASS, f"{ratio:.3f} x the median", gain=ratio))
    wheels = o[:, WHEELS] * wheel_factor  # as they would read after the fixes above
    v = wheels.mean(axis=1)
    moving = wheels_ok & (v > MOVING_MPS)

    findings.append(_speedometer(o, ok, v, moving))
    yaw_finding, yaw_ref = _yaw(o, ok, wheels, v, moving)
    findings.append(yaw_finding)
    if yaw_ref is not None:
        findings.append(_lateral(o, ok, v, moving, yaw_ref))
        findings.append(_steering(o, ok, v, moving, yaw_ref))
    else:
        for name, check in (("lat_accel_mps2", "lateral acceleration against speed x yaw rate"),
                            ("steering_wheel_angle_rad", "steering sign against yaw sign at low speed")):
            findings.append(Finding(check, name, SKIP, "no yaw-rate reference (see the yaw-rate check)"))
    return [f for f in findings if have[_I[f.signal]] or f.result == PASS]


def _speedometer(o, ok, v, moving) -> Finding:
    check, name = "speedometer against mean wheel speed", "speedometer_mps"
    rows = moving & ok[:, _I[name]]
    if rows.sum() < MIN_ROWS:
        return Finding(check, name, SKIP, "too few moving rows")
    ratio = float(np.median(o[rows, _I[name]] / v[rows]))
    if SPEEDO_RATIO[0] <= ratio <= SPEEDO_RATIO[1]:
        return Finding(check, name, PASS, f"speedometer / mean wheel speed {ratio:.3f}", gain=ratio)
    factor = 1.0 / ratio
    hint = unit_hint(factor)
    return Finding(check, name, FAIL, f"speedometer reads {ratio:.3f} x the mean wheel speed (expected "
                   f"{SPEEDO_RATIO[0]:.2f}-{SPEEDO_RATIO[1]:.2f})",
                   f"multiply its scale by {factor:.4g}" + (f" ({hint})" if hint else ""), factor, gain=ratio)


def _yaw(o, ok, wheels, v, moving) -> tuple[Finding, np.ndarray | None]:
    """Yaw rate against the rear wheel-speed difference; returns the finding and the yaw reference to use."""
    check, name = "yaw rate against rear wheel-speed difference", "yaw_rate_radps"
    yaw = o[:, _I[name]]
    dv = wheels[:, 3] - wheels[:, 2]  # rr - rl: positive in a left (counter-clockwise) turn
    wheel_yaw = dv / TRACK_M
    rows = moving & ok[:, _I[name]]
    turning = rows & (np.abs(wheel_yaw) > 0.05)
    if turning.sum() < MIN_ROWS:
        return Finding(check, name, SKIP, "too little turning to check (drive some curves)"), None
    # wheel radius differences make dv proportional to v, a yaw-rate offset a constant: fitted beside the track
    track, r = _fit(dv[rows], yaw[rows], v[rows])
    if not r == r or abs(r) < MIN_SIGN_R:
        return Finding(check, name, FAIL, f"yaw rate does not follow the wheels (r = {r:+.2f})",
                       "check the message and signal the map names for yaw_rate_radps", r=r), wheel_yaw
    sign = 1.0 if r > 0 else -1.0
    track = abs(track)
    in_range = TRACK_RANGE_M[0] <= track <= TRACK_RANGE_M[1]
    if sign < 0:
        detail = f"yaw_rate_radps has the opposite sign of the rear wheel-speed difference (r = {r:+.2f})"
        return Finding(check, name, FAIL, detail, "negate its scale", -1.0, r=r, gain=track), -yaw
    if not in_range:
        factor = track / TRACK_M
        hint = unit_hint(factor)
        detail = f"yaw rate implies a {track:.2f} m track (expected {TRACK_RANGE_M[0]}-{TRACK_RANGE_M[1]} m)"
        return Finding(check, name, FAIL, detail, f"multiply its scale by {factor:.4g}" + (f" ({hint})" if hint
                       else ""), factor, r=r, gain=track), wheel_yaw
    return Finding(check, name, PASS, f"r = {r:+.2f}, implied track {track:.2f} m", r=r, gain=track), yaw


def _lateral(o, ok, v, moving, yaw_ref) -> Finding:
    check, name = "lateral acceleration against speed x yaw rate", "lat_accel_mps2"
    a_y = o[:, _I[name]]
    ref = v * yaw_ref
    rows = moving & ok[:, _I[name]]
    if (rows & (np.abs(ref) > 1.0)).sum() < MIN_ROWS:
        return Finding(check, name, SKIP, "too little cornering to check (> 1 m/s^2)")
    gain, r = _fit(a_y[rows], ref[rows])
    if not r == r or abs(r) < MIN_SIGN_R:
        return Finding(check, name, FAIL, f"lateral acceleration does not follow v x yaw rate (r = {r:+.2f})",
                       "check the message and signal the map names for lat_accel_mps2", r=r)
    if r < 0:
        return Finding(check, name, FAIL, f"lat_accel_mps2 has the opposite sign of v*yaw rate (r = {r:+.2f})",
                       "negate its scale", -1.0, r=r, gain=gain)
    if not LAT_GAIN[0] <= gain <= LAT_GAIN[1]:
        factor = 1.0 / gain
        hint = unit_hint(factor)
        return Finding(check, name, FAIL, f"lateral acceleration is {gain:.3f} x v*yaw rate (expected about 1)",
                       f"multiply its scale by {factor:.4g}" + (f" ({hint})" if hint else ""), factor, r=r, gain=gain)
    return Finding(check, name, PASS, f"r = {r:+.2f}, gain {gain:.3f}", r=r, gain=gain)


def _steering(o, ok, v, moving, yaw_ref) -> Finding:
    check, name = "steering sign against yaw sign at low speed", "steering_wheel_angle_rad"
    delta = o[:, _I[name]]
    rows = moving & ok[:, _I[name]] & (v < 12.0) & (np.abs(yaw_ref) > 0.05)
    if rows.sum() < MIN_ROWS:
        return Finding(check, name, SKIP, "too few low-speed turns (< 12 m/s) to check")
    _, r = _fit(delta[rows], yaw_ref[rows])
    if not r == r or abs(r) < MIN_SIGN_R:
        return Finding(check, name, FAIL, f"steering does not follow the yaw rate at low speed (r = {r:+.2f})",
                       "check the message and signal the map names for steering_wheel_angle_rad", r=r)
    gain = abs(_gain(v[rows] * delta[rows], yaw_ref[rows]))  # i_s * L [m]
    if r < 0:
        return Finding(check, name, FAIL, f"steering_wheel_angle_rad has the opposite sign of the yaw rate at low "
                       f"speed (r = {r:+.2f})", "negate its scale", -1.0, r=r, gain=gain)
    if not STEER_GAIN_M[0] <= gain <= STEER_GAIN_M[1]:
        factor = 40.0 / gain
        hint = unit_hint(factor)
        return Finding(check, name, FAIL, f"steering ratio x wheelbase comes out {gain:.1f} m (expected "
                       f"{STEER_GAIN_M[0]:.0f}-{STEER_GAIN_M[1]:.0f} m)",
                       f"multiply its scale by about {factor:.3g}" + (f" ({hint})" if hint else ""), factor,
                       r=r, gain=gain)
    return Finding(check, name, PASS, f"r = {r:+.2f}, steering ratio x wheelbase {gain:.1f} m", r=r, gain=gain)
