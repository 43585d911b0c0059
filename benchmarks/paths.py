"""Where the benchmarks find and put things (torch-free), and models prepared in a child process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results"
SHIPPED_EDGE = REPO / "export" / "default" / "prml2_edge.onnx"
MODEL_DIR = REPO / "out" / "bench" / "models"
DATASET = REPO / "data" / "bench"


def prepared_paths(name: str, seed: int = 0, checkpoint: str | None = None) -> dict:
    """``{"fp32", "fp32_all", "int8", "source", "trained"}`` of benchmark model ``name`` (``bench_models.prepare``),
    run in a child process so that the caller stays torch-free (its imports and RSS are then the edge runtime's)."""
    script = HERE / "bench_models.py"
    cmd = [sys.executable, str(script), name, str(seed)] + ([str(checkpoint)] if checkpoint else [])
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])
