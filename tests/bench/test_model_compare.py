"""benchmarks/model_compare.py end to end on a small simulated recipe: a model against itself differs by nothing,
window by window, and a missing model file is refused in one line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from model_compare import main  # noqa: E402

from prml2_edge.data.datasets import generate_dataset  # noqa: E402
from prml2_edge.runtime.inference import default_model_path  # noqa: E402


def test_a_model_against_itself_is_paired_to_zero(tmp_path, capsys):
    data = generate_dataset(tmp_path / "data", "small", workers=1, progress=False)
    model = str(default_model_path())
    out = tmp_path / "cmp.json"
    assert main(["--data", str(data), "--a", model, "--b", model, "--splits", "val", "--protocols", "paper",
                 "--max-windows", "1", "--jobs", "1", "--history-min", "0", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    row = doc["rows"]["val / paper"]
    assert row["windows"] >= 1 and row["a"]["rmse_mean_m"] > 0
    assert row["b_minus_a"]["rmse_diff_mean_m"] == 0.0 and row["a"] == row["b"]
    assert all(c["a_rmse_m"] == c["b_rmse_m"] for c in row["per_car"].values())
    assert "| val / paper |" in capsys.readouterr().out


def test_a_missing_model_file_is_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--data", str(tmp_path), "--b", str(tmp_path / "nosuch.onnx")])
    assert e.value.code == 2
    assert "no model file" in capsys.readouterr().err
