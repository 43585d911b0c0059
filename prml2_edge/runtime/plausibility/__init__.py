"""Online plausibility: the nine onboard signals checked against each other while driving.

A car's CAN bus carries the same motion several times over: four wheel speeds and the speedometer describe the
speed; the yaw rate, the difference of the left and right wheels of each axle, the lateral acceleration over the
speed (``a_y / v``) and the steering wheel angle through the single-track model
(``delta_sw = ratio * (L / v + K v) * omega``) describe the rotation; the brake pressure is a deceleration the wheels
must show. :class:`Plausibility` runs between the assembler and the localiser and, every 50 Hz row:

1. **speed** — each wheel, corrected to the car's centre for the yaw rate and scaled by its learned rolling-radius
   ratio, against the median of the other wheels; the speedometer against its learned factor times the wheels' speed;
2. **rotation** — up to five estimates of ``omega`` (gyro, rear pair, front pair, ``a_y / v``, steering); the yaw
   rate, ``a_y`` and the steering are each checked, in their own unit, against the *other* estimates (leave-one-out:
   one faulty signal cannot hide itself);
3. **brake** — the wheels' deceleration against the one the brake pressure predicts;
4. **stuck** — every signal whose value has not changed for :attr:`PlausibilityConfig.stuck_hold_s` (at least 5 of
   its periods) while what the others predict for it moved by more than a few of its resolution steps plus part of
   its tolerance (``stuck_res_steps``, ``stuck_span_tol``);
5. **offset jumps** (yaw rate, a_y, steering): a step within one row of the signal's first difference that the
   residual follows while the others go on as before is an offset jump, flagged when confirmed (0.4-0.9 s) even
   inside the residual tolerance; its size is measured from the values around the step and the substitute is the
   signal less it (reported in ``AssembledRow.offset_jumps``, from which the pipeline takes back the heading the jump
   cost before it was found). A confirmed step back ends the correction.

A residual is smoothed; above its tolerance for :attr:`~PlausibilityConfig.confirm_s` the signal is *flagged*, with a
reason (offset, scale, dropout to zero, stuck); below half the tolerance for :attr:`~PlausibilityConfig.clear_s` it
is cleared. The relations' unknowns are learned online (recursive least squares with forgetting) from unflagged
signals only. A flagged signal, and a stale one, is taken out: invalid for the filter and, in the row, replaced by
what the others predict for it, so the model keeps its full window (``AssembledRow.substituted``, ``substitute_std``);
the pose is ``DEGRADED`` and the status line names the signal and the reason. Checks run above
:attr:`~PlausibilityConfig.min_speed_mps`; below it (parking, ABS sensors blind) flags hold.

Modules: :mod:`.config` (signal indices, :class:`PlausibilityConfig`), :mod:`.models` (RLS, EMA, medians),
:mod:`.relations` (steps 1-3: predictions, tolerances, learning), :mod:`.checks` (step 4: one signal's residual
check and its reasons), :mod:`.jumps` (step 5), :mod:`.substitute` (what replaces a signal taken out) and
:mod:`.stage` (:class:`Plausibility`, the row loop).
"""

from .config import AY, BP, FL, FR, RL, RR, SIGNAL_UNITS, SW, VS, WHEELS, YAW, N, PlausibilityConfig
from .stage import Plausibility

__all__ = ["AY", "BP", "FL", "FR", "N", "RL", "RR", "SIGNAL_UNITS", "SW", "VS", "WHEELS", "YAW", "Plausibility",
           "PlausibilityConfig"]
