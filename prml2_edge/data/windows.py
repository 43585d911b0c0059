"""Sliding windows over drives (L = 250 samples, encoder H = 150), stored once, addressed by index.

Windows never cross a drive boundary. The data of all drives is concatenated once;
a window is its start index, so millions of windows cost 8 bytes each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.data.revsted import Drive


@dataclass
class WindowSet:
    """Sliding windows of length ``L`` over concatenated drives.

    Attributes
    ----------
    onboard : ndarray (T_total, 9) float32
        o_t, canonical order, SI (not normalised).
    z : ndarray (T_total, 5) float32
        Ground truth z_t; NaN for drives without ground truth.
    pose : ndarray (T_total, 3) float64
        [x east m, y north m, psi rad]; NaN for drives without ground truth.
    starts : ndarray (n,) int64
        Start index of each window in the concatenated arrays.
    drive_index : ndarray (n,) int64
        Which drive (position in the list given to :func:`build_windows`) each window is from.
    L, H : int
        Window and encoder length [samples].
    """

    onboard: np.ndarray
    z: np.ndarray
    pose: np.ndarray
    starts: np.ndarray
    L: int
    H: int
    drive_index: np.ndarray | None = None
    bounds: np.ndarray | None = None  # (n_drives, 2) [first, end) of each drive in the concatenated arrays

    def __len__(self) -> int:
        return len(self.starts)

    def get(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Windows ``idx`` as arrays (b, L, 9) float32, (b, L, 5) float32, (b, L, 3) float64."""
        rows = self.starts[np.asarray(idx, dtype=np.int64)][:, None] + np.arange(self.L)[None, :]  # (b, L)
        return self.onboard[rows], self.z[rows], self.pose[rows]

    def segment_starts(self, length: int, stride: int) -> np.ndarray:
        """First samples (global indices) of the ``length``-sample segments every ``stride`` samples that lie
        inside one drive with L - 1 samples of history before them (so every sample has its window)."""
        if self.bounds is None:
            raise ValueError("this window set has no drive bounds")
        out = [np.arange(a + self.L - 1, b - length + 1, stride, dtype=np.int64) for a, b in self.bounds]
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def get_segments(self, starts: np.ndarray, length: int, rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Streaming windows over segments, for training through the EKF across windows.

        Segment ``k`` covers samples ``[s_k, s_k + length)``; it is served by the ``length / rows`` windows
        that end at ``s_k + rows - 1, s_k + 2 rows - 1, ...``, whose newest ``rows`` decoder steps tile the
        segment. Returns onboard (b * length / rows, L, 9) float32 (segment-major, in time order), z
        (b, length, 5) float32 and pose (b, length, 3) float64 of the segment samples.
        """
        if length % rows:
            raise ValueError(f"segment length {length} is not a multiple of rows {rows}")
        starts = np.asarray(starts, dtype=np.int64)
        ends = starts[:, None] + rows * np.arange(length // rows)[None, :] + rows - 1  # (b, length / rows)
        win = (ends.reshape(-1) - self.L + 1)[:, None] + np.arange(self.L)[None, :]
        seg = starts[:, None] + np.arange(length)[None, :]  # (b, length)
        return self.onboard[win], self.z[seg], self.pose[seg]


def build_windows(drives: list[Drive], L: int = schema.WINDOW_LEN, H: int = schema.ENCODER_LEN,
                  stride: int = 10) -> WindowSet:
    """All windows ``[s, s + L)`` with ``s = 0, stride, 2 stride, ...`` inside each drive.

    A drive shorter than ``L`` contributes no window (but its data is kept so indices stay simple).
    """
    if not (0 < H < L):
        raise ValueError(f"need 0 < H < L, got H={H}, L={L}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    onboard, z, pose, starts, which, bounds = [], [], [], [], [], []
    offset = 0
    for k, d in enumerate(drives):
        n = len(d)
        onboard.append(d.onboard.astype(np.float32))
        z.append(d.z_gt.astype(np.float32) if d.z_gt is not None else np.full((n, schema.NUM_STATES), np.nan,
                                                                                np.float32))
        pose.append(d.pose_gt.astype(np.float64) if d.pose_gt is not None else np.full((n, 3), np.nan))
        s = np.arange(0, n - L + 1, stride, dtype=np.int64) + offset
        starts.append(s)
        which.append(np.full(len(s), k, dtype=np.int64))
        bounds.append((offset, offset + n))
        offset += n
    if not drives:
        return WindowSet(np.zeros((0, schema.NUM_SIGNALS), np.float32), np.zeros((0, schema.NUM_STATES), np.float32),
                         np.zeros((0, 3)), np.zeros(0, np.int64), L, H, np.zeros(0, np.int64))
    return WindowSet(
        onboard=np.concatenate(onboard), z=np.concatenate(z), pose=np.concatenate(pose),
        starts=np.concatenate(starts), L=L, H=H, drive_index=np.concatenate(which),
        bounds=np.asarray(bounds, dtype=np.int64).reshape(-1, 2),
    )
