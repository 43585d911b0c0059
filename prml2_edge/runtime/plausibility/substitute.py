"""Substitution: a signal taken out is replaced by what the others predict for it, so the model keeps its window.

A flagged signal, and a stale one (its message stopped, :attr:`~.PlausibilityConfig.substitute_stale`) or one whose
message is under attack, is invalid for the filter (no standstill check from it); its value in the row is replaced by
the relations' prediction (wheel: median of the others, radius ratio and lever arm; speedometer: factor times the
wheels; yaw rate: the weighted median of the other rotation estimates; a_y: ``v omega``; steering: the single-track
model; brake pressure: from the wheels' deceleration), or, after an offset jump, by the value less the measured
offset. ``AssembledRow.substituted`` marks those values and ``substitute_std`` gives their uncertainty: the filter
keeps a substituted yaw rate as its cue, with it added. Nothing is replaced while more than
:attr:`~.PlausibilityConfig.max_substituted` signals are out (with most of the bus gone there is nothing to predict
from), nor a signal never received (a map mistake, which the runtime reports).
"""

from __future__ import annotations

import math

from .config import YAW, N, PlausibilityConfig


class Substitution:
    """What replaces the signals taken out, and how often each was replaced."""

    def __init__(self, cfg: PlausibilityConfig, absent: list[bool]) -> None:
        self.cfg = cfg
        self.absent = absent  # signals the car lacks: never replaced
        self.std_of = {YAW: cfg.substitute_yaw_std_radps}  # uncertainty of the others' prediction as a substitute
        self.seen = [False] * N  # a valid value has arrived (the stage sets it)
        self.rows = [0] * N  # rows each signal was replaced in

    def apply(self, x: list[float], new_valid: list[bool], raw_valid, pred: list[float | None], checks: list,
              untrusted: dict[int, str]) -> tuple[list[bool], list[float]]:
        """Replace, in ``x``, the signals ``new_valid`` takes out; ``raw_valid``: the row's validity as it came.
        ``(substituted, std)`` per signal (std nan where not known or not replaced)."""
        cfg = self.cfg
        seen = self.seen
        subst = [False] * N
        std = [math.nan] * N
        out = [i for i in range(N) if not new_valid[i] and not self.absent[i]]
        if not 0 < len(out) <= cfg.max_substituted:
            return subst, std
        for i in out:
            c = checks[i]
            if not seen[i]:
                continue
            if c.flagged and c.offset and raw_valid[i] and i not in untrusted:
                x[i] -= c.offset  # an offset jump: the value less it
                std[i] = c.offset_std
            elif (c.flagged or i in untrusted or cfg.substitute_stale) and pred[i] is not None:
                x[i] = pred[i]
                std[i] = self.std_of.get(i, math.nan)
            else:
                continue
            subst[i] = True
            self.rows[i] += 1
        return subst, std
