"""benchmarks/offset_observability.py: the gyro's offset separated from the other cues' speed-shaped errors."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from offset_observability import CUES, joint_offset, main  # noqa: E402


def _cues(v: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Each cue's error as its source makes it: a lateral offset / v, a radius difference x v, a steering offset x v."""
    noise = lambda: rng.normal(scale=math.radians(0.05), size=v.shape)  # noqa: E731
    return {"a_y / v": -0.12 / v + noise(), "rear wheels": 0.004 * v / 1.5 + noise(),
            "steering": 0.0015 * v + noise()}


def test_an_offset_is_separable_when_the_speed_varies_and_not_when_it_holds() -> None:
    rng = np.random.default_rng(1)
    b = math.radians(0.4)
    v = np.linspace(8.0, 25.0, 3000)  # a minute of speeding up
    cues = _cues(v, rng)
    assert set(cues) == set(CUES)
    gyro = b + rng.normal(scale=math.radians(0.06), size=v.shape)
    est = joint_offset(v, cues, gyro)
    assert est is not None and abs(math.degrees(est - b)) < 0.05
    # each cue alone says something else: its own error is as large as the offset
    assert all(abs(math.degrees(np.mean(gyro - c) - b)) > 0.2 for c in cues.values())
    held = np.full(250, 15.0)  # 5 s at one speed: the constant and the speed terms are the same column
    assert joint_offset(held, _cues(held, rng), b + np.zeros(250)) is None


def test_a_car_the_recipe_does_not_have_is_refused_in_one_line(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--cars", "nosuchcar", "--json", "unused.json"])
    assert e.value.code == 2 and "no test drive of --cars 'nosuchcar'" in capsys.readouterr().err
