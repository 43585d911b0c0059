"""TUM trajectory files (``timestamp x y z qx qy qz qw``) for the ``evo`` tools.

Planar poses: z = 0, the quaternion a rotation by ``psi`` (ccw from east) about the up axis;
each row is :func:`prml2_edge.tum.tum_line`, the runtime's ``TumSink`` format.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prml2_edge.tum import tum_line


def write_tum(path: str | Path, t_s: np.ndarray, pose: np.ndarray) -> Path:
    """Write ``pose`` (N, 3) [x east m, y north m, psi rad] at ``t_s`` (N,) [s] as a TUM file; returns the path.

    Rows with a non-finite pose are left out (evo cannot read NaN).
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    pose = np.asarray(pose, dtype=np.float64)
    if pose.ndim != 2 or pose.shape[1] != 3 or len(t_s) != len(pose):
        raise ValueError(f"want t_s (N,) and pose (N, 3), got {t_s.shape} and {pose.shape}")
    ok = np.isfinite(pose).all(axis=1) & np.isfinite(t_s)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as f:
        for t, (x, y, psi) in zip(t_s[ok].tolist(), pose[ok].tolist(), strict=True):
            f.write(tum_line(t, x, y, psi))
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a planar TUM file back: ``t_s`` (N,) [s], ``pose`` (N, 3) [m, m, rad]."""
    table = np.atleast_2d(np.loadtxt(path))
    psi = 2.0 * np.arctan2(table[:, 6], table[:, 7])
    return table[:, 0], np.column_stack([table[:, 1], table[:, 2], psi])
