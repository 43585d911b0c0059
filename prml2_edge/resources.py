"""Locate files that ship with the project (DBC, signal maps, default model).

In an installed wheel they live under ``prml2_edge/_data`` (hatchling force-include);
in a source checkout or editable install they are read from the repository root.
"""

from __future__ import annotations

from pathlib import Path

from prml2_edge.errors import Prml2Error

_PACKAGE_DIR = Path(__file__).resolve().parent
_INSTALLED_DATA = _PACKAGE_DIR / "_data"
_REPO_ROOT = _PACKAGE_DIR.parent


def resource_path(*parts: str) -> Path:
    """Path of a shipped file, e.g. ``resource_path("dbc", "prml2_onboard.dbc")``."""
    for base in (_INSTALLED_DATA, _REPO_ROOT):
        candidate = base.joinpath(*parts)
        if candidate.exists():
            return candidate
    raise Prml2Error(f"shipped file {'/'.join(parts)} not found; reinstall prml2-edge (pip install .)")


def project_dbc_path() -> Path:
    """The project's own vehicle DBC, ``dbc/prml2_onboard.dbc``."""
    return resource_path("dbc", "prml2_onboard.dbc")
