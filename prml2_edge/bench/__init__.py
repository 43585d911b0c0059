"""Latency benchmark of the edge runtime (torch-free; used by ``prml2 bench`` and ``benchmarks/``).

* :mod:`~prml2_edge.bench.machine`: what machine this is (CPU model, cores, SIMD flags, library
  versions, load average) and its measured fp32 matrix-multiply rate (NumPy GEMM);
* :mod:`~prml2_edge.bench.flops`: analytic FLOPs of one PRML2 inference from the model config;
* :mod:`~prml2_edge.bench.replay_input`: a seeded simulated drive encoded to CAN frames;
* :mod:`~prml2_edge.bench.latency`: end-to-end latency per 50 Hz step of the real :class:`Pipeline`.

The int8 variants it measures come from :mod:`prml2_edge.training.quantize` (beside the export).
"""
