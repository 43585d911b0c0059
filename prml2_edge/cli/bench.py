"""``prml2 bench``: measure per-step latency of the runtime on this machine."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Measure per-step latency of the runtime on this machine."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 7."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 bench' is not available in this version yet (issue 7)")
