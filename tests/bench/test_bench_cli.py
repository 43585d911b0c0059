"""``prml2 bench --json``: runs torch-free on a tiny setting and prints the documented keys (not timing values)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("onnx")  # the test model is built with onnx.helper

from runtime_models import make_kinematic_model  # noqa: E402

REPO = Path(__file__).resolve().parents[2]

# torch blocked: the edge benchmark must not need it
_RUN = ("import sys; sys.modules['torch'] = None; from prml2_edge.cli.main import main; "
        "sys.exit(main(sys.argv[1:]))")


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _RUN, "bench", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_bench_json_has_documented_keys(tmp_path):
    model = make_kinematic_model(tmp_path / "kinematic.onnx")
    res = _bench("--json", "--model", str(model), "--threads", "1", "--precision", "fp32,int8", "--seconds", "7",
                 "--warmup-steps", "5", "--no-gemm")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)  # one JSON object, nothing else on stdout
    assert {"configs", "machine", "gemm", "paper_orin_infer_ms", "notes"} <= set(doc)
    names = [c["name"] for c in doc["configs"]]
    assert names == ["kinematic-test-fp32-1t", "kinematic-test-int8-1t"]
    for c in doc["configs"]:
        for key in ("e2e_ms", "model_ms", "overhead_ms"):
            assert {"p50", "p95", "p99", "max"} <= set(c[key])
            assert all(isinstance(c[key][q], float) for q in ("p50", "p95", "p99", "max"))
        assert c["steps"] > 0 and c["threads"] == 1
    for key in ("cpu_model", "cores_usable", "flags", "numpy", "onnxruntime", "load_average"):
        assert key in doc["machine"]
    assert doc["machine"]["torch"] is None


def test_bench_table_and_bad_arguments(tmp_path):
    model = make_kinematic_model(tmp_path / "kinematic.onnx")
    res = _bench("--model", str(model), "--threads", "1", "--precision", "fp32", "--seconds", "6",
                 "--warmup-steps", "5")
    assert res.returncode == 0, res.stderr
    assert "kinematic-test-fp32-1t" in res.stdout and "e2e p50" in res.stdout and "GEMM" in res.stdout
    short = _bench("--model", str(model), "--seconds", "2")
    assert short.returncode == 1 and "too short" in short.stderr
    bad = _bench("--model", str(model), "--chunk-s", "0")
    assert bad.returncode == 1 and "--chunk-s > 0" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_bench_measures_the_export_variants_side_by_side_with_their_accuracy(tmp_path):
    model = make_kinematic_model(tmp_path / "kinematic.onnx")
    res = _bench("--json", "--model", str(model), "--threads", "1", "--precision", "fp32,int8-static,fp32-opt",
                 "--seconds", "7", "--warmup-steps", "5", "--no-gemm", "--accuracy-windows", "6",
                 "--calibration-windows", "8")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    names = [c["name"] for c in doc["configs"]]
    assert names == ["kinematic-test-fp32-1t", "kinematic-test-int8-static-1t"]
    fp32, static = doc["configs"]
    assert fp32["accuracy"] is None
    assert static["accuracy"]["n_windows"] == 6 and len(static["accuracy"]["relative_change"]) == 5
    assert fp32["load_average"] == static["load_average"]  # one interleaved measurement, not two runs
    # the optimiser needs a transformer's metadata (heads, width): this closed-form graph is skipped, with a note
    assert any("fp32-opt" in n and "skipped" in n for n in doc["notes"])
