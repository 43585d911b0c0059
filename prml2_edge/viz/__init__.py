"""Plotting: every figure through :mod:`prml2_edge.viz.plots` (matplotlib, the ``plot`` extra)."""
