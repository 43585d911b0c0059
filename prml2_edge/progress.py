"""Progress bars for long work (simulation, training, replay, evaluation), drawn by tqdm on stderr.

On a terminal tqdm redraws its bar in place. When the stream is not a terminal (a log file, a
pipe, CI) it prints a plain line (tqdm's own meter text, no carriage return) at most every
:data:`LINE_INTERVAL_S` seconds, and a last one when the work ends. ``PRML2_NO_PROGRESS=1``
silences both.
"""

from __future__ import annotations

import os
import sys
from typing import TextIO

from tqdm import tqdm

LINE_INTERVAL_S = 30.0  # without a terminal: one line at most this often


class _LineBar(tqdm):
    """tqdm that writes one line per refresh instead of redrawing with ``\\r`` (for logs)."""

    monitor_interval = 0  # no monitor thread: refreshes happen on update() only

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        # close() with leave=False asks to clear the bar (msg ""): print the final meter instead
        self.fp.write((str(self) if not msg else msg) + "\n")
        self.fp.flush()
        return False  # nothing to clear with "\r"


class Progress:
    """Progress over ``total`` units (None: unknown): ``update(n)``, ``set_postfix(text)``, ``close()``.

    ``enabled`` None means "unless ``PRML2_NO_PROGRESS=1``"; ``stream`` defaults to stderr.
    """

    def __init__(self, total: int | None, desc: str = "", unit: str = "it", stream: TextIO | None = None,
                 enabled: bool | None = None) -> None:
        self.stream = stream or sys.stderr
        self.enabled = (os.environ.get("PRML2_NO_PROGRESS") != "1") if enabled is None else bool(enabled)
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        common = {"total": total or None, "desc": desc, "unit": unit, "file": self.stream, "disable": not self.enabled,
                  "dynamic_ncols": self.tty}
        if self.tty:
            self._bar: tqdm = tqdm(**common)
        else:
            self._bar = _LineBar(**common, mininterval=LINE_INTERVAL_S, maxinterval=1e9, leave=False, ascii=True)

    @property
    def n(self) -> int:
        return int(self._bar.n)

    @property
    def total(self) -> int | None:
        return self._bar.total

    def update(self, n: int = 1) -> None:
        self._bar.update(n)

    def set_postfix(self, text: str) -> None:
        self._bar.set_postfix_str(text, refresh=False)

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
