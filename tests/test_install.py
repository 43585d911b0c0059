"""`pip install '.[plot]'` (README command 1: the edge runtime and matplotlib) in an empty venv: no torch, CLI works.

Slow (builds a wheel and installs the runtime's dependencies into a fresh venv), so it
shares one venv per session with the torch-free demo test in the runtime suite.
"""

from __future__ import annotations

import subprocess
import venv
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="session")
def edge_venv(tmp_path_factory, repo_root) -> Path:
    env_dir = tmp_path_factory.mktemp("edge") / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py = env_dir / "bin" / "python"
    proc = subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "-c", str(repo_root / "constraints.txt"), f"{repo_root}[plot]"],
        capture_output=True, text=True, timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return env_dir


def test_runtime_install_has_no_torch_and_cli_works(edge_venv):
    py = edge_venv / "bin" / "python"
    listed = subprocess.run([str(py), "-m", "pip", "list", "--format=freeze"], capture_output=True, text=True)
    names = {line.split("==")[0].lower() for line in listed.stdout.splitlines()}
    assert "torch" not in names
    assert {"numpy", "onnxruntime", "python-can", "cantools", "tqdm", "matplotlib"} <= names
    proc = subprocess.run([str(edge_venv / "bin" / "prml2"), "--help"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([str(edge_venv / "bin" / "prml2"), "train", "--help"], capture_output=True, text=True)
    assert proc.returncode == 1 and "[train]" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    # the project DBC ships inside the wheel
    code = "from prml2_edge.resources import project_dbc_path; print(project_dbc_path())"
    where = subprocess.run([str(py), "-c", code], capture_output=True, text=True, cwd=edge_venv)
    assert "_data" in where.stdout, where.stdout + where.stderr


def test_demo_runs_without_torch_after_plain_install(edge_venv, tmp_path):
    """Issue 6: `pip install '.[plot]'` then `prml2 demo` (the README's first command) prints the report and plots."""
    env = {"PATH": str(edge_venv / "bin") + ":/usr/bin:/bin", "PRML2_NO_PROGRESS": "1", "HOME": str(tmp_path)}
    proc = subprocess.run([str(edge_venv / "bin" / "prml2"), "demo"], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "balanced: yes" in out and "end_to_end" in out and "paper" in out
    pngs = list(tmp_path.rglob("*.png"))
    assert pngs and pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
