"""OnnxModel: a real onnxruntime session on a real ONNX graph; mismatching models refused at start-up."""

from __future__ import annotations

import numpy as np
import pytest
from runtime_models import kinematic_weights, make_kinematic_model

from prml2_edge import schema
from prml2_edge.errors import ModelError
from prml2_edge.runtime.inference import OnnxModel, default_model_path
from prml2_edge.runtime.status import InferenceStatus


def test_kinematic_model_runs_and_matches_numpy(tmp_path, rng):
    model = OnnxModel(make_kinematic_model(tmp_path / "m.onnx"), threads=1)
    assert model.window_len == schema.WINDOW_LEN and model.decoder_len == schema.DECODER_LEN
    window = rng.uniform(0, 20, (1, schema.WINDOW_LEN, schema.NUM_SIGNALS)).astype(np.float32)
    assert model.step(window) is InferenceStatus.SUCCESS
    want = window[0, schema.ENCODER_LEN:] @ kinematic_weights()
    np.testing.assert_allclose(model.mean, want, rtol=1e-5, atol=1e-5)
    assert (model.var > 0).all()
    assert "CPUExecutionProvider" in model.providers


@pytest.mark.parametrize(("overrides", "match"), [
    ({"signal_names": list(reversed(schema.SIGNAL_NAMES))}, "signal order differs"),
    ({"schema_hash": "0123456789abcdef"}, "schema hash"),
    ({"format": "something-else"}, "not a PRML2 model"),
    ({"guard_in_graph": True}, "guard is inside"),
])
def test_mismatching_metadata_is_refused_saying_what_differs(tmp_path, overrides, match):
    path = make_kinematic_model(tmp_path / "bad.onnx", meta_overrides=overrides)
    with pytest.raises(ModelError, match=match):
        OnnxModel(path)


def test_graph_shape_differing_from_metadata_is_refused(tmp_path):
    path = make_kinematic_model(tmp_path / "short.onnx", L=200, H=100, meta_overrides={"L": 250, "H": 150})
    with pytest.raises(ModelError, match="shape"):
        OnnxModel(path)


def test_missing_or_corrupt_model_is_one_line_error(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        OnnxModel(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file")
    with pytest.raises(ModelError, match="cannot load"):
        OnnxModel(bad)


def test_non_finite_or_non_positive_outputs_are_reported_not_raised(tmp_path):
    window = np.ones((1, schema.WINDOW_LEN, schema.NUM_SIGNALS), dtype=np.float32)
    nan_model = OnnxModel(make_kinematic_model(tmp_path / "nan.onnx", bias=[np.nan, 0, 0, 0, 0]))
    assert nan_model.step(window) is InferenceStatus.INVALID_OUTPUT
    neg_var = OnnxModel(make_kinematic_model(tmp_path / "neg.onnx", var_scale_on_input=-2.0))
    assert neg_var.step(window) is InferenceStatus.INVALID_OUTPUT  # var * (1 - 2 * 1) < 0
    assert neg_var.step(window[:, :10]) is InferenceStatus.ERROR  # wrong input shape: onnxruntime raised
    assert neg_var.n_errors == 1 and neg_var.last_error


def test_default_model_path_names_the_shipped_file():
    try:
        path = default_model_path()
    except ModelError as exc:
        assert "export/default/prml2_edge.onnx" in str(exc)
    else:
        assert path.name == "prml2_edge.onnx" and path.is_file()


def test_two_threads_asked_for_run_on_the_faster_count_and_fixed_threads_keeps_two():
    """``threads`` >= 2 is an upper bound: both counts are timed at start and the session kept is the faster one's
    (the shipped edge model's operators are short; which wins depends on the machine, the rule does not)."""
    picked = OnnxModel(default_model_path(), threads=2)
    timing = picked.thread_timing_ms
    assert set(timing) == {1, 2} and all(t > 0 for t in timing.values())
    assert picked.threads == min(timing, key=timing.get) and picked.threads_requested == 2
    assert picked.session.get_session_options().intra_op_num_threads == picked.threads
    window = np.zeros((1, picked.window_len, schema.NUM_SIGNALS), dtype=np.float32)
    window[0] = picked.metadata.norm_mean
    assert picked.step(window) is InferenceStatus.SUCCESS
    fixed = OnnxModel(default_model_path(), threads=2, fixed_threads=True)
    assert fixed.threads == 2 and fixed.thread_timing_ms is None
    assert fixed.session.get_session_options().intra_op_num_threads == 2
    one = OnnxModel(default_model_path(), threads=1)
    assert one.threads == 1 and one.thread_timing_ms is None
