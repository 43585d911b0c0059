"""benchmarks/offset_learning.py on one car's drives cut short: the filter's offset estimate read at the marks the
drive reaches, per drive and per car, and wrong input refused in one line."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from offset_learning import main  # noqa: E402


def test_the_offset_estimate_is_read_at_the_marks_each_drive_reaches(tmp_path, capsys):
    out = tmp_path / "ol.json"
    assert main(["--cars", "city_fwd", "--minutes", "1.2", "--workers", "1", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert {d["car"] for d in doc["drives"]} == {"city_fwd"} and len(doc["drives"]) == 2
    for d in doc["drives"]:
        assert set(d["learned_dps"]) == {"0.5", "1"}  # 1.2 min reaches the 0.5 and 1 minute marks only
        assert all(math.isfinite(v) and abs(v) < 2.0 for v in d["learned_dps"].values())
        assert any(v != 0.0 for v in d["learned_dps"].values())  # the estimate moved off its prior of 0
    share = doc["by_car"]["city_fwd"]["1"]
    assert share == pytest.approx(sum(d["learned_dps"]["1"] for d in doc["drives"]) / 2 / 0.4)
    assert doc["by_car"]["all"] == doc["by_car"]["city_fwd"]
    printed = capsys.readouterr().out
    assert "| city_fwd |" in printed and "| drives that reach it | 2 | 2 | 0 | 0 | 0 |" in printed


@pytest.mark.parametrize("argv, message", [(["--offset-dps", "0"], "nothing to learn"),
                                           (["--cars", "nosuchcar"], "its fleet is"),
                                           (["--model", "nosuch.onnx"], "no model file")])
def test_wrong_input_is_refused_in_one_line(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and message in capsys.readouterr().err
