"""Writing a benchmark's result document: one JSON file, the same way for every script in ``benchmarks/``."""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
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


def announce(name: str) -> dict:
    """The machine's description (:func:`~prml2_edge.bench.machine.machine_info`), after saying on stderr which CPU
    and flags run benchmark ``name``: numbers from different machines are not comparable."""
    from prml2_edge.bench.machine import machine_info

    machine = machine_info()
    print(f"[{name}] {machine['cpu_model']}, flags {' '.join(machine['flags'])}", file=sys.stderr)
    return machine


def finish(doc: dict, path: str | Path, markdown: Callable[[dict], list[str]], t0: float) -> Path:
    """End a benchmark: ``doc["wall_s"]`` from ``t0`` (``time.monotonic()`` at its start), ``doc`` written to
    ``path``, its ``markdown(doc)`` printed and where it went; returns the path."""
    doc["wall_s"] = round(time.monotonic() - t0, 1)
    out = write_json(doc, path)
    print("\n".join(markdown(doc)))
    print(f"wrote {out} ({doc['wall_s']:.0f} s)")
    return out
