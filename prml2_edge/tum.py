"""One TUM trajectory row (``timestamp x y z qx qy qz qw``), shared by the runtime's TumSink and evaluation.

Planar poses: z = 0, the quaternion a rotation by ``psi`` (counter-clockwise from east) about
the up axis. Timestamps carry 6 decimals (microseconds), positions 4, the quaternion 8.
"""

from __future__ import annotations

import math


def tum_line(t_s: float, x_m: float, y_m: float, psi_rad: float) -> str:
    """The TUM line (with its newline) of a planar pose: x east, y north [m], ``psi_rad`` ccw from east."""
    half = 0.5 * psi_rad
    return f"{t_s:.6f} {x_m:.4f} {y_m:.4f} 0.0 0.0 0.0 {math.sin(half):.8f} {math.cos(half):.8f}\n"
