"""Real, small ONNX models for runtime tests (built with onnx.helper; onnx is a test/train dependency only).

:func:`make_kinematic_model` writes a physically meaningful closed-form PRML2 model: over the
decoder steps (the last L - H rows of the window) it predicts ``v_x`` = mean of the four wheel
speeds, ``a_y`` = lateral acceleration, ``omega_z`` = yaw rate, ``v_y = a_x = 0``, with constant
variances. It is a linear map ``z = o @ W`` in the graph (Slice + MatMul + Add), carries valid
PRML2 metadata, and so exercises every runtime stage for real, without training.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from prml2_edge import schema
from prml2_edge.model_meta import INPUT_NAME, METADATA_KEY, ModelMetadata

# one-sigma of the kinematic model's outputs: v_x, v_y, a_x, a_y, omega_z
KINEMATIC_STD = (0.1, 0.05, 0.5, 0.3, 0.01)


def kinematic_weights() -> np.ndarray:
    """W (9, 5) with z = o @ W: v_x = mean wheel speed, a_y = lateral accel, omega_z = yaw rate."""
    w = np.zeros((schema.NUM_SIGNALS, schema.NUM_STATES), dtype=np.float32)
    for name in schema.WHEEL_SPEED_NAMES:
        w[schema.SIGNAL_BY_NAME[name].index, schema.Z.V_X] = 0.25
    w[schema.SIGNAL_BY_NAME["lat_accel_mps2"].index, schema.Z.A_Y] = 1.0
    w[schema.SIGNAL_BY_NAME["yaw_rate_radps"].index, schema.Z.OMEGA_Z] = 1.0
    return w


def make_kinematic_model(path: str | Path, weights: np.ndarray | None = None, std=KINEMATIC_STD,
                         bias: np.ndarray | None = None, var_scale_on_input: float = 0.0,
                         meta_overrides: dict | None = None, L: int = schema.WINDOW_LEN,
                         H: int = schema.ENCODER_LEN, batch: int | str = 1) -> Path:
    """Write the closed-form model to ``path`` and return it.

    ``var_scale_on_input`` multiplies the variance by ``(1 + s * o[:, :, 0])`` (s < 0 lets a test
    drive the variance non-positive on purpose); ``meta_overrides`` replaces metadata fields
    (to build mismatching models); ``bias`` (5,) is added to the mean (NaN makes a broken model); ``batch`` is the
    graph's batch dimension (a name such as ``"batch"`` leaves it free).
    """
    path = Path(path)
    w = kinematic_weights() if weights is None else np.asarray(weights, dtype=np.float32)
    b = np.zeros(schema.NUM_STATES, dtype=np.float32) if bias is None else np.asarray(bias, dtype=np.float32)
    var = np.square(np.asarray(std, dtype=np.float32)).reshape(1, 1, schema.NUM_STATES)
    inits = [
        numpy_helper.from_array(np.array([H], dtype=np.int64), "starts"),
        numpy_helper.from_array(np.array([L], dtype=np.int64), "ends"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), "axes"),
        numpy_helper.from_array(w, "W"),
        numpy_helper.from_array(b, "b"),
        numpy_helper.from_array(np.zeros((schema.NUM_SIGNALS, schema.NUM_STATES), dtype=np.float32), "W0"),
        numpy_helper.from_array(var, "var"),
        numpy_helper.from_array(np.array([0], dtype=np.int64), "c_start"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), "c_end"),
        numpy_helper.from_array(np.array([2], dtype=np.int64), "c_axis"),
        numpy_helper.from_array(np.array(var_scale_on_input, dtype=np.float32), "s"),
        numpy_helper.from_array(np.array(1.0, dtype=np.float32), "one"),
    ]
    nodes = [
        helper.make_node("Slice", [INPUT_NAME, "starts", "ends", "axes"], ["dec"]),  # (1, L-H, 9)
        helper.make_node("MatMul", ["dec", "W"], ["lin"]),  # (1, L-H, 5)
        helper.make_node("Add", ["lin", "b"], ["z_mean"]),
        helper.make_node("MatMul", ["dec", "W0"], ["zeros"]),
        helper.make_node("Slice", ["dec", "c_start", "c_end", "c_axis"], ["o0"]),  # (1, L-H, 1) speedometer
        helper.make_node("Mul", ["o0", "s"], ["so0"]),
        helper.make_node("Add", ["so0", "one"], ["factor"]),
        helper.make_node("Add", ["zeros", "var"], ["var_b"]),
        helper.make_node("Mul", ["var_b", "factor"], ["z_var"]),
    ]
    graph = helper.make_graph(
        nodes, "prml2_kinematic",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, [batch, L, schema.NUM_SIGNALS])],
        [helper.make_tensor_value_info("z_mean", TensorProto.FLOAT, [batch, L - H, schema.NUM_STATES]),
         helper.make_tensor_value_info("z_var", TensorProto.FLOAT, [batch, L - H, schema.NUM_STATES])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="prml2-tests")
    model.ir_version = 8
    meta = ModelMetadata(version="test", preset="kinematic-test", norm_mean=[0.0] * schema.NUM_SIGNALS,
                         norm_std=[1.0] * schema.NUM_SIGNALS, dataset_fingerprint="none", L=L, H=H)
    text = meta.to_json()
    if meta_overrides:
        import json

        data = json.loads(text)
        data.update(meta_overrides)
        text = json.dumps(data)
    helper.set_model_props(model, {METADATA_KEY: text})
    onnx.checker.check_model(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


class ListSink:
    """A pipeline sink that keeps every StepOutput (tests)."""

    def __init__(self) -> None:
        self.outs = []

    def step(self, out) -> None:
        self.outs.append(out)

    def close(self) -> None:
        pass
