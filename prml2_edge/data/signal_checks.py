"""Physics checks of the onboard signals: signs and scales a moving car gives for free (NumPy only).

Each check compares a signal with a reference that other signals make, on the 50 Hz rows where
both are valid and the car moves:

* the four wheel speeds against their median (a wheel in km/h declared as m/s reads 3.6 x);
* the speedometer against the mean wheel speed (it reads 0-10 % above them, never below);
* the yaw rate against the rear wheel-speed difference over the track, ``(v_rr - v_rl) / track``;
* the lateral acceleration against speed x yaw rate (``a_y = v_x * psi_dot`` in a steady turn);
* the steering wheel angle against the path curvature ``psi_dot / v`` (both left positive: a
  kinematic turn has ``delta_sw = i_s * L * kappa``, ``i_s * L`` about 25-70 m, more at speed
  as the car understeers).

The three rotation checks (yaw, lateral, steering) work on gentle curves with coarse sensors.
Their offsets (a gyro's bias, a wheel's radius, a steering sensor's zero) are fitted out first;
then only the *turning rows* count: those where the reference moves beyond a threshold set by
resolution, the larger of :data:`REF_STEPS` steps of the reference, :data:`SIG_STEPS` steps of the
checked signal (so a coarse sensor visibly moves) and :data:`MIN_TURN_DPS` of yaw rate (what a
straight road's steering corrections stay under). A check runs only with :data:`MIN_TURN_S`
seconds of turning rows; otherwise it is SKIP (not verified, never a pass). On the turning rows
the sign comes from two statistics that a quantised signal cannot fool: the correlation ``r``
of the (0.5 s low-passed, offset-free) signal with its reference about zero, and a sign test
(the share of turning rows in which both have the same sign, its p-value over turning seconds).
Right when ``r >= MIN_SIGN_R`` and at least :data:`MIN_AGREE` of the rows agree, flipped when
``r <= -MIN_SIGN_R`` and at most ``1 - MIN_AGREE`` agree, otherwise the signal does not follow its
reference (a wrong message or signal). A scale check uses the gain on the same rows (geometric-mean
regression: a coarse signal on either side does not pull it towards 0). Each finding carries its
:class:`Evidence`.

A failure names the signal, what it disagrees with and by how much, and the fix as a factor for
the map's ``scale`` (``scale_factor``, -1 for a flipped sign). The references are chosen so that
each failure has one culprit: the wheels are checked first against each other, the yaw rate
against the wheels, and the lateral acceleration and the steering against the yaw rate
corrected by what its own check found (or against the wheels, whichever resolves finer).
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
MIN_ROWS = 100  # rows (2 s) a wheel or speedometer check needs
MIN_SIGN_R = 0.5  # |r| a sign check needs to decide
MIN_AGREE = 0.75  # share of turning rows whose signs agree (or disagree, for a flip) to decide
MIN_TURN_S = 5.0  # seconds of turning rows a rotation check needs
MIN_TURN_DPS = 0.5  # turning below this yaw rate [deg/s] is not counted: a straight road's corrections
REF_STEPS = 1.5  # the reference moves by at least this many of its resolution steps ...
SIG_STEPS = 0.75  # ... and by this many steps of the checked signal (rounded, it then reads one step)
STEER_NOMINAL_M = 40.0  # i_s * L of a typical car [m]: turns a steering step into a curvature step
SPEEDO_RATIO = (0.95, 1.15)  # speedometer / mean wheel speed
LAT_GAIN = (0.75, 1.3)  # a_y / (v psi_dot)
STEER_GAIN_M = (15.0, 120.0)  # i_s * L [m]: v * delta_sw / psi_dot at low speed ...
STEER_UNDERSTEER_S2PM2 = 0.005  # ... and up to (1 + this * v^2) times more at speed (understeer)
WHEEL_TOL = 0.12  # a wheel's ratio to the median of the four

_I = {name: s.index for name, s in schema.SIGNAL_BY_NAME.items()}
WHEELS = schema.WHEEL_SPEED_INDICES
_DT = schema.DT_S
_DEG = math.pi / 180.0
UNIT_FACTORS = ((1 / 3.6, "km/h -> m/s"), (3.6, "m/s -> km/h"), (0.44704, "mph -> m/s"),
                (math.pi / 180, "deg -> rad"), (180 / math.pi, "rad -> deg"), (schema.G_MPS2, "g -> m/s^2"),
                (1 / schema.G_MPS2, "m/s^2 -> g"), (0.1, "x 0.1"), (10.0, "x 10"))
ROTATION_SIGNALS = ("yaw_rate_radps", "lat_accel_mps2", "steering_wheel_angle_rad")


@dataclass(frozen=True)
class Evidence:
    """How much a rotation check had to go on (SI unless named; thresholds in yaw-rate terms)."""

    reference: str  # what the signal was compared with
    turning_s: float  # seconds of turning rows: the reference beyond the threshold
    needs_s: float  # seconds the check needs to decide
    threshold_dps: float  # the turning counted [deg/s of yaw rate], median over the rows
    rows: int  # moving rows with both valid
    speed_mps: float  # median speed over them
    agree: float | None = None  # share of turning rows in which signal and reference have the same sign
    p_value: float | None = None  # sign test over turning seconds: chance of that (dis)agreement by luck


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
    evidence: Evidence | None = None  # the rotation checks: what they decided on
    needs: str = ""  # a SKIP: the driving that would let the check run

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


def resolution(values: np.ndarray) -> float | None:
    """The smallest step between distinct values (a quantised sensor's resolution), None with fewer than 2."""
    u = np.unique(np.asarray(values, dtype=np.float64))
    u = u[np.isfinite(u)]
    if len(u) < 2:
        return None
    d = np.diff(u)
    d = d[d > 1e-9 * max(float(np.max(np.abs(u))), 1e-12)]  # float rounding of one grid value
    return float(np.min(d)) if len(d) else None


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    sa, sb = float(np.std(a)), float(np.std(b))
    if len(a) < 3 or sa == 0.0 or sb == 0.0:
        return math.nan
    return float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))


