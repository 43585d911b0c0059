"""The relations: how each signal is predicted from the others, how far it may read from that, what they learn.

A car's CAN bus carries the same motion several times over, and every row each signal gets a prediction from the
others, a tolerance and a residual (steps 1-3 of the stage):

1. **speed** — each wheel, corrected to the car's centre for the yaw rate (``-/+ half track * omega``) and scaled by
   its learned rolling-radius ratio, against the median of the other wheels; the speedometer against its learned
   factor times the wheels' speed (low-passed like the instrument);
2. **rotation** — up to five estimates of ``omega`` (gyro, rear pair, front pair, ``a_y / v``, steering through the
   single-track model ``delta_sw = ratio * (L / v + K v) * omega``); the yaw rate, ``a_y`` and the steering are each
   checked, in their own unit, against the weighted median of the *other* estimates (leave-one-out: one faulty
   signal cannot hide itself);
3. **brake** — the wheels' deceleration against the one the brake pressure predicts.

Tolerances are an absolute part, a part relative to the value and (yaw rate, a_y, steering) the signal's resolution
measured online, plus the lags between the sensors as a time times the yaw acceleration. The unknowns (each axle's
effective track and left/right radius difference, the a_y offset, the steering gain and understeer, the speedometer
factor, every wheel's radius ratio, the brake gain) are learned online by recursive least squares with forgetting
(:attr:`~.PlausibilityConfig.learn_tau_s`), only from rows in which the signals involved are unflagged; a relation
takes part in the checks once it has seen enough driving (:attr:`~.PlausibilityConfig.warmup_s`, turns for the
steering). The predictions are also what replaces a signal taken out (:mod:`.substitute`).
"""

from __future__ import annotations

import math

from .config import _DEG, AY, BP, COARSEST_STEP, FL, FR, RL, RR, SW, VS, WHEELS, YAW, N, PlausibilityConfig
from .models import Ema, Rls, median, weighted_median


