"""The residual check of one signal (step 4 of the stage): what it remembers, how a flag clears, why it was raised.

A residual is smoothed (EMA, :attr:`~.PlausibilityConfig.smooth_s`, :attr:`~.PlausibilityConfig.smooth_rot_s` for the
rotation); above its tolerance for :attr:`~.PlausibilityConfig.confirm_s` the signal is *flagged*, with a reason
(offset, scale, dropout to zero, stuck); below half the tolerance for :attr:`~.PlausibilityConfig.clear_s` (and its
value moving) it is cleared. **Stuck**: the value has not changed for :attr:`~.PlausibilityConfig.stuck_hold_s` (at
least 5 of its periods) while what the others predict for it moved by more than a few resolution steps plus part of
its tolerance. A **dropout** (exactly 0 where the others say far more) is flagged at once. A signal corrected for an
offset jump (:mod:`.jumps`) stays flagged until the jump steps back, or until the value less the offset disagrees with
the others too, when the others' prediction takes over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .config import SIGNAL_UNITS, VS, WHEELS, PlausibilityConfig


@dataclass
class Check:
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

    def restart(self) -> None:
        """After a gap in the stream: the residual and the stuck check start again (flag and resolution stay)."""
        self.resid = self.over_s = 0.0
        self.changed_t = -math.inf
        self.pred_lo, self.pred_hi = math.inf, -math.inf

    def while_flagged(self, r: float, tol: float, alpha: float, dt: float, t: float, hold_s: float,
                      cfg: PlausibilityConfig) -> None:
        """One row of a flagged signal (residual ``r``, already smoothed into :attr:`resid`): the offset correction
        checked, the flag cleared after :attr:`~.PlausibilityConfig.clear_s` of agreement."""
        if self.offset:
            # the corrected value must agree with the others, or the correction was wrong (a drift, a scale)
            self.offset_resid += alpha * (r - self.offset - self.offset_resid)
            worse = abs(self.offset_resid) > tol and abs(self.offset_resid) > abs(self.resid)
            self.offset_over_s = self.offset_over_s + dt if worse else 0.0
            if self.offset_over_s >= cfg.jump_drop_s:
                self.offset = 0.0
                self.reason += "; the value less it disagrees too: the others' prediction replaces it"
        # (an offset jump measured at its step ends with the step back, or when the value less it disagrees)
        if abs(self.resid) < 0.5 * tol and t - self.changed_t < hold_s and not self.offset:
            self.under_s += dt
            if self.under_s >= cfg.clear_s:
                self.flagged = False
                self.over_s = 0.0
                self.offset = 0.0
                self.reason = ""
        else:
            self.under_s = 0.0


def reason(i: int, x: float, p: float | None, c: Check, stuck: bool, t: float) -> str:
    """Why signal ``i`` (reading ``x`` where the others predict ``p``) is flagged, in its own unit."""
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
