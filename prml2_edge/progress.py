"""A dependency-free progress bar for long work (simulation, training, replay, evaluation).

Writes to stderr; redraws in place on a terminal and prints a line every ~10 % when
stderr is not a TTY (CI logs, pipes). ``PRML2_NO_PROGRESS=1`` silences it.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO


class Progress:
    """Progress over ``total`` units: ``update(n)``, ``set_postfix(text)``, ``close()``."""

    def __init__(self, total: int | None, desc: str = "", unit: str = "it", stream: TextIO | None = None,
                 enabled: bool | None = None) -> None:
        self.total = total
        self.desc = desc
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = (os.environ.get("PRML2_NO_PROGRESS") != "1") if enabled is None else enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.n = 0
        self.postfix = ""
        self._t0 = time.monotonic()
        self._last_draw = 0.0
        self._last_decile = -1
        self._closed = False

    def update(self, n: int = 1) -> None:
        self.n += n
        self._maybe_draw()

    def set_postfix(self, text: str) -> None:
        self.postfix = text
        self._maybe_draw()

    def _line(self) -> str:
        elapsed = time.monotonic() - self._t0
        rate = self.n / elapsed if elapsed > 0 else 0.0
        if self.total:
            frac = min(1.0, self.n / self.total)
            bar = "#" * int(frac * 24)
            eta = (self.total - self.n) / rate if rate > 0 else 0.0
            core = f"{self.desc} [{bar:<24}] {self.n}/{self.total} {self.unit} {rate:.1f}/s eta {eta:.0f}s"
        else:
            core = f"{self.desc} {self.n} {self.unit} {rate:.1f}/s"
        return f"{core} {self.postfix}".rstrip()

    def _maybe_draw(self, force: bool = False) -> None:
        if not self.enabled or self._closed:
            return
        now = time.monotonic()
        if self.tty:
            if force or now - self._last_draw > 0.1:
                self.stream.write("\r" + self._line()[:160].ljust(80))
                self.stream.flush()
                self._last_draw = now
        else:
            decile = int(10 * self.n / self.total) if self.total else int(now - self._t0) // 10
            if force or decile > self._last_decile:
                self._last_decile = decile
                self.stream.write(self._line() + "\n")
                self.stream.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._maybe_draw(force=True)
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()
        self._closed = True

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
