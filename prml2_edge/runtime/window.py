"""Sliding window of the last L rows of o_t, ready for the model without copying.

Rows are written twice into a (2L, 9) buffer (at ``i`` and ``i + L``), so the window is
always the contiguous slice ``buf[i : i + L]``, oldest first: O(1) per step, no allocation,
and a C-contiguous array onnxruntime takes as is.
"""

from __future__ import annotations

import numpy as np

from prml2_edge import schema


class Window:
    """The newest ``length`` rows (9 signals each) and how many of them had invalid signals.

    Parameters
    ----------
    length:
        L, rows per window (``schema.WINDOW_LEN`` = 250, i.e. 5 s at 50 Hz).
    dtype:
        Storage and model-input dtype (float32 for ONNX).
    """

    def __init__(self, length: int = schema.WINDOW_LEN, n_signals: int = schema.NUM_SIGNALS,
                 dtype: type = np.float32) -> None:
        if length < 1:
            raise ValueError(f"window length must be >= 1, got {length}")
        self.length = int(length)
        self._buf = np.zeros((2 * self.length, n_signals), dtype=dtype)
        self._invalid = np.zeros(self.length, dtype=bool)
        self._i = 0  # slot of the oldest row == slot the next row goes to
        self.count = 0  # rows pushed since the last clear
        self.n_invalid = 0  # rows in the window with at least one invalid signal

    def clear(self) -> None:
        """Forget every row (after a discontinuity in the stream)."""
        self._buf[:] = 0.0
        self._invalid[:] = False
        self._i = 0
        self.count = 0
        self.n_invalid = 0

    def step(self, row: np.ndarray, all_valid: bool = True) -> None:
        """Append one row (9,) [SI, canonical order]; ``all_valid`` False when any signal was invalid."""
        i = self._i
        self._buf[i] = row
        self._buf[i + self.length] = row
        self.n_invalid += int(not all_valid) - int(self._invalid[i])
        self._invalid[i] = not all_valid
        self._i = (i + 1) % self.length
        self.count += 1

    @property
    def full(self) -> bool:
        return self.count >= self.length

    @property
    def invalid_fraction(self) -> float:
        """Fraction of the window's rows that had an invalid signal (rows not yet filled count as invalid)."""
        missing = max(self.length - self.count, 0)
        return (self.n_invalid + missing) / self.length

    def view(self) -> np.ndarray:
        """(1, L, 9) view of the window, oldest row first (valid until the next :meth:`step`)."""
        return self._buf[self._i:self._i + self.length][None]