def _smooth(x: np.ndarray, n: int = 25) -> np.ndarray:
    """Moving average over ``n`` rows (0.5 s at 50 Hz) along axis 0: quantisation and noise out."""
    if len(x) < n:
        return x
    k = np.ones(n) / n
    if x.ndim == 1:
        return np.convolve(x, k, mode="same")
    return np.stack([np.convolve(x[:, j], k, mode="same") for j in range(x.shape[1])], axis=1)


def _scale_fix(factor: float) -> str:
    hint = unit_hint(factor)
    return f"multiply its scale by {factor:.4g}" + (f" ({hint})" if hint else "")


def check_onboard(onboard: np.ndarray, valid: np.ndarray | None = None,
                  present: tuple[bool, ...] | None = None, steps=None) -> list[Finding]:
    """Run every physics check on (N, 9) 50 Hz onboard rows (SI, canonical order).

    ``valid`` (N, 9) marks usable values (default all); ``present`` (9,) False for signals the
    map does not read (absent): checks on them are skipped. ``steps`` (9,) are the signals'
    resolutions [SI] (None or NaN entries: measured on the rows).
    """
    o = np.asarray(onboard, dtype=np.float64)
    ok = np.ones(o.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    ok = ok & np.isfinite(o)
    have = np.ones(schema.NUM_SIGNALS, dtype=bool) if present is None else np.asarray(present, dtype=bool)
    step = np.array([np.nan if steps is None or steps[i] is None else float(steps[i])
                     for i in range(schema.NUM_SIGNALS)])
    for i in np.flatnonzero(~np.isfinite(step)):
        found = resolution(o[ok[:, i], i])
        step[i] = found if found is not None else 0.0
    o = _smooth(np.where(ok, o, 0.0))
    findings, wheel_factor = _wheel_findings(o, ok)
    wheels = o[:, WHEELS] * wheel_factor  # as they would read after the fixes above
    wheel_step = float(np.max(step[list(WHEELS)[2:]] * np.abs(wheel_factor[2:])))
    v = wheels.mean(axis=1)
    moving = ok[:, WHEELS].all(axis=1) & (v > MOVING_MPS)
    findings.append(_speedometer(o, ok, v, moving))
    findings += _rotation(o, ok, wheels, v, moving, step, wheel_step, bool(have[_I["yaw_rate_radps"]]))
    return [f for f in findings if have[_I[f.signal]] or f.result == PASS]


def _wheel_findings(o, ok) -> tuple[list[Finding], np.ndarray]:
    """Each wheel against the median of the four; the factor that would fix each."""
    findings = []
    wheels_ok = ok[:, WHEELS].all(axis=1)
    v_med = np.median(o[:, WHEELS], axis=1)
    moving = wheels_ok & (v_med > MOVING_MPS)
    wheel_factor = np.ones(4)
    for j, w in enumerate(WHEELS):
        name = schema.SIGNAL_NAMES[w]
        rows = moving & ok[:, w]
        if rows.sum() < MIN_ROWS:
            findings.append(Finding("wheels against each other", name, SKIP, "too few moving rows",
                                    needs=f"at least {MIN_ROWS * _DT:g} s above {MOVING_MPS:g} m/s"))
            continue
        ratio = float(np.median(o[rows, w] / v_med[rows]))
        if abs(ratio - 1.0) > WHEEL_TOL:
            factor = 1.0 / ratio
            wheel_factor[j] = factor
            findings.append(Finding("wheels against each other", name, FAIL,
                                    f"{name} reads {ratio:.3f} x the median of the four wheels",
                                    _scale_fix(factor), factor, gain=ratio))
        else:
            findings.append(Finding("wheels against each other", name, PASS, f"{ratio:.3f} x the median", gain=ratio))
    return findings, wheel_factor


def _speedometer(o, ok, v, moving) -> Finding:
    check, name = "speedometer against mean wheel speed", "speedometer_mps"
    rows = moving & ok[:, _I[name]]
    if rows.sum() < MIN_ROWS:
        return Finding(check, name, SKIP, "too few moving rows",
                       needs=f"at least {MIN_ROWS * _DT:g} s above {MOVING_MPS:g} m/s")
    ratio = float(np.median(o[rows, _I[name]] / v[rows]))
    if SPEEDO_RATIO[0] <= ratio <= SPEEDO_RATIO[1]:
        return Finding(check, name, PASS, f"speedometer / mean wheel speed {ratio:.3f}", gain=ratio)
    factor = 1.0 / ratio
    return Finding(check, name, FAIL, f"speedometer reads {ratio:.3f} x the mean wheel speed (expected "
                   f"{SPEEDO_RATIO[0]:.2f}-{SPEEDO_RATIO[1]:.2f})", _scale_fix(factor), factor, gain=ratio)


@dataclass(frozen=True)
class _Turning:
    """A signal against its reference on the turning rows: the statistics a rotation check decides on."""

    evidence: Evidence
    r: float = math.nan  # correlation about zero of the offset-free signal and reference on the turning rows
    gain: float = math.nan  # signal per reference there (geometric-mean regression, signed)

    @property
    def enough(self) -> bool:
        return self.evidence.turning_s >= self.evidence.needs_s

    def sign(self) -> int:
        """+1 same sign, -1 opposite, 0 neither clearly (the correlation and the sign test must agree)."""
        agree = self.evidence.agree
        if agree is None or not self.r == self.r:
            return 0
        if self.r >= MIN_SIGN_R and agree >= MIN_AGREE:
            return 1
        if self.r <= -MIN_SIGN_R and agree <= 1.0 - MIN_AGREE:
            return -1
        return 0

    def summary(self) -> str:
        e = self.evidence
        p = "p < 1e-6" if e.p_value is not None and e.p_value < 1e-6 else f"p = {e.p_value:.2g}"
        share = e.agree if self.r >= 0 else 1.0 - e.agree
        return (f"r = {self.r:+.2f}, sign {'agreed' if self.r >= 0 else 'opposite'} in {100 * share:.0f} % of "
                f"{e.turning_s:.1f} s turning beyond {e.threshold_dps:.2g} deg/s ({p})")

    def skip(self, check: str, name: str) -> Finding:
        e = self.evidence
        needs = f"curves beyond {e.threshold_dps:.2g} deg/s of yaw rate for {e.needs_s:g} s"
        if e.rows * _DT < e.needs_s:
            return Finding(check, name, SKIP, f"too few rows to check: {e.rows * _DT:.1f} s above {MOVING_MPS:g} m/s "
                           f"with {name} and its reference ({e.reference}) valid", evidence=e, needs=needs)
        return Finding(check, name, SKIP, f"too little turning to check: {e.turning_s:.1f} s beyond "
                       f"{e.threshold_dps:.2g} deg/s of yaw rate ({e.reference}), needs {e.needs_s:g} s",
                       evidence=e, needs=needs)


def _sign_test(agree: float, n: int) -> float:
    """Two-sided binomial sign test: the chance that ``n`` independent signs agree (or disagree) this often."""
    if n <= 0:
        return 1.0
    k = round(agree * n)
    k = max(k, n - k)
    if n > 500:
        return min(1.0, math.erfc((2 * k - n) / math.sqrt(n) / math.sqrt(2.0)))
    return min(1.0, 2.0 * sum(math.comb(n, j) for j in range(k, n + 1)) / 2.0 ** n)


def _turning(y, x, rows, nuisance, thr_x, to_dps, reference: str, v) -> _Turning:
    """``y`` against reference ``x`` on ``rows``: offsets (ones and ``nuisance`` columns) fitted out of both,
    then the rows where ``|x|`` exceeds ``thr_x`` (per row, x's unit; ``to_dps`` turns it into deg/s)."""
    n = int(rows.sum())
    speed = float(np.median(v[rows])) if n else 0.0
    thr_dps = float(np.median((thr_x * to_dps)[rows])) if n else MIN_TURN_DPS
    base = Evidence(reference, 0.0, MIN_TURN_S, thr_dps, n, speed)
    if n < 3:
        return _Turning(base)
    cols = np.stack([np.ones(n), *(c[rows] for c in nuisance)], axis=1)
    xp = x[rows] - cols @ np.linalg.lstsq(cols, x[rows], rcond=None)[0]
    yp = y[rows] - cols @ np.linalg.lstsq(cols, y[rows], rcond=None)[0]
    turn = np.abs(xp) > thr_x[rows]
    turning_s = float(turn.sum()) * _DT
    base = Evidence(reference, turning_s, MIN_TURN_S, thr_dps, n, speed)
    xt, yt = xp[turn], yp[turn]
    sxx, syy, sxy = float(np.dot(xt, xt)), float(np.dot(yt, yt)), float(np.dot(xt, yt))
    if turning_s < MIN_TURN_S or sxx == 0.0:
        return _Turning(base)
    r = sxy / math.sqrt(sxx * syy) if syy > 0.0 else 0.0
    agree = float(np.mean(np.where(yt == 0.0, 0.5, (np.sign(xt) == np.sign(yt)).astype(float))))
    gain = math.copysign(math.sqrt(syy / sxx), sxy) if sxy != 0.0 else 0.0
    ev = Evidence(reference, turning_s, MIN_TURN_S, thr_dps, n, speed, agree, _sign_test(agree, int(turning_s)))
    return _Turning(ev, r, gain)


@dataclass(frozen=True)
class _YawReference:
    """The yaw rate the lateral and steering checks compare with: the yaw signal as its check would fix it,
    or the rear wheels' difference, whichever resolves finer."""

    omega: np.ndarray  # [rad/s]
    ok: np.ndarray  # rows where it is valid
    step: float  # its resolution [rad/s]
    name: str  # for the evidence
    from_wheels: bool


def _rotation(o, ok, wheels, v, moving, step, wheel_step, have_yaw: bool) -> list[Finding]:
    """The yaw, lateral and steering checks, each against the best reference the ones before leave."""
    wheel_yaw = (wheels[:, 3] - wheels[:, 2]) / TRACK_M  # rr - rl: positive in a left (counter-clockwise) turn
    wheel_ref = _YawReference(wheel_yaw, moving, wheel_step / TRACK_M,
                              f"rear wheel-speed difference / {TRACK_M:g} m track", True)
    yaw_finding, factor = _yaw(o, ok, v, moving, wheel_ref, step[_I["yaw_rate_radps"]])
    ref = wheel_ref
    yaw_step = step[_I["yaw_rate_radps"]] * abs(factor or 0.0)
    # a track out of range puts the wheels in doubt (slip): the yaw rate is the reference then, however coarse
    wheels_doubtful = yaw_finding.result == FAIL and yaw_finding.scale_factor not in (None, -1.0)
    if have_yaw and factor is not None and (yaw_step < wheel_ref.step or wheels_doubtful):
        ref = _YawReference(o[:, _I["yaw_rate_radps"]] * factor, moving & ok[:, _I["yaw_rate_radps"]], yaw_step,
                            "yaw rate" + (" (as its fix would read)" if factor != 1.0 else ""), False)
    return [yaw_finding, _lateral(o, ok, v, ref, step[_I["lat_accel_mps2"]]),
            _steering(o, ok, v, ref, step[_I["steering_wheel_angle_rad"]])]


def _yaw(o, ok, v, moving, wheel_ref: _YawReference, yaw_step: float) -> tuple[Finding, float | None]:
    """Yaw rate against the rear wheel-speed difference; also the factor that makes the yaw rate a reference
    (1 when right, -1 flipped, a unit conversion; None when it does not follow the wheels or was not checked)."""
    check, name = "yaw rate against rear wheel-speed difference", "yaw_rate_radps"
    yaw = o[:, _I[name]]
    rows = moving & ok[:, _I[name]]
    thr = np.full(len(v), max(REF_STEPS * wheel_ref.step, SIG_STEPS * yaw_step, MIN_TURN_DPS * _DEG))
    # wheel radius differences make the wheel difference proportional to v; the gyro's offset is a constant
    t = _turning(yaw, wheel_ref.omega, rows, (v,), thr, np.full(len(v), 1 / _DEG), wheel_ref.name, v)
    if not t.enough:
        return t.skip(check, name), None
    sign = t.sign()
    if sign == 0:
        return Finding(check, name, FAIL, f"yaw rate does not follow the wheels ({t.summary()})",
                       "check the message and signal the map names for yaw_rate_radps", r=t.r,
                       evidence=t.evidence), None
    track = TRACK_M / abs(t.gain)  # yaw = dv / track and the reference is dv / TRACK_M
    if sign < 0:
        detail = f"yaw_rate_radps has the opposite sign of the rear wheel-speed difference ({t.summary()})"
        return Finding(check, name, FAIL, detail, "negate its scale", -1.0, r=t.r, gain=track,
                       evidence=t.evidence), -1.0
    if not TRACK_RANGE_M[0] <= track <= TRACK_RANGE_M[1]:
        factor = track / TRACK_M
        detail = f"yaw rate implies a {track:.2f} m track (expected {TRACK_RANGE_M[0]}-{TRACK_RANGE_M[1]} m)"
        # a unit mistake is fixed for the checks after this one; any other factor is more likely the wheels'
        # (slip, a wide track) than the gyro's: they go on with the yaw rate as it reads
        snapped, hint = snap_factor(factor)
        return Finding(check, name, FAIL, detail, _scale_fix(factor), factor, r=t.r, gain=track,
                       evidence=t.evidence), snapped if hint else 1.0
    return Finding(check, name, PASS, f"{t.summary()}, implied track {track:.2f} m", r=t.r, gain=track,
                   evidence=t.evidence), 1.0


def _lateral(o, ok, v, ref: _YawReference, ay_step: float) -> Finding:
    check, name = "lateral acceleration against speed x yaw rate", "lat_accel_mps2"
    a_y = o[:, _I[name]]
    rows = ref.ok & ok[:, _I[name]]
    vv = np.maximum(v, MOVING_MPS)
    thr_yaw = np.maximum(max(REF_STEPS * ref.step, MIN_TURN_DPS * _DEG), SIG_STEPS * ay_step / vv)
    # a yaw-rate offset reads as b * v; the wheels' radius differences as c0 * v + c1 * v^2
    nuisance = (v, v * v) if ref.from_wheels else (v,)
    t = _turning(a_y, v * ref.omega, rows, nuisance, thr_yaw * vv, 1 / (_DEG * vv), f"speed x {ref.name}", v)
    if not t.enough:
        return t.skip(check, name)
    sign = t.sign()
    if sign == 0:
        return Finding(check, name, FAIL, f"lateral acceleration does not follow v x yaw rate ({t.summary()})",
                       "check the message and signal the map names for lat_accel_mps2", r=t.r, evidence=t.evidence)
    gain = abs(t.gain)
    if sign < 0:
        return Finding(check, name, FAIL, f"lat_accel_mps2 has the opposite sign of v*yaw rate ({t.summary()})",
                       "negate its scale", -1.0, r=t.r, gain=gain, evidence=t.evidence)
    if not LAT_GAIN[0] <= gain <= LAT_GAIN[1]:
        factor = 1.0 / gain
        return Finding(check, name, FAIL, f"lateral acceleration is {gain:.3f} x v*yaw rate (expected about 1)",
                       _scale_fix(factor), factor, r=t.r, gain=gain, evidence=t.evidence)
    return Finding(check, name, PASS, f"{t.summary()}, gain {gain:.3f}", r=t.r, gain=gain, evidence=t.evidence)


def _steering(o, ok, v, ref: _YawReference, steer_step: float) -> Finding:
    check, name = "steering wheel angle against path curvature", "steering_wheel_angle_rad"
    delta = o[:, _I[name]]
    rows = ref.ok & ok[:, _I[name]]
    vv = np.maximum(v, MOVING_MPS)
    thr_yaw = np.maximum(max(REF_STEPS * ref.step, MIN_TURN_DPS * _DEG), SIG_STEPS * steer_step / STEER_NOMINAL_M * vv)
    # the steering sensor's zero is a constant; a yaw-rate offset b reads as b / v in the curvature
    t = _turning(delta, ref.omega / vv, rows, (1.0 / vv,), thr_yaw / vv, vv / _DEG,
                 f"curvature: {ref.name} / speed", v)
    if not t.enough:
        return t.skip(check, name)
    sign = t.sign()
    if sign == 0:
        return Finding(check, name, FAIL, f"steering does not follow the path curvature ({t.summary()})",
                       "check the message and signal the map names for steering_wheel_angle_rad", r=t.r,
                       evidence=t.evidence)
    gain = abs(t.gain)  # i_s * L (1 + K v^2) [m]
    if sign < 0:
        return Finding(check, name, FAIL, f"steering_wheel_angle_rad has the opposite sign of the path curvature "
                       f"({t.summary()})", "negate its scale", -1.0, r=t.r, gain=gain, evidence=t.evidence)
    high = STEER_GAIN_M[1] * (1.0 + STEER_UNDERSTEER_S2PM2 * t.evidence.speed_mps ** 2)
    if not STEER_GAIN_M[0] <= gain <= high:
        factor = STEER_NOMINAL_M * (1.0 + STEER_UNDERSTEER_S2PM2 / 2 * t.evidence.speed_mps ** 2) / gain
        hint = unit_hint(factor)
        return Finding(check, name, FAIL, f"steering ratio x wheelbase comes out {gain:.1f} m at "
                       f"{t.evidence.speed_mps:.0f} m/s (expected {STEER_GAIN_M[0]:.0f}-{high:.0f} m)",
                       f"multiply its scale by about {factor:.3g}" + (f" ({hint})" if hint else ""), factor,
                       r=t.r, gain=gain, evidence=t.evidence)
    return Finding(check, name, PASS, f"{t.summary()}, steering ratio x wheelbase {gain:.1f} m", r=t.r, gain=gain,
                   evidence=t.evidence)
