"""The car sliding: when the lateral acceleration and the yaw rate disagree, the odometry is not to be trusted.

Over ground, the lateral velocity in the car's frame changes at ``dv_y/dt = a_y - v_x * omega_z``. While the
tyres grip, ``v_y`` stays small and the two sides match to the sensors' error (on the benchmark's drives and the
real ReV-StED sample the 0.1 s mean of ``|a_y - v_x omega_z|`` never passes 1.5 m/s^2, with offsets, roll and
noise). In a skid or a spin they part by tens of m/s^2 (a car sliding sideways at 24 m/s on snow: 30 m/s^2), and
neither the model (trained on gripping tyres) nor the wheels (locked or spinning) measure the motion.
:class:`SlideMonitor` turns that residual into a bound on the position the filter did not see: the unmodelled
lateral speed ``dv`` is the residual integrated over the slide, and the position's standard deviation grows by
``dv * dt`` per step until the tyres grip again. So the GNSS fixes that follow pass the innovation gate and pull
the pose back, and the GNSS check (:mod:`~prml2_edge.runtime.gnss_check`), which trusts the odometry over its
baseline, starts its baseline again after the slide instead of taking genuine fixes for a spoof.
"""

from __future__ import annotations

import math


class SlideMonitor:
    """``|a_y - v_x omega_z|`` against ``threshold_mps2`` (module docstring); :meth:`step` once per filter step."""

    TAU_S = 0.1  # the residual's low-pass time constant: one noisy sample is not a slide
    GRIP_S = 0.5  # below the threshold this long: gripping again, the unmodelled speed is forgotten

    def __init__(self, threshold_mps2: float | None, dt_s: float) -> None:
        self.threshold = math.inf if threshold_mps2 is None else float(threshold_mps2)
        self.dt_s = float(dt_s)
        self._alpha = min(1.0, self.dt_s / self.TAU_S)
        self.episodes = 0
        self.reset()

    def reset(self) -> None:
        self.started = False  # the last step began a slide
        self.residual = 0.0  # low-passed |a_y - v_x omega_z| [m/s^2]
        self.sliding = False
        self.dv = 0.0  # lateral speed the filter has not seen in this slide [m/s]
        self._grip_s = 0.0

    def step(self, a_y: float | None, v_x: float, omega_z: float | None) -> float:
        """One step: the growth of the position's standard deviation per axis [m] (0 while gripping). A missing
        signal (None) holds the residual. A new slide is counted in :attr:`episodes` and :attr:`started`."""
        self.started = False
        if a_y is not None and omega_z is not None:
            self.residual += self._alpha * (abs(a_y - v_x * omega_z) - self.residual)
        if self.residual > self.threshold:
            if not self.sliding:
                self.sliding, self.started = True, True
                self.episodes += 1
            self._grip_s = 0.0
            self.dv += self.residual * self.dt_s
        elif self.sliding:
            self._grip_s += self.dt_s
            if self._grip_s >= self.GRIP_S:
                self.sliding, self.dv = False, 0.0
        return self.dv * self.dt_s if self.sliding else 0.0
