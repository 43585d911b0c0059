"""Online plausibility: the nine onboard signals checked against each other while driving.

A car's CAN bus carries the same motion several times over: four wheel speeds and the
speedometer describe the speed; the yaw rate, the difference of the left and right wheels of
each axle, the lateral acceleration over the speed (``a_y / v``) and the steering wheel angle
through the single-track model (``delta_sw = ratio * (L / v + K v) * omega``) describe the
rotation; the brake pressure is a deceleration the wheels must show. :class:`Plausibility` runs
between the assembler and the localiser and, every 50 Hz row:

1. **speed** — each wheel, corrected to the car's centre for the yaw rate (``-/+ half track *
   omega``) and scaled by its learned rolling-radius ratio, against the median of the other
   wheels; the speedometer against its learned factor times the wheels' speed (low-passed like
   the instrument);
2. **rotation** — up to five estimates of ``omega`` (gyro, rear pair, front pair, ``a_y / v``,
   steering); the yaw rate, ``a_y`` and the steering are each checked, in their own unit, against
   the median of the *other* estimates (leave-one-out: one faulty signal cannot hide itself);
3. **brake** — the wheels' deceleration against the one the brake pressure predicts;
4. **stuck** — every signal whose value has not changed for :attr:`PlausibilityConfig.stuck_hold_s`
   (at least 5 of its periods) while what the others predict for it moved by more than twice its
   tolerance.
5. **offset jumps** (yaw rate, a_y, steering, :meth:`Plausibility._jump_row`): a step within one row
   of the signal's first difference that the residual follows while the others go on as before is
   an offset jump, flagged when confirmed (0.4-0.9 s) even inside the residual tolerance; its size is
   measured from the values around the step and the substitute is the signal less it (reported in
   ``AssembledRow.offset_jumps``, from which the pipeline takes back the heading the jump cost before
   it was found). A confirmed step back ends the correction.

A residual is smoothed (EMA, :attr:`~PlausibilityConfig.smooth_s`); above its tolerance for
:attr:`~PlausibilityConfig.confirm_s` the signal is *flagged*, with a reason (offset, scale,
dropout to zero, stuck); below half the tolerance for :attr:`~PlausibilityConfig.clear_s` it is
cleared. Tolerances are an absolute part, a part relative to the value and (yaw rate, a_y,
steering) the signal's resolution measured online. The relations' unknowns (each axle's effective
track and left/right radius difference, the a_y offset, the steering gain and understeer, the
speedometer factor, every wheel's radius ratio, the brake gain) are learned online by recursive
least squares with forgetting (:attr:`~PlausibilityConfig.learn_tau_s`), only from rows in which
the signals involved are unflagged; a relation takes part in the checks once it has seen enough
driving (:attr:`~PlausibilityConfig.warmup_s`, turns for the steering).

A flagged signal, and a stale one (its message stopped), is taken out: it is invalid for the
filter (no standstill check from it) and its value in the row is replaced by what the others
predict for it (wheel: median of the others, radius ratio and lever arm; speedometer: factor times
the wheels; yaw rate: the weighted median of the other rotation estimates; a_y: ``v omega``;
steering: the single-track model; brake pressure: from the wheels' deceleration), so the model
keeps its full window. ``AssembledRow.substituted`` marks those values (``substitute_std`` their
uncertainty: the filter keeps a substituted yaw rate as its cue, with it added); the pose is ``DEGRADED`` and the status
line names the signal and the reason. Checks run above :attr:`~PlausibilityConfig.min_speed_mps`;
below it (parking, ABS sensors blind) flags hold.

"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from prml2_edge import schema
from prml2_edge.runtime.rows import AssembledRow

_SIG = {s.name: s.index for s in schema.SIGNALS}
VS, SW, YAW, AY, BP = (_SIG[n] for n in ("speedometer_mps", "steering_wheel_angle_rad", "yaw_rate_radps",
                                          "lat_accel_mps2", "brake_pressure_bar"))
FL, FR, RL, RR = schema.WHEEL_SPEED_INDICES
WHEELS = (FL, FR, RL, RR)
N = schema.NUM_SIGNALS
_DEG = schema.DEG_TO_RAD


@dataclass(frozen=True)
class PlausibilityConfig:
    """Tunables of :class:`Plausibility` (SI units). Chosen on the simulated fleet's training cars
    (``benchmarks/reliability.py`` reports the held-out car); the README explains each."""

    enabled: bool = True
    min_speed_mps: float = 5.0  # cross-checks run above this speed
    smooth_s: float = 0.25  # EMA time constant of the speed and brake residuals
    smooth_rot_s: float = 0.4  # and of the rotation residuals (yaw rate, a_y, steering: transients lead and lag)
    confirm_s: float = 0.15  # smoothed residual above tolerance this long: flagged
    clear_s: float = 1.0  # below half the tolerance this long: cleared
    warmup_s: float = 10.0  # driving time before a learned relation takes part in the checks
    learn_tau_s: float = 120.0  # forgetting time of the learned relations
    half_track_m: float = 0.78  # lever arm of the wheels (the effective track is learned per axle)
    steering_ratio: float = 15.0  # only for the front wheels' steer correction
    wheel_tol_mps: float = 0.3
    wheel_tol_rel: float = 0.04
    wheel_vote_tol_mps: float = 0.15  # a wheel further than this from the others does not vote on the rotation
    wheel_slip_per_mps2: float = 0.015  # driven and braked wheels slip: relative tolerance per m/s^2 of |a_x|
    speedo_tol_mps: float = 0.6
    speedo_tol_rel: float = 0.05
    speedo_lag_s: float = 0.25  # the instrument's low-pass
    yaw_tol_radps: float = 0.4 * _DEG
    yaw_tol_rel: float = 0.04
    ay_tol_mps2: float = 0.45
    ay_tol_rel: float = 0.15
    steer_tol_rad: float = 6.0 * _DEG
    steer_tol_rel: float = 0.25
    res_gain: float = 0.5  # tolerance per resolution step of the signal (quantisation)
    # sensors lag each other (yaw-rate and a_y filters, the car's yaw response behind the steering): tolerance
    # per unit of the yaw acceleration, as a time [s]
    lag_yaw_s: float = 0.02  # the yaw-rate sensor and the wheels
    lead_ay_s: float = 0.08  # a_y leads the yaw rate by the side-slip rate
    lead_steer_s: float = 0.15  # the steering leads it by the car's yaw response
    # the wheel- and steering-based rotation estimates pass a first-order lag like the inertial sensors' filters
    inertial_lag_s: float = 0.04
    brake_tol_mps2: float = 0.9  # pressure higher than the deceleration supports (stuck high)
    brake_tol_low_mps2: float = 1.8  # deceleration the pressure does not explain (coasting, engine braking)
    brake_tol_rel: float = 0.3
    brake_min_bar: float = 3.0  # pressure above idle that counts as braking (learning the gain)
    wheel_yaw_max_accel_mps2: float = 2.5  # the wheel pairs estimate the rotation below this |a_x| ...
    wheel_yaw_slip: float = 0.001  # ... with an uncertainty of this times |a_x a_y| v / track (left/right slip)
    ay_check_max_mps2: float = 6.0  # rotation relations are linear below this lateral acceleration
    stuck_hold_s: float = 0.5
    dropout_tol: float = 4.0  # a signal reading 0 this many tolerances from its prediction is flagged at once
    stuck_res_steps: float = 5.0  # ... while the smoothed prediction moved by this many resolution steps ...
    stuck_span_tol: float = 0.5  # ... plus this many absolute tolerances
    substitute_stale: bool = True  # a stale signal (message stopped) gets the others' prediction too
    substitute_yaw_std_radps: float = 0.5 * _DEG  # uncertainty of the others' yaw rate (the filter's cue from it)
    # offset jumps of the yaw rate, a_y and steering: a step in the signal's own first difference (beyond
    # jump_noise_gain times its usual innovation) that the residual follows (its mean over jump_after_s, from
    # jump_lag_s after the step, moved by the step within jump_match of it, against jump_before_s before)
    jump_noise_gain: float = 6.0
    jump_lag_s: float = 0.1  # yaw rate (the motion cannot step: the others follow a real change within 0.1 s) ...
    jump_lag_ay_s: float = 0.3  # ... a_y and the steering: the car's response to a steering step settles first
    jump_lag_steer_s: float = 0.5
    jump_after_s: float = 0.3
    jump_before_s: float = 0.5
    jump_match: float = 0.3
    jump_others_still: float = 0.5  # steering: the others' prediction moved by less than this part of the step
    jump_sharp: float = 0.25  # the differences next to the step stay within this part of it
    jump_steady: float = 0.15  # the residual before and after the step varies by at most this part of it
    jump_drop_s: float = 0.5  # the value less the offset worse than the value itself this long: the correction ends
    jump_min_yaw_radps: float = 1.0 * _DEG  # smallest offset jump looked for (a real step of the motion is smaller)
    jump_min_ay_mps2: float = 0.7
    jump_min_steer_rad: float = 7.0 * _DEG
    jump_steer_max_ay_mps2: float = 5.0
    max_substituted: int = 3  # at most this many signals replaced at once (a whole ESP message is two)


class _Rls:
    """Recursive least squares with exponential forgetting, in plain floats (2 or 3 parameters)."""

    def __init__(self, theta: list[float], prior_std: list[float], forget: float) -> None:
        self.theta = list(theta)
        n = len(theta)
        self.P = [[(prior_std[i] ** 2 if i == j else 0.0) for j in range(n)] for i in range(n)]
        self.max_var = [sd * sd for sd in prior_std]
        self.forget = forget
        self.n = 0

    def update(self, phi: list[float], y: float, noise_var: float) -> None:
        n = len(phi)
        P = self.P
        Pphi = [sum(P[i][j] * phi[j] for j in range(n)) for i in range(n)]
        s = noise_var * self.forget + sum(phi[i] * Pphi[i] for i in range(n))
        if not s > 0.0:
            return
        err = y - sum(self.theta[i] * phi[i] for i in range(n))
        k = [p / s for p in Pphi]
        for i in range(n):
            self.theta[i] += k[i] * err
        lam = self.forget
        for i in range(n):
            for j in range(n):
                P[i][j] = (P[i][j] - k[i] * Pphi[j]) / lam
        # no wind-up: a parameter the data do not excite (the track on a straight) keeps at most its prior
        # uncertainty, so one odd sample cannot move it far
        for i in range(n):
            if P[i][i] > self.max_var[i]:
                f = math.sqrt(self.max_var[i] / P[i][i])
                for j in range(n):
                    P[i][j] *= f
                    P[j][i] *= f
        self.n += 1

    def predict(self, phi: list[float]) -> float:
        return sum(t * p for t, p in zip(self.theta, phi, strict=True))


class _Ema:
    __slots__ = ("a", "value")

    def __init__(self, alpha: float, value: float = 0.0) -> None:
        self.a = alpha
        self.value = value

    def update(self, x: float) -> float:
        self.value += self.a * (x - self.value)
        return self.value


def _weighted_median(items: list[tuple[float, float]]) -> tuple[float, float]:
    """``(value, sigma)`` of the weighted median of ``(value, sigma)`` pairs, weights ``1 / sigma^2``."""
    items = sorted(items)
    w = [1.0 / (sd * sd) for _, sd in items]
    half = 0.5 * sum(w)
    acc = 0.0
    for (value, sd), wi in zip(items, w, strict=True):
        acc += wi
        if acc >= half:
            return value, sd
    return items[-1]


def _mean_at(pts: list[tuple[int, float]]) -> float:
    return sum(v for _, v in pts) / len(pts)


def _trend_at(pts: list[tuple[int, float]], k: float) -> float:
    """The straight line through ``(row, value)`` points (least squares), at row ``k``."""
    n = len(pts)
    km = sum(a for a, _ in pts) / n
    vm = sum(v for _, v in pts) / n
    sxx = sum((a - km) ** 2 for a, _ in pts)
    b = sum((a - km) * (v - vm) for a, v in pts) / sxx if sxx > 0 else 0.0
    return vm + b * (k - km)


def _median(xs: list[float]) -> float:
    s = sorted(xs)
    n = len(s)
    m = n // 2
    return s[m] if n % 2 else 0.5 * (s[m - 1] + s[m])


@dataclass
class _Check:
    """Residual state of one signal."""

    resid: float = 0.0  # smoothed residual [signal unit]
    over_s: float = 0.0  # time above tolerance
    under_s: float = 0.0  # time below half the tolerance (while flagged)
    flagged: bool = False
    reason: str = ""
    # stuck check: time the value last changed and the span of the prediction since
    last_value: float = math.nan
    changed_t: float = -math.inf
    pred_lo: float = math.inf
    pred_hi: float = -math.inf
    resolution: float = math.inf  # smallest change seen
    offset: float = 0.0  # an offset jump measured at its step (the substitute is the value less it)
    offset_std: float = 0.0
    offset_resid: float = 0.0  # smoothed residual of the corrected value
    offset_over_s: float = 0.0


@dataclass
class _Jump:
    """Step detector of one signal: its first differences, their usual innovation, the raw residuals."""

    last_x: float = math.nan
    d1: deque = field(default_factory=lambda: deque(maxlen=6))
    noise: float = 0.0  # EMA of |first difference - local slope|
    noise_n: int = 0
    resid: deque = field(default_factory=lambda: deque(maxlen=96))  # (row number, raw residual, prediction)
    values: deque = field(default_factory=lambda: deque(maxlen=64))  # (row number, value)
    n: int = 0
    cand: list | None = None  # [row number, t, step, pre-step differences, post-step differences, S]


SIGNAL_UNITS = {VS: ("m/s", 1.0), SW: ("deg", 1 / _DEG), YAW: ("deg/s", 1 / _DEG), AY: ("m/s^2", 1.0),
                BP: ("bar", 1.0), FL: ("m/s", 1.0), FR: ("m/s", 1.0), RL: ("m/s", 1.0), RR: ("m/s", 1.0)}


class Plausibility:
    """Cross-checks of the onboard signals, one 50 Hz row per :meth:`check` (module docstring).

    Parameters
    ----------
    rate_hz:
        (9,) rate of each signal on this bus (signal map), for the stuck check's hold time.
    config:
        :class:`PlausibilityConfig`.
    substituted:
        (9,) bool, signals the car lacks (the map's ``absent``): never checked, never replaced.
    """

    def __init__(self, rate_hz, config: PlausibilityConfig | None = None, substituted=None,
                 dt_s: float = schema.DT_S) -> None:
        self.config = cfg = config or PlausibilityConfig()
        self.dt_s = float(dt_s)
        rate = np.asarray(rate_hz, dtype=float)
        self.stuck_hold_s = [max(cfg.stuck_hold_s, 5.0 / float(r)) for r in rate]
        self._tol_abs = [cfg.wheel_tol_mps] * N
        for i, v in ((VS, cfg.speedo_tol_mps), (YAW, cfg.yaw_tol_radps), (AY, cfg.ay_tol_mps2),
                     (SW, cfg.steer_tol_rad), (BP, cfg.brake_min_bar)):
            self._tol_abs[i] = v
        self.absent = [bool(x) for x in (np.zeros(N, bool) if substituted is None else np.asarray(substituted))]
        self.reset()

    def reset(self) -> None:
        cfg = self.config
        dt = self.dt_s
        forget = 1.0 - dt / cfg.learn_tau_s
        self._alpha = [dt / (cfg.smooth_rot_s if i in (YAW, AY, SW) else cfg.smooth_s) for i in range(N)]
        self.checks = [_Check() for _ in range(N)]
        self.jumps = {i: _Jump() for i in (YAW, AY, SW)}
        self._sub_std = {YAW: cfg.substitute_yaw_std_radps}  # uncertainty of the others' prediction as a substitute
        self._jump_rows = {i: (int(round(lag / dt)), int(round(cfg.jump_after_s / dt)),
                               int(round(cfg.jump_before_s / dt)))
                           for i, lag in ((YAW, cfg.jump_lag_s), (AY, cfg.jump_lag_ay_s), (SW, cfg.jump_lag_steer_s))}
        self._jump_min = {YAW: cfg.jump_min_yaw_radps, AY: cfg.jump_min_ay_mps2, SW: cfg.jump_min_steer_rad}
        h2 = 2.0 * cfg.half_track_m
        # wheel pairs: right - left = track * omega + eps * v
        self.rear = _Rls([h2, 0.0], [0.2, 0.02], forget)
        self.front = _Rls([h2, 0.0], [0.2, 0.02], forget)
        # steering: delta_sw = c0 + c1 * omega / v + c2 * omega * v
        self.steer = _Rls([0.0, cfg.steering_ratio * 2.7, cfg.steering_ratio * 0.002],
                          [0.05, 20.0, 0.05], forget)
        self.ay_offset = _Ema(dt / 20.0)
        self.speedo_factor = _Ema(dt / 20.0, 1.04)
        self.wheel_ratio = [_Ema(dt / 30.0, 1.0) for _ in range(4)]
        self.brake_idle = _Ema(dt / 5.0, 0.0)
        self.brake_gain = _Rls([0.1, 0.3], [0.1, 0.5], forget)  # decel = gain * (p - idle) + coast
        self._v_lp = _Ema(dt / cfg.speedo_lag_s)
        self._v_hist: list[float] = []
        self._v_lp_set = False
        self._decel = 0.0
        self._omega = 0.0
        self._omega_rate = _Ema(dt / 0.1)
        self._rate_env = 0.0
        self._w_ng, self._w_ng_set = 0.0, False
        self._rate_decay = math.exp(-dt / (2.0 * cfg.smooth_s))
        self._est_lp = {RL: _Ema(dt / cfg.inertial_lag_s), FL: _Ema(dt / cfg.inertial_lag_s),
                        SW: _Ema(dt / cfg.inertial_lag_s)}
        self._est_seen: dict[int, bool] = {RL: False, FL: False, SW: False}
        self.moving_s = 0.0
        self.turning_s = 0.0
        self.braking_s = 0.0
        self.flag_episodes = [0] * N
        self.flag_rows = [0] * N
        self.substituted_rows = [0] * N
        self.first_flag: list[tuple[float, str] | None] = [None] * N
        self._seen = [False] * N  # a valid value has arrived
        self.untrusted: dict[int, str] = {}  # signals taken out because their message is under attack
        self.offsets_found: list[tuple[int, float, float, float]] = []

    def _restart(self) -> None:
        """After a gap in the stream: the transient state starts again (learned relations and flags stay)."""
        self._v_hist.clear()
        self._v_lp_set = False
        for s_ in self._est_seen:
            self._est_seen[s_] = False
        self._rate_env = 0.0
        self._w_ng_set = False
        for c in self.checks:
            c.resid = c.over_s = 0.0
            c.changed_t = -math.inf
            c.pred_lo, c.pred_hi = math.inf, -math.inf
        for j in self.jumps.values():
            j.last_x = math.nan
            j.d1.clear()
            j.resid.clear()
            j.values.clear()
            j.cand = None

    # ---- one row --------------------------------------------------------------------------------------

    def check(self, row: AssembledRow, untrusted: dict[int, str] | None = None) -> AssembledRow:
        """The row with flagged (and stale) signals invalid and replaced by the others' prediction.

        ``untrusted`` ``{index: reason}``: signals to take out whatever they read (a message under attack).
        """
        if not self.config.enabled:
            return row
        x = row.values.tolist()
        valid = row.valid.tolist()
        if row.discontinuity:
            self._restart()
        self.untrusted = dict(untrusted) if untrusted else {}
        for i in self.untrusted:
            valid[i] = False
        self.offsets_found: list[tuple[int, float, float, float]] = []
        pred, newly = self._step(x, valid, row.t_s)
        new_valid = list(valid)
        subst = [False] * N
        seen = self._seen
        for i in range(N):
            if valid[i]:
                seen[i] = True
            c = self.checks[i]
            if c.flagged and not self.absent[i]:
                new_valid[i] = False
                self.flag_rows[i] += 1
        out = [i for i in range(N) if not new_valid[i] and not self.absent[i]]
        # replace only while enough of the car is left to predict from: a signal never received is a map
        # mistake (the runtime says so), and with most of the bus gone there is nothing to predict from
        std = [math.nan] * N
        if 0 < len(out) <= self.config.max_substituted:
            raw_valid = row.valid
            for i in out:
                c = self.checks[i]
                if not seen[i]:
                    continue
                if c.flagged and c.offset and raw_valid[i] and i not in self.untrusted:
                    x[i] -= c.offset  # an offset jump: the value less it
                    std[i] = c.offset_std
                elif (c.flagged or i in self.untrusted or self.config.substitute_stale) and pred[i] is not None:
                    x[i] = pred[i]
                    std[i] = self._sub_std.get(i, math.nan)
                else:
                    continue
                subst[i] = True
                self.substituted_rows[i] += 1
        if not any(subst) and not newly and not self.offsets_found and new_valid == row.valid.tolist():
            return row
        return replace(row, values=np.asarray(x), valid=np.asarray(new_valid, dtype=bool),
                       substituted=np.asarray(subst, dtype=bool), newly_flagged=tuple(newly),
                       substitute_std=np.asarray(std) if any(subst) else None,
                       offset_jumps=tuple(self.offsets_found))

    def _ok(self, i: int, valid: list[bool]) -> bool:
        return valid[i] and not self.checks[i].flagged

    def _step(self, x: list[float], valid: list[bool], t: float) -> tuple[list[float | None], list[int]]:
        cfg = self.config
        dt = self.dt_s
        pred: list[float | None] = [None] * N
        tol = [math.inf] * N
        resid: list[float | None] = [None] * N
        h = cfg.half_track_m
        w = self._omega
        ok = [self._ok(i, valid) for i in range(N)]

        # ---- 1. speed ----
        lever = (-h, h, -h, h)
        steer_road = abs(x[SW]) / cfg.steering_ratio if valid[SW] else 0.0
        cos_front = math.cos(min(steer_road, 1.0))
        u = [0.0] * 4
        for j, i in enumerate(WHEELS):
            ui = x[i] - lever[j] * w
            if j < 2:
                ui *= cos_front  # a steered wheel runs on a larger radius than the rear axle
            u[j] = ui / self.wheel_ratio[j].value
        usable = [j for j, i in enumerate(WHEELS) if ok[i]]
        v_hat = _median([u[j] for j in usable]) if usable else (
            x[VS] / self.speedo_factor.value if ok[VS] else None)
        moving = v_hat is not None and v_hat >= cfg.min_speed_mps
        if moving:
            self.moving_s += dt
        v = v_hat if v_hat is not None else 0.0
        for j, i in enumerate(WHEELS):
            others = [u[k] for k in usable if k != j]
            if not others:
                continue
            ref = _median(others)
            back = ref * self.wheel_ratio[j].value
            if j < 2:
                back /= cos_front
            pred[i] = max(back + lever[j] * w, 0.0)
            if moving and len(others) >= 2 and valid[i]:
                slack = (1.0 / cos_front - 1.0) * ref
                rel = cfg.wheel_tol_rel + cfg.wheel_slip_per_mps2 * abs(self._decel)
                tol[i] = cfg.wheel_tol_mps + rel * ref + slack
                resid[i] = x[i] - pred[i]
                if ok[i] and len(others) == 3 and self.checks[i].resid ** 2 < 0.25 * tol[i] ** 2:
                    self.wheel_ratio[j].update(self.wheel_ratio[j].value * u[j] / ref if ref > 0 else 1.0)
        # a wheel whose residual already exceeds half its tolerance does not vote on the rotation
        calm_w = [ok[i] and (resid[i] is None or abs(resid[i]) < cfg.wheel_vote_tol_mps) for i in WHEELS]  # type: ignore
        if v_hat is None:
            self._v_lp_set = False  # the instrument's filter starts again when the wheels are back
        elif not self._v_lp_set:
            self._v_lp.value, self._v_lp_set = v, True
        v_lp = self._v_lp.update(v) if v_hat is not None else self._v_lp.value
        pred[VS] = self.speedo_factor.value * v_lp if usable else None
        if moving and valid[VS] and len(usable) >= 2:
            tol[VS] = cfg.speedo_tol_mps + cfg.speedo_tol_rel * v_lp
            resid[VS] = x[VS] - pred[VS]  # type: ignore[operator]
            if ok[VS] and self.checks[VS].resid ** 2 < 0.25 * tol[VS] ** 2:
                self.speedo_factor.update(x[VS] / v_lp if v_lp > 0 else self.speedo_factor.value)

        hist = self._v_hist
        if v_hat is None:
            hist.clear()  # nothing to differentiate: the deceleration restarts when the wheels are back
        else:
            hist.append(v)
        if len(hist) > 11:
            del hist[0]
        decel = (hist[0] - hist[-1]) / (10 * dt) if len(hist) == 11 else 0.0
        self._decel = decel  # (the wheel check of the next row uses it)

        # ---- 2. rotation ----
        # braking or accelerating hard, the inner wheels slip more than the outer (load transfer): the wheel
        # pairs do not measure the rotation then
        grip = abs(decel) < cfg.wheel_yaw_max_accel_mps2
        est: dict[int, float] = {}  # source signal (YAW, AY, SW, RL for the rear pair, FL for the front) -> omega
        sd: dict[int, float] = {}  # and its uncertainty [rad/s]
        env = self._rate_env
        if valid[YAW]:
            est[YAW] = x[YAW] - self.checks[YAW].offset
            sd[YAW] = 0.3 * _DEG + 0.5 * self._resolution(YAW) + cfg.lag_yaw_s * env
        if v >= 1.0:  # (the checks need `moving`; below it the estimates still feed the substitutes)
            if grip and calm_w[2] and calm_w[3] and self.rear.n * dt >= cfg.warmup_s:
                est[RL] = (x[RR] - x[RL] - self.rear.theta[1] * v) / self.rear.theta[0]
            if grip and calm_w[0] and calm_w[1] and self.front.n * dt >= cfg.warmup_s:
                est[FL] = (x[FR] - x[FL] - self.front.theta[1] * v) / (self.front.theta[0] * cos_front)
            if valid[AY] and self.moving_s >= cfg.warmup_s and v >= 3.0:
                est[AY] = (x[AY] - self.checks[AY].offset - self.ay_offset.value) / v
                sd[AY] = (0.2 + 0.1 * abs(x[AY]) + 0.5 * self._resolution(AY)) / v + cfg.lead_ay_s * env
            if valid[SW] and self.turning_s >= cfg.warmup_s and v >= 3.0:
                g = self.steer.theta[1] / v + self.steer.theta[2] * v
                if g > 1.0:
                    est[SW] = (x[SW] - self.checks[SW].offset - self.steer.theta[0]) / g
                    sd[SW] = (1.0 * _DEG + 0.1 * abs(x[SW]) + 0.5 * self._resolution(SW)) / g + cfg.lead_steer_s * env
        for s_, lp in self._est_lp.items():
            if s_ in est:
                if not self._est_seen[s_]:
                    lp.value = est[s_]
                est[s_] = lp.update(est[s_])
                if s_ in (RL, FL):
                    a_lat = abs(x[AY]) if valid[AY] else abs(v * w)
                    sd[s_] = ((0.005 + 0.0003 * v + cfg.wheel_yaw_slip * abs(decel) * a_lat * v) / 1.56
                              + 0.02 * abs(est[s_]) + cfg.lag_yaw_s * env)
            self._est_seen[s_] = s_ in est
        # (a signal corrected for an offset jump it was flagged for goes on predicting the others, less the offset;
        # its own check stays on the raw value, which must step back)
        sources_ok = {s: e for s, e in est.items() if s in (RL, FL) or ok[s] or (self.checks[s].offset and valid[s])}
        if RL in sources_ok and FL in sources_ok and \
                abs(sources_ok[RL] - sources_ok[FL]) > 3.0 * (sd[RL] + sd[FL]) + 1.0 * _DEG:
            # the two wheel pairs disagree (a wheel a little off moves its pair's estimate by degrees per second):
            # keep the one closer to the other estimates, or neither
            rest = [e for k, e in sources_ok.items() if k not in (RL, FL)]
            if rest:
                m = _median(rest)
                del sources_ok[RL if abs(sources_ok[RL] - m) > abs(sources_ok[FL] - m) else FL]
            else:
                del sources_ok[RL], sources_ok[FL]
        if sources_ok:
            omega = _weighted_median([(e, sd[k]) for k, e in sources_ok.items()])[0]
        else:
            omega = 0.0 if v_hat is not None and v < 1.0 else w
        # yaw acceleration envelope, peak-held and decaying over the residuals' memory, from the estimates other
        # than the gyro (an offset jump of the gyro must not widen its own tolerance)
        not_gyro = [(e, sd[k]) for k, e in sources_ok.items() if k != YAW]
        w_ng = _weighted_median(not_gyro)[0] if not_gyro else omega
        rate = max(abs(self._omega_rate.update((w_ng - self._w_ng) / dt)) if self._w_ng_set else 0.0,
                   self._rate_env * self._rate_decay)
        self._w_ng, self._w_ng_set = w_ng, bool(not_gyro)
        self._rate_env = rate
        for s in (YAW, AY, SW):
            others = [(e, sd[k]) for k, e in sources_ok.items() if k != s]
            w_ref, sd_ref = _weighted_median(others) if others else (omega, math.inf)
            if not others and not (v_hat is not None and v < 1.0):
                pass  # nothing left to predict the rotation from
            elif s == YAW:
                pred[YAW] = w_ref
            elif s == AY:
                pred[AY] = self.ay_offset.value + v * w_ref
            elif v > 3.0:
                pred[SW] = self.steer.predict([1.0, w_ref / v, w_ref * v])
            elif valid[SW]:
                pred[SW] = x[SW]  # parking: nothing predicts the steering; hold it
            if not (moving and s in est and len(others) >= 2):
                continue
            res = self._resolution(s)
            if s == YAW:
                tol[s] = cfg.yaw_tol_radps + cfg.yaw_tol_rel * abs(w_ref) + cfg.res_gain * res + sd_ref
            elif s == AY:
                tol[s] = (cfg.ay_tol_mps2 + cfg.ay_tol_rel * abs(pred[AY]) + cfg.res_gain * res  # type: ignore[arg-type]
                          + (sd_ref + cfg.lead_ay_s * rate) * v)
            else:
                g = self.steer.theta[1] / v + self.steer.theta[2] * v
                tol[s] = (cfg.steer_tol_rad + cfg.steer_tol_rel * abs(pred[SW]) + cfg.res_gain * res  # type: ignore[arg-type]
                          + (sd_ref + cfg.lead_steer_s * rate) * g)
            resid[s] = x[s] - pred[s]  # type: ignore[operator]
        self._omega = omega
        # learning the rotation relations from the gyro, while everything involved agrees
        # the gyro teaches the other relations only while it agrees with them (a fault not yet flagged must not
        # pull them along)
        warming = min(self.rear.n, self.front.n) * dt < cfg.warmup_s  # nothing to check the gyro against yet
        gyro_calm = abs(self.checks[YAW].resid) < 0.5 * tol[YAW] if resid[YAW] is not None else warming
        calm = moving and ok[YAW] and gyro_calm and (not valid[AY] or abs(x[AY]) < cfg.ay_check_max_mps2)
        if calm:
            wy = x[YAW]
            if grip and ok[RL] and ok[RR]:
                self.rear.update([wy, v], x[RR] - x[RL], 0.02 ** 2)
            if grip and ok[FL] and ok[FR]:
                self.front.update([wy * cos_front, v], x[FR] - x[FL], 0.03 ** 2)
            if ok[AY] and abs(x[AY]) < 3.0:
                self.ay_offset.update(x[AY] - v * wy)
            if ok[SW] and abs(x[AY] if valid[AY] else v * wy) < 4.0:
                self.steer.update([1.0, wy / v, wy * v], x[SW], (2.0 * _DEG) ** 2)
                if abs(wy) > 2.0 * _DEG:
                    self.turning_s += dt

        # ---- 3. brake: the wheels' deceleration against the pressure's ----
        idle = self.brake_idle.value
        g_b, coast = self.brake_gain.theta
        if g_b > 0.02 and usable:
            pred[BP] = idle + max(decel - coast, 0.0) / g_b
        if valid[BP] and v > 3.0 and len(hist) == 11:
            if ok[BP]:
                if decel < 0.2 and x[BP] < idle + cfg.brake_min_bar:
                    self.brake_idle.update(x[BP])
                if x[BP] > idle + cfg.brake_min_bar:
                    self.braking_s += dt
                self.brake_gain.update([max(x[BP] - idle, 0.0), 1.0], decel, 0.3 ** 2)
            if self.braking_s >= 2.0 and g_b > 0.02 and moving and pred[BP] is not None:
                a_pred = g_b * max(x[BP] - idle, 0.0) + coast
                # in bar; pressure above the prediction (r > 0) gets the tighter tolerance
                r = x[BP] - pred[BP]  # type: ignore[operator]
                low = self.checks[BP].resid < 0.0
                tol[BP] = ((cfg.brake_tol_low_mps2 if low else cfg.brake_tol_mps2)
                           + cfg.brake_tol_rel * abs(a_pred)) / g_b
                resid[BP] = r

        # ---- 4. residuals, stuck, flags ----
        newly = []
        for i in range(N):
            if self.absent[i] or not valid[i]:
                continue
            c = self.checks[i]
            xi = x[i]
            if xi != c.last_value:
                if math.isfinite(c.last_value):
                    step = abs(xi - c.last_value)
                    if step < c.resolution:
                        c.resolution = step
                c.last_value = xi
                c.changed_t = t
                c.pred_lo, c.pred_hi = math.inf, -math.inf
            r = resid[i]
            if i in self.jumps:
                # (the single-track relation the steering is checked by holds only at low lateral acceleration)
                linear = i != SW or abs(x[AY] if valid[AY] else v * w) < cfg.jump_steer_max_ay_mps2
                self._jump_row(i, xi, r, moving and linear, t, c, pred[i], newly)
            if r is None:
                continue
            c.resid += self._alpha[i] * (r - c.resid)
            ti = tol[i]
            # stuck: the value has not changed while the *smoothed* prediction (the held value less the smoothed
            # residual) moved by more than a few resolution steps; a healthy sensor of that resolution would have
            # changed (the raw prediction's noise alone must not trip it on a coarse sensor)
            c.pred_lo = min(c.pred_lo, -c.resid)
            c.pred_hi = max(c.pred_hi, -c.resid)
            span = c.pred_hi - c.pred_lo
            stuck = (t - c.changed_t >= self.stuck_hold_s[i] and abs(c.resid) > 0.5 * ti
                     and span > cfg.stuck_res_steps * self._resolution(i) + cfg.stuck_span_tol * self._tol_abs[i]
                     and (i != BP or xi > self.brake_idle.value + cfg.brake_min_bar))  # idle: nobody brakes
            if not c.flagged:
                if abs(c.resid) > ti:
                    c.over_s += dt
                else:
                    c.over_s = 0.0
                # a dropout (exactly 0 where the others say far more) is flagged at once: every row it stays in
                # the window and the filter costs heading
                dropout = xi == 0.0 and abs(r) > cfg.dropout_tol * ti
                if c.over_s >= cfg.confirm_s or stuck or dropout:
                    c.flagged = True
                    c.under_s = 0.0
                    c.reason = self._reason(i, xi, pred[i], c, stuck, t)
                    newly.append(i)
                    self.flag_episodes[i] += 1
                    if self.first_flag[i] is None:
                        self.first_flag[i] = (t, c.reason)
            else:
                if c.offset:
                    # the corrected value must agree with the others, or the correction was wrong (a drift, a scale)
                    c.offset_resid += self._alpha[i] * (r - c.offset - c.offset_resid)
                    worse = abs(c.offset_resid) > ti and abs(c.offset_resid) > abs(c.resid)
                    c.offset_over_s = c.offset_over_s + dt if worse else 0.0
                    if c.offset_over_s >= cfg.jump_drop_s:
                        c.offset = 0.0
                        c.reason += "; the value less it disagrees too: the others' prediction replaces it"
                # (an offset jump measured at its step ends with the step back, or when the value less it disagrees)
                if abs(c.resid) < 0.5 * ti and t - c.changed_t < self.stuck_hold_s[i] and not c.offset:
                    c.under_s += dt
                    if c.under_s >= cfg.clear_s:
                        c.flagged = False
                        c.over_s = 0.0
                        c.offset = 0.0
                        c.reason = ""
                else:
                    c.under_s = 0.0
        return pred, newly

    def _jump_row(self, i: int, xi: float, r: float | None, moving: bool, t: float, c: _Check,
                  p: float | None, newly: list[int]) -> None:
        """Offset jumps: a step in the signal's first difference that its residual follows.

        A step ``S`` (the difference at one row less the local slope, from the 5 differences either side) beyond
        :attr:`~PlausibilityConfig.jump_noise_gain` times the usual innovation, the signal's ``jump_min_*`` and
        1.5 resolution steps, with the differences next to it and the slope after it as before (``jump_sharp``), is
        a candidate. It is an offset jump when the raw residual's mean over ``jump_after_s`` (from the signal's
        ``jump_lag*_s`` after the step) moved from its mean over ``jump_before_s`` before by ``S`` within
        ``jump_match``, the residual steady on both sides (``jump_steady``) and, for the steering, the others'
        prediction going on along its trend (``jump_others_still``): a real change of the car's motion moves the
        others with it, a bump is gone by then. :meth:`_offset_found` then measures it and flags the signal.
        """
        cfg = self.config
        j = self.jumps[i]
        j.n += 1
        n = j.n
        if r is not None and p is not None:
            j.resid.append((n, r, p))
        d = xi - j.last_x if math.isfinite(j.last_x) else math.nan
        j.last_x = xi
        j.values.append((n, xi))
        if not math.isfinite(d):
            return
        lag, after, before = self._jump_rows[i]
        res = self._resolution(i)
        cand = j.cand
        if cand is not None:
            if cand[5] is None:
                cand[4].append(d)
                if len(cand[4]) == 5:
                    slope = 0.5 * (_median(cand[3]) + _median(cand[4]))
                    cand[5] = cand[2] - slope
                    # an offset jumps within one row; the driver's fastest steering, a bump, take several
                    # and the signal goes on at the rate it had (a driver's step starts a ramp)
                    if max(abs(cand[3][-1] - slope), abs(cand[4][0] - slope), abs(cand[4][1] - slope),
                           abs(_median(cand[4]) - _median(cand[3]))) > cfg.jump_sharp * abs(cand[5]) + res:
                        j.cand = None
                        j.d1.append(d)
                        return
            elif n - cand[0] >= lag + after:
                j.cand = None
                step = cand[5]
                win_pre = [e for e in j.resid if cand[0] - before <= e[0] < cand[0]]
                win_post = [e for e in j.resid if cand[0] + lag <= e[0] < cand[0] + lag + after]
                pre, post = [e[1] for e in win_pre], [e[1] for e in win_post]
                p_pre, p_post = [(e[0], e[2]) for e in win_pre], [(e[0], e[2]) for e in win_post]
                # steering: the others went on as they were going (a driver's steering step turns the car after it)
                still = i != SW or (len(p_pre) >= 3 and bool(p_post) and abs(
                    _mean_at(p_post) - _trend_at(p_pre, sum(k for k, _ in p_post) / len(p_post)))
                    < cfg.jump_others_still * abs(step))
                if still and len(pre) >= before // 2 and len(post) >= after // 2:
                    m0, m1 = sum(pre) / len(pre), sum(post) / len(post)
                    shift = m1 - m0
                    # an offset leaves the residual as steady as it was; a response settling (the car catching
                    # up with a fast steering input) moves it
                    var0 = sum((a - m0) ** 2 for a in pre) / len(pre)
                    var1 = sum((a - m1) ** 2 for a in post) / len(post)
                    lim = (cfg.jump_steady * step) ** 2 + 0.25 * res * res  # (a coarse signal's quantisation)
                    steady = var0 <= lim and var1 <= lim + 2.0 * var0
                    if steady and shift * step > 0 and \
                            abs(shift - step) < cfg.jump_match * abs(step) + 2.0 * math.sqrt(var0 + var1):
                        self._offset_found(i, c, step, shift, pre, post, m0, m1, res, cand, t, xi, p, newly)
        if j.cand is None and moving and j.noise_n >= 50 and len(j.d1) == j.d1.maxlen:
            hist = list(j.d1)[-5:]
            inn = d - _median(hist)
            if abs(inn) > max(cfg.jump_noise_gain * j.noise, self._jump_min[i], 1.5 * res):
                j.cand = [n, t, d, hist, [], None]
            else:
                j.noise += (min(abs(inn), 4.0 * j.noise) - j.noise) * self.dt_s / 5.0
        elif j.cand is None and len(j.d1) == j.d1.maxlen:
            inn = abs(d - _median(list(j.d1)[-5:]))
            j.noise_n += 1
            j.noise += (inn - j.noise) / min(j.noise_n, 250) if j.noise_n < 50 else \
                (min(inn, 4.0 * j.noise) - j.noise) * self.dt_s / 5.0
        j.d1.append(d)

    @staticmethod
    def _step_fit(j: _Jump, k0: int, half: int = 15) -> tuple[float, float] | None:
        """``(step, std)`` at row ``k0`` from the values around it: a quadratic in time plus a step, least squares."""
        pts = [(k - k0, v) for k, v in j.values if -half <= k - k0 < half]
        if len(pts) < half or sum(1 for tau, _ in pts if tau < 0) < 4 or sum(1 for tau, _ in pts if tau >= 0) < 4:
            return None
        tau = np.array([p_[0] for p_ in pts], dtype=float)
        a = np.column_stack([np.ones_like(tau), tau, tau * tau, (tau >= 0).astype(float)])
        y = np.array([p_[1] for p_ in pts])
        coef, *_ = np.linalg.lstsq(a, y, rcond=None)
        dof = len(pts) - 4
        s2 = float(np.sum((y - a @ coef) ** 2)) / dof if dof > 0 else 0.0
        return float(coef[3]), math.sqrt(s2 * float(np.linalg.inv(a.T @ a)[3, 3]))

    def _offset_found(self, i, c, step, shift, pre, post, m0, m1, res, cand, t, xi, p, newly) -> None:
        """An offset jump confirmed: flag the signal (if not yet) and correct it by the measured offset."""
        if c.flagged and c.reason.startswith(("stuck", "dropout")):
            return  # a dead value, not an offset: the others' prediction stays its substitute
        if xi == 0.0:
            return
        t_step = cand[1]
        fit = self._step_fit(self.jumps[i], cand[0])
        before = c.offset
        if fit is not None:
            # the values around the step measure it best (the residual carries the others' noise); they must see the
            # step too (a coarse signal's difference wobbles by a step: the values around it do not)
            if abs(fit[0] - step) > self.config.jump_match * abs(step) + res \
                    or abs(fit[0]) < max(self._jump_min[i], 1.5 * res):
                return
            c.offset, sd_fit = fit
            c.offset_std = math.hypot(sd_fit, res / math.sqrt(12.0))
        else:
            var_d = 2.0 * self.jumps[i].noise ** 2 + res * res / 3.0
            var_s = (sum((a - m0) ** 2 for a in pre) / len(pre) / max(len(pre) / 5.0, 1.0)
                     + sum((a - m1) ** 2 for a in post) / len(post) / max(len(post) / 5.0, 1.0))
            w = var_s / (var_d + var_s) if var_d + var_s > 0 else 1.0
            c.offset = w * step + (1.0 - w) * shift
            c.offset_std = math.sqrt(var_d * var_s / (var_d + var_s)) if var_d + var_s > 0 else 0.0
        c.offset_resid, c.offset_over_s = 0.0, 0.0
        if before:
            if c.offset * before < 0 and abs(c.offset + before) < self.config.jump_match * abs(before) + res:
                c.offset = 0.0  # it stepped back: the correction ends, the flag clears as usual
                c.reason += f"; stepped back at {t_step:.2f} s"
                return
            c.offset += before  # a second jump on top of the first
        self.offsets_found.append((i, c.offset - before, c.offset_std, t_step))
        unit, k = SIGNAL_UNITS[i]
        ref = f"{p * k:.2f}" if p is not None else "?"
        c.reason = (f"offset: jumped by {c.offset * k:+.2f} {unit} at {t_step:.2f} s (reads {xi * k:.2f} where the "
                    f"others say {ref}); replaced by the value less the jump")
        if not c.flagged:
            c.flagged = True
            c.under_s = 0.0
            newly.append(i)
            self.flag_episodes[i] += 1
            if self.first_flag[i] is None:
                self.first_flag[i] = (t, c.reason)

    def _resolution(self, i: int) -> float:
        """Smallest change of signal ``i`` seen so far, at most the coarsest common step (the reference car's)."""
        return min(self.checks[i].resolution, schema.SIGNALS[i].revsted_step)

    def _reason(self, i: int, x: float, p: float | None, c: _Check, stuck: bool, t: float) -> str:
        unit, k = SIGNAL_UNITS[i]
        ref = f"{p * k:.2f}" if p is not None else "?"
        if stuck:
            return f"stuck at {x * k:.2f} {unit} for {t - c.changed_t:.1f} s while the others moved it to {ref}"
        if x == 0.0 and p is not None and abs(p) > 0.0:
            return f"dropout: reads 0 where the others say {ref} {unit}"
        if i in WHEELS or i == VS:
            ratio = x / p if p else math.nan
            return f"scale: reads {x * k:.2f} {unit}, {ratio:.3f} x what the others say ({ref})"
        return f"offset: reads {x * k:.2f} {unit} where the others say {ref} ({c.resid * k:+.2f})"

    # ---- reporting ------------------------------------------------------------------------------------

    @property
    def flagged(self) -> np.ndarray:
        return np.array([c.flagged for c in self.checks], dtype=bool)

    def reasons(self) -> dict[str, str]:
        """``{signal name: why it is out}`` for the signals flagged (or untrusted) now."""
        out = {schema.SIGNAL_NAMES[i]: c.reason for i, c in enumerate(self.checks) if c.flagged}
        out.update({schema.SIGNAL_NAMES[i]: why for i, why in self.untrusted.items()})
        return out

    def summary(self) -> dict:
        names = schema.SIGNAL_NAMES
        return {
            "enabled": self.config.enabled,
            "flagged_now": self.reasons(),
            "flag_episodes": {names[i]: n for i, n in enumerate(self.flag_episodes) if n},
            "flagged_rows": {names[i]: n for i, n in enumerate(self.flag_rows) if n},
            "substituted_rows": {names[i]: n for i, n in enumerate(self.substituted_rows) if n},
            "first_flag": {names[i]: {"t_s": f[0], "reason": f[1]} for i, f in enumerate(self.first_flag) if f},
            "learned": {"rear_track_m": self.rear.theta[0], "rear_radius_diff": self.rear.theta[1],
                        "front_track_m": self.front.theta[0], "front_radius_diff": self.front.theta[1],
                        "lat_accel_offset_mps2": self.ay_offset.value, "speedometer_factor": self.speedo_factor.value,
                        "steering_gain": self.steer.theta[1], "steering_understeer": self.steer.theta[2],
                        "wheel_ratio": [e.value for e in self.wheel_ratio],
                        "brake_gain_mps2_per_bar": self.brake_gain.theta[0]},
            "driving_s": self.moving_s,
        }
