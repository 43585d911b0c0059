"""Dependency-free plotting for the edge runtime (NumPy + zlib only): see :mod:`prml2_edge.viz.png`."""
