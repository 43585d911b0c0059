"""``prml2 demo``: replay a built-in simulated drive through the runtime and report pose and latency."""

from __future__ import annotations

import argparse

from prml2_edge.errors import Prml2Error

HELP = "Replay a built-in simulated drive through the runtime and report pose and latency."
NEEDS: tuple[tuple[str, str], ...] = ()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options yet: filled in by issue 6."""


def run(args: argparse.Namespace) -> int:
    raise Prml2Error("'prml2 demo' is not available in this version yet (issue 6)")
