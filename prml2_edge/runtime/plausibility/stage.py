"""The plausibility stage itself: one 50 Hz row in, the row with the signals that lie taken out and replaced, out.

Per row, :meth:`Plausibility.check` runs the relations (steps 1-3, :mod:`.relations`), then for every signal its
residual check (step 4, :mod:`.checks`: smoothing, stuck, dropout, flag, clear) and, for the yaw rate, a_y and
steering, the offset-jump detector (step 5, :mod:`.jumps`), and last the substitution (:mod:`.substitute`). Checks
run above :attr:`~.PlausibilityConfig.min_speed_mps`; below it (parking, ABS sensors blind) flags hold.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from prml2_edge import schema
from prml2_edge.runtime.rows import AssembledRow

from .checks import Check, reason
from .config import AY, BP, COARSEST_STEP, SW, VS, YAW, N, PlausibilityConfig
from .jumps import JumpDetector, take_offset
from .relations import Relations
from .substitute import Substitution


class Plausibility:
    """Cross-checks of the onboard signals, one 50 Hz row per :meth:`check` (package docstring).

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
        """Everything starts again: learned relations, flags, counts."""
        cfg = self.config
        dt = self.dt_s
        self._alpha = [dt / (cfg.smooth_rot_s if i in (YAW, AY, SW) else cfg.smooth_s) for i in range(N)]
        self.checks = [Check() for _ in range(N)]
        self.jumps = {i: JumpDetector(i, cfg, dt) for i in (YAW, AY, SW)}
        self.relations = Relations(cfg, dt, self.checks)
        self.substitution = Substitution(cfg, self.absent)
        self.flag_episodes = [0] * N
        self.flag_rows = [0] * N
        self.first_flag: list[tuple[float, str] | None] = [None] * N
        self.untrusted: dict[int, str] = {}  # signals taken out because their message is under attack
        self.offsets_found: list[tuple[int, float, float, float]] = []

    def _restart(self) -> None:
        """After a gap in the stream: the transient state starts again (learned relations and flags stay)."""
        self.relations.restart()
        for c in self.checks:
            c.restart()
        for j in self.jumps.values():
            j.restart()

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
        self.offsets_found = []
        pred, newly = self._step(x, valid, row.t_s)
        new_valid = list(valid)
        seen = self.substitution.seen
        absent = self.absent
        for i, c in enumerate(self.checks):
            if valid[i]:
                seen[i] = True
            if c.flagged and not absent[i]:
                new_valid[i] = False
                self.flag_rows[i] += 1
        subst, std = self.substitution.apply(x, new_valid, row.valid, pred, self.checks, self.untrusted)
        if not any(subst) and not newly and not self.offsets_found and new_valid == row.valid.tolist():
            return row
        return replace(row, values=np.asarray(x), valid=np.asarray(new_valid, dtype=bool),
                       substituted=np.asarray(subst, dtype=bool), newly_flagged=tuple(newly),
                       substitute_std=np.asarray(std) if any(subst) else None,
                       offset_jumps=tuple(self.offsets_found))

    def _step(self, x: list[float], valid: list[bool], t: float) -> tuple[list[float | None], list[int]]:
        """Steps 1-5 on one row: ``(every signal's prediction, the signals flagged at this row)``."""
        ok = [v_ and not c.flagged for v_, c in zip(valid, self.checks, strict=True)]
        pred, tol, resid, moving, v, w = self.relations.predict(x, valid, ok)
        return pred, self._flags(x, valid, t, pred, tol, resid, moving, v, w)

    def _flags(self, x, valid, t, pred, tol, resid, moving, v, w) -> list[int]:
        """Step 4 (with step 5 on the raw residuals): residuals smoothed, stuck and dropout tested, flags raised."""
        cfg = self.config
        dt = self.dt_s
        absent, checks, jumps, alpha, hold_s = self.absent, self.checks, self.jumps, self._alpha, self.stuck_hold_s
        newly: list[int] = []
        for i in range(N):
            if absent[i] or not valid[i]:
                continue
            c = checks[i]
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
            if i in jumps:
                # (the single-track relation the steering is checked by holds only at low lateral acceleration)
                linear = i != SW or abs(x[AY] if valid[AY] else v * w) < cfg.jump_steer_max_ay_mps2
                self._jump(i, xi, r, moving and linear, t, c, pred[i], newly)
            if r is None:
                continue
            c.resid += alpha[i] * (r - c.resid)
            ti = tol[i]
            # stuck: the value has not changed while the *smoothed* prediction (the held value less the smoothed
            # residual) moved by more than a few resolution steps; a healthy sensor of that resolution would have
            # changed (the raw prediction's noise alone must not trip it on a coarse sensor)
            c.pred_lo = min(c.pred_lo, -c.resid)
            c.pred_hi = max(c.pred_hi, -c.resid)
            if c.flagged:
                c.while_flagged(r, ti, alpha[i], dt, t, hold_s[i], cfg)
                continue
            c.over_s = c.over_s + dt if abs(c.resid) > ti else 0.0
            stuck = (t - c.changed_t >= hold_s[i] and abs(c.resid) > 0.5 * ti
                     and c.pred_hi - c.pred_lo > cfg.stuck_res_steps * min(c.resolution, COARSEST_STEP[i])
                     + cfg.stuck_span_tol * self._tol_abs[i]
                     and (i != BP or xi > self.relations.brake_idle.value + cfg.brake_min_bar))  # idle: nobody brakes
            # a dropout (exactly 0 where the others say far more) is flagged at once: every row it stays in
            # the window and the filter costs heading
            dropout = xi == 0.0 and abs(r) > cfg.dropout_tol * ti
            if c.over_s >= cfg.confirm_s or stuck or dropout:
                c.reason = reason(i, xi, pred[i], c, stuck, t)
                self._flag(i, c, t, newly)
        return newly

    def _jump(self, i: int, xi: float, r: float | None, moving: bool, t: float, c: Check, p: float | None,
              newly: list[int]) -> None:
        """Step 5 for signal ``i``: its jump detector's row; a confirmed offset jump corrects and flags it."""
        res = min(c.resolution, COARSEST_STEP[i])
        found = self.jumps[i].row(xi, r, p, moving, t, res)
        if found is None:
            return
        report = take_offset(c, i, found, res, self.config.jump_match, xi, p)
        if report is None:
            return
        self.offsets_found.append(report)
        if not c.flagged:
            self._flag(i, c, t, newly)

    def _flag(self, i: int, c: Check, t: float, newly: list[int]) -> None:
        """Signal ``i`` flagged at ``t`` (its reason already set)."""
        c.flagged = True
        c.under_s = 0.0
        newly.append(i)
        self.flag_episodes[i] += 1
        if self.first_flag[i] is None:
            self.first_flag[i] = (t, c.reason)

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
        """Flags now and so far, rows flagged and substituted, the learned relations and the driving time."""
        names = schema.SIGNAL_NAMES
        rel = self.relations
        return {
            "enabled": self.config.enabled,
            "flagged_now": self.reasons(),
            "flag_episodes": {names[i]: n for i, n in enumerate(self.flag_episodes) if n},
            "flagged_rows": {names[i]: n for i, n in enumerate(self.flag_rows) if n},
            "substituted_rows": {names[i]: n for i, n in enumerate(self.substitution.rows) if n},
            "first_flag": {names[i]: {"t_s": f[0], "reason": f[1]} for i, f in enumerate(self.first_flag) if f},
            "learned": {"rear_track_m": rel.rear.theta[0], "rear_radius_diff": rel.rear.theta[1],
                        "front_track_m": rel.front.theta[0], "front_radius_diff": rel.front.theta[1],
                        "lat_accel_offset_mps2": rel.ay_offset.value, "speedometer_factor": rel.speedo_factor.value,
                        "steering_gain": rel.steer.theta[1], "steering_understeer": rel.steer.theta[2],
                        "wheel_ratio": [e.value for e in rel.wheel_ratio],
                        "brake_gain_mps2_per_bar": rel.brake_gain.theta[0]},
            "driving_s": rel.moving_s,
        }
