"""The CAN yaw rate's resolution, measured from the steps between its distinct readings (issue 26).

A quantised signal's every step is a multiple of its resolution, so until enough steps are seen the smallest one
bounds it (``from_steps``; else the configured resolution stands); every :data:`RESOLUTION_WINDOW` steps the 10th
percentile of the window is the measured resolution (a fine gyro's noise makes small steps, a coarse one's steps
are its step). A gyro at least ``coarse_threshold`` coarse is *coarse*: the filter lets the model carry its rate
between steps (runtime/filter.py). With ``coarse_until_fine`` it counts as coarse from the start while its
configured resolution and every step it has taken are that coarse (a fine gyro shows a small step within a few
samples; a coarse one on mild roads may take a minute to show 200).

One rule, two users: the runtime's filter feeds it reading by reading (:meth:`YawResolution.reading`); a replay of
rows the filter did not see (the drive so far in the benchmark, a unit's history) feeds it a whole column
(:meth:`YawResolution.of`) and gets the same number.
"""

from __future__ import annotations

import collections
from collections.abc import Iterable

import numpy as np

RESOLUTION_WINDOW = 200  # steps between distinct readings per measurement


class YawResolution:
    """The resolution [rad/s] as measured so far (:attr:`radps`), whether it is measured and whether the gyro is
    coarse."""

    def __init__(self, configured_radps: float, coarse_threshold_radps: float, from_steps: bool = True,
                 coarse_until_fine: bool = True) -> None:
        self.radps = float(configured_radps)
        self.coarse_threshold = float(coarse_threshold_radps)
        self.from_steps = bool(from_steps)
        self.measured = False
        self.coarse = bool(coarse_until_fine) and self.radps >= self.coarse_threshold
        self._last: float | None = None
        self._steps: collections.deque[float] = collections.deque(maxlen=RESOLUTION_WINDOW)

    @classmethod
    def from_config(cls, config) -> YawResolution:
        """As a :class:`~prml2_edge.runtime.localizer_config.LocalizerConfig` sets it up."""
        return cls(config.yaw_cue_resolution_radps, config.coarse_yaw_resolution_radps,
                   config.resolution_from_steps, config.coarse_until_fine_step)

    @classmethod
    def of(cls, yaw: np.ndarray, config) -> float:
        """The resolution [rad/s] the runtime would have measured after the readings ``yaw`` (NaN: missing,
        skipped) under ``config``'s rules."""
        res = cls.from_config(config)
        res.readings(np.asarray(yaw, dtype=np.float64))
        return res.radps

    def readings(self, yaw: Iterable[float]) -> None:
        for value in yaw:
            if value == value:  # not NaN
                self.reading(float(value))

    def reading(self, yaw: float) -> bool:
        """One reading [rad/s]; True when the resolution changed."""
        last, self._last = self._last, yaw
        if last is None or yaw == last:
            return False
        step = abs(yaw - last)
        self._steps.append(step)
        changed = False
        if not self.measured:
            if self.from_steps and step < self.radps:
                self.radps, changed = step, True
            if step < self.coarse_threshold:
                self.coarse = False  # a fine step: not coarse until measured otherwise
        if len(self._steps) == RESOLUTION_WINDOW:
            self.radps = float(np.percentile(self._steps, 10))
            self.measured, changed = True, True
            self.coarse = self.radps >= self.coarse_threshold
            self._steps.clear()
        return changed
