"""The edge runtime: CAN frames in, 50 Hz pose out. NumPy, onnxruntime, python-can and cantools only.

Stages, each a small class with one ``step()`` (``pipeline.py`` wires them):

``source`` (python-can bus or log replay) -> ``decode`` (ID-filtered DBC decoding, integrity
and range checks) -> ``assembler`` (50 Hz grid, zero-order hold, per-signal age/validity)
-> ``localizer`` (``window`` -> ``inference`` ONNX Runtime -> physics guard -> NumPy EKF,
GNSS fusion) -> ``sinks`` (JSON lines, CSV, TUM, CAN). ``latency`` times every stage;
``stats`` accounts for every frame; ``providers`` picks the ONNX Runtime execution providers.

Nothing here imports torch (``tests/runtime/test_runtime_no_torch.py`` checks it), nor the packages
around the runtime (``cli``, ``service``, ``training``, ``evaluation``).
"""
