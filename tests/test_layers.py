"""The package's layering: no module imports from a layer above its own (read from the source, not by running it)."""

from __future__ import annotations

import ast
from pathlib import Path

import prml2_edge

ROOT = Path(prml2_edge.__file__).parent
# lower layers first; a module may import its own layer and the ones before it
LAYERS = [
    {"schema", "errors", "resources", "progress", "tum", "dead_reckoning", "model_meta", "config"},
    {"can", "ekf", "guard", "viz", "data"},
    {"runtime", "bench"},
    {"service", "evaluation", "testing", "fleet"},
    {"training"},
    {"cli"},
]


def _layer(top: str) -> int:
    return next(i for i, names in enumerate(LAYERS) if top in names)


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("prml2_edge."):
            out.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[1] for a in node.names if a.name.startswith("prml2_edge."))
    return out


def test_no_module_imports_a_higher_layer():
    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        top = rel.parts[0].removesuffix(".py")
        if top == "__init__":
            continue
        for target in _imports(path):
            if _layer(target) > _layer(top):
                bad.append(f"{rel} imports prml2_edge.{target}")
    assert not bad, bad


def test_the_runtime_imports_no_cli_service_training_or_evaluation():
    for path in sorted((ROOT / "runtime").glob("*.py")):
        assert not _imports(path) & {"cli", "service", "training", "evaluation", "testing"}, path
