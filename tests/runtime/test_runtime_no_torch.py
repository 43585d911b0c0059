"""The edge runtime never imports torch: every runtime module imports, and the demo runs, with torch blocked."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

from runtime_models import make_kinematic_model

import prml2_edge.runtime
import prml2_edge.viz

BLOCK = "import sys; sys.modules['torch'] = None; sys.modules['onnx'] = None; sys.modules['matplotlib'] = None\n"


def runtime_modules() -> list[str]:
    names = ["prml2_edge.ekf", "prml2_edge.ekf.numpy_ekf", "prml2_edge.guard", "prml2_edge.can.signal_map",
             "prml2_edge.can.encode", "prml2_edge.data.simulate", "prml2_edge.cli.main", "prml2_edge.cli.replay",
             "prml2_edge.cli.run_live", "prml2_edge.cli.demo"]
    for pkg in (prml2_edge.runtime, prml2_edge.viz):
        names += [f"{pkg.__name__}.{m.name}" for m in pkgutil.iter_modules(pkg.__path__)]
    return names


def test_every_runtime_module_imports_without_torch():
    names = runtime_modules()
    assert "prml2_edge.runtime.pipeline" in names and "prml2_edge.viz.plots" in names
    code = BLOCK + "import importlib\n" + "".join(f"importlib.import_module({n!r})\n" for n in names) + \
        "assert sys.modules['torch'] is None\nprint('ok')\n"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


def test_demo_runs_without_torch_onnx_or_matplotlib_and_says_how_to_get_the_plot(tmp_path):
    model = make_kinematic_model(tmp_path / "m.onnx")  # built here, with onnx; the child cannot import it
    code = BLOCK + ("from prml2_edge.cli.main import main\n"
                    f"rc = main(['demo', '--seconds', '12', '--gnss-seconds', '5', '--model', {str(model)!r}, "
                    f"'--out', {str(tmp_path / 'demo')!r}])\n"
                    "assert sys.modules['torch'] is None\nsys.exit(rc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={"PRML2_NO_PROGRESS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "pose track vs ground truth" in proc.stdout and not (tmp_path / "demo" / "trajectory.png").exists()
    # without matplotlib the demo does everything else and says in one line how to get the plot
    hint = [line for line in proc.stdout.splitlines() if "matplotlib" in line]
    assert len(hint) == 1 and "trajectory.png" in hint[0] and "'.[plot]'" in hint[0], proc.stdout
