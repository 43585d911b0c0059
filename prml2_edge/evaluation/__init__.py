"""Evaluation with the paper's protocol (Sec. V; method.md "Evaluation protocol"), torch-free.

Every model runs through :meth:`prml2_edge.runtime.localizer.StreamingLocalizer.run_arrays`,
the streaming path of the live runtime: :mod:`.models` (the OSD baseline and ablation
wrappers as runtime models), :mod:`.protocol` (segments, 60 s windows, tuning on val),
:mod:`.metrics`, :mod:`.report`, :mod:`.tum`, :mod:`.osd` (the OSD baseline); the figures are drawn by
:mod:`prml2_edge.viz.plots`.
"""