class Relations:
    """The relations' learned models and what they carry from row to row (filters, the last rotation, drive time).

    ``checks`` is the stage's list of per-signal :class:`~.checks.Check`, read here: a relation learns only from
    unflagged, calm signals, and a signal corrected for an offset jump predicts the others less its offset.
    """

    def __init__(self, cfg: PlausibilityConfig, dt_s: float, checks: list) -> None:
        self.cfg = cfg
        self.dt_s = dt = dt_s
        self.checks = checks
        forget = 1.0 - dt / cfg.learn_tau_s
        h = cfg.half_track_m
        self._lever = (-h, h, -h, h)  # lever arm of each wheel about the car's centre
        h2 = 2.0 * cfg.half_track_m
        # wheel pairs: right - left = track * omega + eps * v
        self.rear = Rls([h2, 0.0], [0.2, 0.02], forget)
        self.front = Rls([h2, 0.0], [0.2, 0.02], forget)
        # steering: delta_sw = c0 + c1 * omega / v + c2 * omega * v
        self.steer = Rls([0.0, cfg.steering_ratio * 2.7, cfg.steering_ratio * 0.002], [0.05, 20.0, 0.05], forget)
        self.ay_offset = Ema(dt / 20.0)
        self.speedo_factor = Ema(dt / 20.0, 1.04)
        self.wheel_ratio = [Ema(dt / 30.0, 1.0) for _ in range(4)]
        self.brake_idle = Ema(dt / 5.0, 0.0)
        self.brake_gain = Rls([0.1, 0.3], [0.1, 0.5], forget)  # decel = gain * (p - idle) + coast
        self._v_lp = Ema(dt / cfg.speedo_lag_s)
        self._v_hist: list[float] = []
        self._v_lp_set = False
        self._decel = 0.0
        self._omega = 0.0
        self._omega_rate = Ema(dt / 0.1)
        self._rate_env = 0.0
        self._w_ng, self._w_ng_set = 0.0, False
        self._rate_decay = math.exp(-dt / (2.0 * cfg.smooth_s))
        self._est_lp = {RL: Ema(dt / cfg.inertial_lag_s), FL: Ema(dt / cfg.inertial_lag_s),
                        SW: Ema(dt / cfg.inertial_lag_s)}
        self._est_seen: dict[int, bool] = {RL: False, FL: False, SW: False}
        self._lsd: dict[int, float] = {RL: 0.0, FL: 0.0}  # what the wheel pairs' learned relations do not know
        self.moving_s = 0.0
        self.turning_s = 0.0
        self.braking_s = 0.0

    def restart(self) -> None:
        """After a gap in the stream: the filters and differences start again (the learned models stay)."""
        self._v_hist.clear()
        self._v_lp_set = False
        for s_ in self._est_seen:
            self._est_seen[s_] = False
        self._rate_env = 0.0
        self._w_ng_set = False

    def resolution(self, i: int) -> float:
        """Smallest change of signal ``i`` seen so far, at most the coarsest common step (the reference car's)."""
        return min(self.checks[i].resolution, COARSEST_STEP[i])

    def predict(self, x: list[float], valid: list[bool], ok: list[bool]):
        """Steps 1-3 on one row: ``(pred, tol, resid, moving, v, w)``.

        ``pred``, ``tol`` and ``resid`` per signal (None, inf, None where there is none this row); ``moving``: the
        car drives (the checks run), ``v`` its speed, ``w`` the rotation of the row before. ``ok``: valid and not
        flagged (what the relations may learn from and predict with).
        """
        pred: list[float | None] = [None] * N
        tol = [math.inf] * N
        resid: list[float | None] = [None] * N
        w = self._omega
        v_hat, v, moving, cos_front, usable, calm_w, decel = self._speed(x, valid, ok, w, pred, tol, resid)
        self._rotation(x, valid, ok, v_hat, v, moving, cos_front, calm_w, decel, w, pred, tol, resid)
        self._brake(x, valid, ok, v, moving, usable, decel, pred, tol, resid)
        return pred, tol, resid, moving, v, w

    # ---- 1. speed ----------------------------------------------------------------------------------------

    def _speed(self, x, valid, ok, w, pred, tol, resid):
        """The car's speed from the wheels (or the speedometer), the wheels' and the speedometer's checks and the
        deceleration: ``(v_hat, v, moving, cos_front, usable wheels, calm wheels, decel)``."""
        cfg = self.cfg
        lever = self._lever
        steer_road = abs(x[SW]) / cfg.steering_ratio if valid[SW] else 0.0
        cos_front = math.cos(min(steer_road, 1.0))
        u = [0.0] * 4
        for j, i in enumerate(WHEELS):
            ui = x[i] - lever[j] * w
            if j < 2:
                ui *= cos_front  # a steered wheel runs on a larger radius than the rear axle
            u[j] = ui / self.wheel_ratio[j].value
        usable = [j for j, i in enumerate(WHEELS) if ok[i]]
        v_hat = median([u[j] for j in usable]) if usable else (
            x[VS] / self.speedo_factor.value if ok[VS] else None)
        moving = v_hat is not None and v_hat >= cfg.min_speed_mps
        if moving:
            self.moving_s += self.dt_s
        v = v_hat if v_hat is not None else 0.0
        self._wheels(x, valid, ok, w, u, usable, moving, cos_front, pred, tol, resid)
        # a wheel whose residual already exceeds wheel_vote_tol_mps does not vote on the rotation
        calm_w = [ok[i] and (resid[i] is None or abs(resid[i]) < cfg.wheel_vote_tol_mps) for i in WHEELS]  # type: ignore
        self._speedometer(x, valid, ok, v_hat, v, moving, usable, pred, tol, resid)
        return v_hat, v, moving, cos_front, usable, calm_w, self._deceleration(v_hat, v)

    def _wheels(self, x, valid, ok, w, u, usable, moving, cos_front, pred, tol, resid) -> None:
        """Each wheel against the median of the others, taken back to it; its radius ratio learned while calm."""
        cfg = self.cfg
        lever = self._lever
        for j, i in enumerate(WHEELS):
            others = [u[k] for k in usable if k != j]
            if not others:
                continue
            ref = median(others)
            ratio = self.wheel_ratio[j]
            back = ref * ratio.value
            if j < 2:
                back /= cos_front
            pred[i] = max(back + lever[j] * w, 0.0)
            if moving and len(others) >= 2 and valid[i]:
                slack = (1.0 / cos_front - 1.0) * ref
                rel = cfg.wheel_tol_rel + cfg.wheel_slip_per_mps2 * abs(self._decel)
                tol[i] = cfg.wheel_tol_mps + rel * ref + slack
                resid[i] = x[i] - pred[i]
                if ok[i] and len(others) == 3 and self.checks[i].resid ** 2 < 0.25 * tol[i] ** 2:
                    ratio.update(ratio.value * u[j] / ref if ref > 0 else 1.0)

    def _speedometer(self, x, valid, ok, v_hat, v, moving, usable, pred, tol, resid) -> None:
        """The speedometer against its learned factor times the wheels' speed, low-passed like the instrument."""
        cfg = self.cfg
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

    def _deceleration(self, v_hat, v) -> float:
        """The speed's drop over the last 10 rows (0 until there are 11)."""
        hist = self._v_hist
        if v_hat is None:
            hist.clear()  # nothing to differentiate: the deceleration restarts when the wheels are back
        else:
            hist.append(v)
        if len(hist) > 11:
            del hist[0]
        decel = (hist[0] - hist[-1]) / (10 * self.dt_s) if len(hist) == 11 else 0.0
        self._decel = decel  # (the wheel check of the next row uses it)
        return decel

    # ---- 2. rotation -------------------------------------------------------------------------------------

    def _rotation(self, x, valid, ok, v_hat, v, moving, cos_front, calm_w, decel, w, pred, tol, resid) -> None:
        """The rotation's estimates, their weighted median ``omega``, the checks of the yaw rate, a_y and steering
        against the others' and the rotation relations learned from the gyro."""
        # braking or accelerating hard, the inner wheels slip more than the outer (load transfer): the wheel
        # pairs do not measure the rotation then
        grip = abs(decel) < self.cfg.wheel_yaw_max_accel_mps2
        est, sd = self._estimates(x, valid, v, grip, calm_w, cos_front)
        self._filter_estimates(est, sd, x, valid, v, w, decel)
        sources_ok = self._sources(est, sd, ok, valid)
        if sources_ok:
            omega = weighted_median([(e, sd[k]) for k, e in sources_ok.items()])[0]
        else:
            omega = 0.0 if v_hat is not None and v < 1.0 else w
        rate = self._yaw_accel(sources_ok, sd, omega)
        self._rotation_checks(x, valid, est, sd, sources_ok, omega, v_hat, v, moving, rate, pred, tol, resid)
        self._omega = omega
        self._learn_rotation(x, valid, ok, v, moving, grip, cos_front, tol, resid)

    def _estimates(self, x, valid, v, grip, calm_w, cos_front):
        """``(est, sd)``: ``omega`` from each source signal (YAW, AY, SW; RL for the rear pair, FL for the front)
        and its uncertainty [rad/s]."""
        cfg = self.cfg
        dt = self.dt_s
        checks = self.checks
        est: dict[int, float] = {}
        sd: dict[int, float] = {}
        env = self._rate_env
        if valid[YAW]:
            est[YAW] = x[YAW] - checks[YAW].offset
            sd[YAW] = 0.3 * _DEG + 0.5 * self.resolution(YAW) + cfg.lag_yaw_s * env
        if v >= 1.0:  # (the checks need `moving`; below it the estimates still feed the substitutes)
            if grip and calm_w[2] and calm_w[3] and self.rear.n * dt >= cfg.warmup_s:
                est[RL] = (x[RR] - x[RL] - self.rear.theta[1] * v) / self.rear.theta[0]
            if grip and calm_w[0] and calm_w[1] and self.front.n * dt >= cfg.warmup_s:
                est[FL] = (x[FR] - x[FL] - self.front.theta[1] * v) / (self.front.theta[0] * cos_front)
            if valid[AY] and self.moving_s >= cfg.warmup_s and v >= 3.0:
                est[AY] = (x[AY] - checks[AY].offset - self.ay_offset.value) / v
                sd[AY] = (0.2 + 0.1 * abs(x[AY]) + 0.5 * self.resolution(AY)) / v + cfg.lead_ay_s * env
            if valid[SW] and self.turning_s >= cfg.warmup_s and v >= 3.0:
                g = self.steer.theta[1] / v + self.steer.theta[2] * v
                if g > 1.0:
                    est[SW] = (x[SW] - checks[SW].offset - self.steer.theta[0]) / g
                    sd[SW] = (1.0 * _DEG + 0.1 * abs(x[SW]) + 0.5 * self.resolution(SW)) / g + cfg.lead_steer_s * env
        return est, sd

    def _filter_estimates(self, est, sd, x, valid, v, w, decel) -> None:
        """The wheel- and steering-based estimates pass a first-order lag like the inertial sensors' filters; the
        wheel pairs' uncertainty grows with the left/right slip (``|a_x a_y| v / track``)."""
        cfg = self.cfg
        env = self._rate_env
        for s_, lp in self._est_lp.items():
            if s_ in est:
                if not self._est_seen[s_]:
                    lp.value = est[s_]
                est[s_] = lp.update(est[s_])
                if s_ in (RL, FL):
                    a_lat = abs(x[AY]) if valid[AY] else abs(v * w)
                    sd[s_] = ((0.005 + 0.0003 * v + cfg.wheel_yaw_slip * abs(decel) * a_lat * v) / 1.56
                              + 0.02 * abs(est[s_]) + cfg.lag_yaw_s * env)
                    self._lsd[s_] = self._learned_sd(self.rear if s_ == RL else self.front, est[s_], v)
            self._est_seen[s_] = s_ in est

    def _learned_sd(self, pair, omega: float, v: float) -> float:
        """What the pair's learned track and radius difference do not know yet, as a rotation [rad/s]: the
        prediction's standard deviation ``sqrt(phi' P phi)`` over the track, ``phi = (omega, v)``. Gentle highway
        curves barely excite the track, and a gyro offset nobody calibrated teaches the radius difference a
        bias. It widens the tolerance of a check whose reference is that pair (not the pair's weight: the
        references and the jump detector see the same estimates as before)."""
        if not self.cfg.learned_sd:
            return 0.0
        P = pair.P
        var = P[0][0] * omega * omega + 2.0 * P[0][1] * omega * v + P[1][1] * v * v
        return math.sqrt(max(var, 0.0)) / max(pair.theta[0], 0.5)

    def _sources(self, est, sd, ok, valid) -> dict[int, float]:
        """The estimates that may predict the others: unflagged ones and the wheel pairs, less a pair that
        disagrees with the other."""
        checks = self.checks
        # (a signal corrected for an offset jump it was flagged for goes on predicting the others, less the offset;
        # its own check stays on the raw value, which must step back)
        sources_ok = {s: e for s, e in est.items() if s in (RL, FL) or ok[s] or (checks[s].offset and valid[s])}
        if RL in sources_ok and FL in sources_ok and \
                abs(sources_ok[RL] - sources_ok[FL]) > 3.0 * (sd[RL] + sd[FL]) + 1.0 * _DEG:
            # the two wheel pairs disagree (a wheel a little off moves its pair's estimate by degrees per second):
            # keep the one closer to the other estimates, or neither
            rest = [e for k, e in sources_ok.items() if k not in (RL, FL)]
            if rest:
                m = median(rest)
                del sources_ok[RL if abs(sources_ok[RL] - m) > abs(sources_ok[FL] - m) else FL]
            else:
                del sources_ok[RL], sources_ok[FL]
        return sources_ok

    def _yaw_accel(self, sources_ok, sd, omega) -> float:
        """Yaw acceleration envelope, peak-held and decaying over the residuals' memory, from the estimates other
        than the gyro (an offset jump of the gyro must not widen its own tolerance)."""
        not_gyro = [(e, sd[k]) for k, e in sources_ok.items() if k != YAW]
        w_ng = weighted_median(not_gyro)[0] if not_gyro else omega
        rate = max(abs(self._omega_rate.update((w_ng - self._w_ng) / self.dt_s)) if self._w_ng_set else 0.0,
                   self._rate_env * self._rate_decay)
        self._w_ng, self._w_ng_set = w_ng, bool(not_gyro)
        self._rate_env = rate
        return rate

    def _rotation_checks(self, x, valid, est, sd, sources_ok, omega, v_hat, v, moving, rate, pred, tol,
                         resid) -> None:
        """The yaw rate, a_y and steering predicted from the *other* estimates (leave-one-out), checked in their
        own unit while moving and at least two others are there."""
        cfg = self.cfg
        for s in (YAW, AY, SW):
            others = [(e, sd[k]) for k, e in sources_ok.items() if k != s]
            w_ref, sd_ref = weighted_median(others) if others else (omega, math.inf)
            ref_key = next((k for k, e in sources_ok.items() if k != s and e == w_ref), None)
            sd_ref += self._lsd.get(ref_key, 0.0) if ref_key in (RL, FL) else 0.0
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
            res = self.resolution(s)
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

    def _learn_rotation(self, x, valid, ok, v, moving, grip, cos_front, tol, resid) -> None:
        """The wheel pairs, the a_y offset and the steering model learned from the gyro, while everything involved
        agrees: the gyro teaches them only while it agrees with them (a fault not yet flagged must not pull them
        along)."""
        cfg = self.cfg
        dt = self.dt_s
        warming = min(self.rear.n, self.front.n) * dt < cfg.warmup_s  # nothing to check the gyro against yet
        gyro_calm = abs(self.checks[YAW].resid) < 0.5 * tol[YAW] if resid[YAW] is not None else warming
        calm = moving and ok[YAW] and gyro_calm and (not valid[AY] or abs(x[AY]) < cfg.ay_check_max_mps2)
        if not calm:
            return
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

    # ---- 3. brake ----------------------------------------------------------------------------------------

    def _brake(self, x, valid, ok, v, moving, usable, decel, pred, tol, resid) -> None:
        """The wheels' deceleration against the pressure's; the idle pressure and the brake gain learned from it."""
        cfg = self.cfg
        idle = self.brake_idle.value
        g_b, coast = self.brake_gain.theta
        if g_b > 0.02 and usable:
            pred[BP] = idle + max(decel - coast, 0.0) / g_b
        if not (valid[BP] and v > 3.0 and len(self._v_hist) == 11):
            return
        if ok[BP]:
            if decel < 0.2 and x[BP] < idle + cfg.brake_min_bar:
                self.brake_idle.update(x[BP])
            if x[BP] > idle + cfg.brake_min_bar:
                self.braking_s += self.dt_s
            self.brake_gain.update([max(x[BP] - idle, 0.0), 1.0], decel, 0.3 ** 2)
        if self.braking_s >= 2.0 and g_b > 0.02 and moving and pred[BP] is not None:
            a_pred = g_b * max(x[BP] - idle, 0.0) + coast
            # in bar; pressure above the prediction (r > 0) gets the tighter tolerance
            r = x[BP] - pred[BP]  # type: ignore[operator]
            low = self.checks[BP].resid < 0.0
            tol[BP] = ((cfg.brake_tol_low_mps2 if low else cfg.brake_tol_mps2)
                       + cfg.brake_tol_rel * abs(a_pred)) / g_b
            resid[BP] = r
