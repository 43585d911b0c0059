"""Writing a benchmark's result document: one JSON file, the same way for every script in ``benchmarks/``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def _plain(x: Any) -> Any:
    """What ``json`` cannot write by itself, as it can: NumPy scalars and arrays, paths. Anything else is a
    mistake in the document and raises, instead of being written as its repr."""
    if hasattr(x, "tolist"):  # numpy scalar or array
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"a benchmark result holds a {type(x).__name__}, which JSON cannot hold: {x!r}")


def write_json(doc: dict, path: str | Path, indent: int = 1) -> Path:
    """Write ``doc`` to ``path`` (its folder made if missing) as indented JSON ending in a newline; returns the
    path. NaN stays NaN (the docs' tables render it as such)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=indent, default=_plain) + "\n")
    return out
