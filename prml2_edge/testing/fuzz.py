"""Fuzzed CAN frames for the reliability tests and the fuzz benchmark (``benchmarks/fuzz.py``).

:func:`fuzz_stream` repeats a genuine log (time moving on with every pass) and turns each frame into
one of three: the genuine frame (55 %), a mutated one (25 %: flipped bits, a changed length, a hostile
timestamp) or a hostile random frame (20 %, :func:`prml2_edge.testing.faults.random_frame`). This
module only builds test input; the runtime never imports it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import can
import numpy as np

from prml2_edge.testing.faults import random_frame

KNOWN_IDS = [0xA0, 0xA1, 0xC2, 0x130, 0x140, 0x158, 0x610]  # the project DBC's input messages


def mutate(rng: np.random.Generator, msg: can.Message, t_s: float) -> can.Message:
    """A genuine frame with flipped bits, a changed length or a hostile timestamp."""
    data = bytearray(msg.data)
    r = rng.random()
    if r < 0.5 and data:
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(0, len(data)))
            data[i] ^= 1 << int(rng.integers(0, 8))
    elif r < 0.7:
        data = data[: int(rng.integers(0, 9))] if rng.random() < 0.5 else data + bytes(int(rng.integers(1, 57)))
    elif r < 0.8:
        t_s = float(rng.choice([math.nan, math.inf, -math.inf, -1e9, 1e12, 0.0, t_s - 3.0, t_s + 7.0, t_s - 0.3,
                                t_s + 0.1]))
    fd = len(data) > 8
    return can.Message(timestamp=t_s, arbitration_id=msg.arbitration_id, is_extended_id=False, data=bytes(data),
                       is_fd=fd)


def fuzz_stream(frames: Sequence[can.Message], n: int, seed: int = 2024,
                known_ids: Sequence[int] = KNOWN_IDS) -> Iterator[can.Message]:
    """``n`` frames: ``frames`` again and again (each pass ``span + 1`` s later), genuine, mutated or random."""
    rng = np.random.default_rng(seed)
    span = float(frames[-1].timestamp - frames[0].timestamp) + 1.0
    kinds = rng.random(n)
    ids = list(known_ids)
    for k in range(n):
        msg = frames[k % len(frames)]
        t_s = msg.timestamp + span * (k // len(frames))
        kind = kinds[k]
        if kind < 0.55:
            yield can.Message(timestamp=t_s, arbitration_id=msg.arbitration_id, is_extended_id=False, data=msg.data)
        elif kind < 0.8:
            yield mutate(rng, msg, t_s)
        else:
            yield random_frame(rng, t_s, ids)
