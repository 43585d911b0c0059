"""ONNX export: fixed shape, embedded metadata, onnxruntime parity with torch, int8, the CLI."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from prml2_edge import schema  # noqa: E402
from prml2_edge.cli.main import main  # noqa: E402
from prml2_edge.model_meta import INPUT_NAME, METADATA_KEY, OUTPUT_NAMES, ModelMetadata  # noqa: E402
from prml2_edge.training.checkpoint import make_checkpoint, save_checkpoint  # noqa: E402
from prml2_edge.training.export_onnx import (  # noqa: E402
    compare_int8,
    export_onnx,
    metadata_for,
    parity,
    quantize_int8,
    read_metadata,
)
from prml2_edge.training.model import Prml2Model  # noqa: E402
from prml2_edge.training.presets import get_preset  # noqa: E402

torch.set_num_threads(1)
PRESET = get_preset("tiny")
NORM_MEAN = np.array([12.0, 0.1, 0.0, 0.0, 4.0, 12.0, 12.0, 12.0, 12.0])
NORM_STD = np.array([7.0, 1.5, 0.2, 1.8, 8.0, 7.0, 7.0, 7.0, 7.0])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny model with non-trivial weights and its checkpoint file."""
    torch.manual_seed(3)
    model = Prml2Model(PRESET.model, NORM_MEAN, NORM_STD, [12.0, 0.0, 0.0, 0.0, 0.0], [7.0, 0.2, 1.2, 1.8, 0.2])
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    ckpt = make_checkpoint(model.eval(), "tiny", PRESET.train, "fp-test", epoch=2, stage="finetune")
    path = save_checkpoint(ckpt, tmp_path_factory.mktemp("ckpt") / "best.pt")
    return model, ckpt, path


def _windows(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (NORM_MEAN + NORM_STD * rng.normal(size=(n, schema.WINDOW_LEN, schema.NUM_SIGNALS))).astype(np.float32)


def test_graph_has_fixed_shape_metadata_and_matches_torch(trained, tmp_path):
    model, ckpt, _ = trained
    path = export_onnx(model, metadata_for(model, ckpt), tmp_path / "m.onnx")
    proto = onnx.load(str(path))
    assert max(op.version for op in proto.opset_import if op.domain in ("", "ai.onnx")) >= 17
    dims = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim] for v in (*proto.graph.input,
                                                                                 *proto.graph.output)}
    assert dims == {INPUT_NAME: [1, 250, 9], OUTPUT_NAMES[0]: [1, 100, 5], OUTPUT_NAMES[1]: [1, 100, 5]}
    meta = read_metadata(path)
    meta.check_schema()
    assert meta.preset == "tiny" and meta.dataset_fingerprint == "fp-test" and not meta.guard_in_graph
    np.testing.assert_allclose(meta.norm_mean, NORM_MEAN, rtol=1e-6)
    assert np.asarray(meta.ekf_process_noise).shape == (8, 8)
    assert meta.training["finetune"] is True and meta.config["d_model"] == PRESET.model.d_model
    assert [p.key for p in proto.metadata_props].count(METADATA_KEY) == 1
    diff = parity(model, path, _windows(100))
    assert diff["n"] == 100
    assert diff["mean"] <= 1e-4 and diff["var"] <= 1e-4, diff


def test_graph_excludes_the_guard(trained, tmp_path):
    """A window that makes the model predict beyond the limits comes out unguarded."""
    model, ckpt, _ = trained
    with torch.no_grad():
        big = Prml2Model(PRESET.model, NORM_MEAN, NORM_STD, [40.0, 0, 0, 0, 3.0], [1.0, 1, 1, 1, 1])
        big.load_state_dict({k: v for k, v in model.state_dict().items() if k != "z_mean"}, strict=False)
    path = export_onnx(big, metadata_for(big, ckpt), tmp_path / "big.onnx")
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    mean, var = sess.run(list(OUTPUT_NAMES), {INPUT_NAME: _windows(1)})
    assert mean.shape == (1, 100, 5) and np.all(var > 0)
    assert np.abs(mean[..., 0]).max() > schema.V_MAX_MPS and np.abs(mean[..., 4]).max() > schema.OMEGA_MAX_RADPS


def test_int8_keeps_metadata_and_reports_accuracy(trained, tmp_path):
    model, ckpt, _ = trained
    fp32 = export_onnx(model, metadata_for(model, ckpt), tmp_path / "m.onnx")
    q = quantize_int8(fp32, tmp_path / "m8.onnx")
    assert read_metadata(q).training["int8"] is True
    w = _windows(8, seed=1)
    with torch.no_grad():
        z = model(torch.as_tensor(w))[0].numpy() + 0.1  # a stand-in truth
    report = compare_int8(fp32, q, w, z)
    assert set(report["fp32"]) == set(schema.STATE_NAMES) and report["n_windows"] == 8
    assert 0 < report["max_abs_mean_diff"] < 5.0


def test_cli_export_prints_parity(trained, tmp_path, capsys):
    _, _, ckpt_path = trained
    out = tmp_path / "cli.onnx"
    assert main(["export", "--checkpoint", str(ckpt_path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "parity torch vs onnxruntime on 100 windows" in text
    ModelMetadata.from_json(onnx.load(str(out)).metadata_props[0].value).check_schema()


def test_cli_export_user_errors_are_one_line(trained, tmp_path, capsys):
    _, _, ckpt_path = trained
    assert main(["export", "--checkpoint", str(ckpt_path), "--out", str(tmp_path / "x.onnx"), "--int8"]) == 1
    assert "--int8 needs --data" in capsys.readouterr().err
    assert main(["export", "--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path / "x.onnx")]) == 1
    err = capsys.readouterr().err
    assert "not found" in err and len(err.strip().splitlines()) == 1


def test_newest_rows_forward_equals_the_full_forward(trained):
    model, _, _ = trained
    x = torch.as_tensor(_windows(3, seed=2))
    with torch.no_grad():
        mean, var = model(x)
        for rows in (1, 7, 100):
            m, v = model(x, rows=rows)
            assert m.shape == (3, rows, 5)
            torch.testing.assert_close(m, mean[:, -rows:], rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(v, var[:, -rows:], rtol=1e-5, atol=1e-6)
    from prml2_edge.errors import ModelError

    with pytest.raises(ModelError, match="rows must be in"):
        model(x, rows=0)


def test_streaming_export_returns_the_newest_row_with_its_metadata(trained, tmp_path):
    from prml2_edge.runtime.inference import OnnxModel

    model, ckpt, _ = trained
    full = export_onnx(model, metadata_for(model, ckpt), tmp_path / "full.onnx")
    one = export_onnx(model, metadata_for(model, ckpt), tmp_path / "one.onnx", rows=1)
    proto = onnx.load(str(one))
    dims = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim] for v in proto.graph.output}
    assert dims == {OUTPUT_NAMES[0]: [1, 1, 5], OUTPUT_NAMES[1]: [1, 1, 5]}
    assert read_metadata(one).output_rows == 1 and read_metadata(full).output_rows is None
    assert read_metadata(full).rows == 100
    diff = parity(model, one, _windows(100))
    assert diff["mean"] <= 1e-4 and diff["var"] <= 1e-4, diff
    w = _windows(1, seed=4)
    a, b = OnnxModel(full), OnnxModel(one)
    assert a.step(w).name == b.step(w).name == "SUCCESS"
    assert b.mean.shape == (1, 5) and a.mean.shape == (100, 5)
    np.testing.assert_allclose(b.mean[-1], a.mean[-1], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(b.var[-1], a.var[-1], rtol=1e-5, atol=1e-7)
    # the int8 recipe keeps head/skip/input projection in float also under the wrapper's "/model/" names
    q = quantize_int8(one, tmp_path / "one8.onnx")
    assert read_metadata(q).output_rows == 1
    names = {n.name for n in onnx.load(str(q)).graph.node if n.op_type == "MatMul"}
    assert any("/head/" in n for n in names) and any("/skip/" in n for n in names)


def test_metadata_with_impossible_output_rows_is_refused(trained, tmp_path):
    from dataclasses import replace

    from prml2_edge.errors import ModelError

    model, ckpt, _ = trained
    meta = replace(metadata_for(model, ckpt), output_rows=101)
    with pytest.raises(ModelError, match="output_rows=101"):
        meta.check_schema()


def test_reexport_from_onnx_recovers_every_weight(trained, tmp_path, capsys):
    from prml2_edge.training.export_onnx import model_from_onnx

    model, ckpt, _ = trained
    full = export_onnx(model, metadata_for(model, ckpt), tmp_path / "full.onnx")
    one = export_onnx(model, metadata_for(model, ckpt), tmp_path / "one.onnx", rows=1)
    for graph in (full, one):  # the streaming graph holds the model under the wrapper's "model." names
        twin, _, info = model_from_onnx(graph)
        assert info["weights_loaded"] == info["weights_total"]
        for (name, a), (_, b) in zip(model.state_dict().items(), twin.state_dict().items(), strict=True):
            torch.testing.assert_close(a, b, msg=name)
    out = tmp_path / "stream.onnx"
    assert main(["export", "--checkpoint", str(full), "--out", str(out)]) == 0
    assert "newest 1 decoder step" in capsys.readouterr().out
    meta = read_metadata(out)
    assert meta.output_rows == 1 and meta.training == read_metadata(full).training
    assert main(["export", "--checkpoint", str(full), "--out", str(out), "--rows", "0"]) == 1
    err = capsys.readouterr().err
    assert "--rows must be 'all' or a number from 1 to" in err and len(err.strip().splitlines()) == 1


def test_streaming_graph_gives_the_full_graphs_trajectory(trained, tmp_path):
    """The localiser consumes only the newest decoder row: both graphs give the same poses."""
    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer

    model, ckpt, _ = trained
    full = export_onnx(model, metadata_for(model, ckpt), tmp_path / "full.onnx")
    one = export_onnx(model, metadata_for(model, ckpt), tmp_path / "one.onnx", rows=1)
    rng = np.random.default_rng(5)
    n = schema.WINDOW_LEN + 120
    onboard = NORM_MEAN + 0.3 * NORM_STD * rng.normal(size=(n, schema.NUM_SIGNALS))
    x0 = np.zeros(8)
    x0[4] = 12.0
    trajs = []
    for path in (full, one):
        for stride in (1, 3):
            loc = StreamingLocalizer(OnnxModel(path), LocalizerConfig(stride=stride, fuse_gnss=False))
            trajs.append(loc.run_arrays(onboard, x0, start_index=schema.WINDOW_LEN - 1).x)
    assert np.isfinite(trajs[0][-1]).all()
    np.testing.assert_allclose(trajs[2], trajs[0], atol=1e-4)
    np.testing.assert_allclose(trajs[3], trajs[1], atol=1e-4)
    assert not np.allclose(trajs[0][-1], trajs[1][-1])  # the strides differ: the check can see a difference


def test_static_int8_graph_is_quantised_runs_in_the_runtime_and_agrees_with_fp32(trained, tmp_path):
    """``--int8 static``'s recipe: QDQ nodes calibrated on simulated windows; the runtime's OnnxModel runs it."""
    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.training.quantize import quantize_static_int8, simulated_windows, z_rmse_change

    model, ckpt, _ = trained
    fp32 = export_onnx(model, metadata_for(model, ckpt), tmp_path / "m.onnx", rows=1)
    calibration, _ = simulated_windows(16)
    assert calibration.shape == (16, schema.WINDOW_LEN, schema.NUM_SIGNALS) and np.isfinite(calibration).all()
    q = quantize_static_int8(fp32, tmp_path / "m_s8.onnx", calibration)
    ops = [n.op_type for n in onnx.load(str(q)).graph.node]
    assert ops.count("QuantizeLinear") >= 4 and ops.count("DequantizeLinear") >= 4  # really quantised
    training = read_metadata(q).training
    assert training["int8"] is True and training["variant"] == "static-qdq-u8"
    assert training["calibration"]["windows"] == 16
    windows, z = simulated_windows(12, seed=8000)
    a, b = OnnxModel(fp32), OnnxModel(q)
    spread = []
    for w in windows:
        assert a.step(w[None]).name == b.step(w[None]).name == "SUCCESS"
        np.testing.assert_allclose(b.mean, a.mean, atol=0.05 * NORM_STD[0])  # int8 rounding, not a different model
        spread.append(a.mean[0].copy())  # OnnxModel reuses its output buffer
    assert np.ptp(np.asarray(spread)[:, 0]) > 0.05 * NORM_STD[0]  # the windows differ more than the tolerance
    change = z_rmse_change(fp32, q, windows, z)
    assert change["n_windows"] == 12 and set(change["relative_change"]) == set(schema.STATE_NAMES)


def test_optimized_graph_has_fused_ops_and_the_fp32_numbers(trained, tmp_path):
    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.training.quantize import max_output_difference, optimize_transformer

    model, ckpt, _ = trained
    fp32 = export_onnx(model, metadata_for(model, ckpt), tmp_path / "m.onnx", rows=1)
    fused = optimize_transformer(fp32, tmp_path / "m_opt.onnx", attention=False, ort_fusions=True)
    assert fused.get("SkipLayerNormalization", 0) > 0 and fused["ort_Attention"] == 0  # its attention fusion: none
    domains = {n.domain for n in onnx.load(str(tmp_path / "m_opt.onnx")).graph.node}
    assert "com.microsoft" in domains
    assert read_metadata(tmp_path / "m_opt.onnx").training["fusions"] == fused
    diff = max_output_difference(fp32, tmp_path / "m_opt.onnx", _windows(20, seed=6))
    assert diff["mean"] <= 1e-4 and diff["var"] <= 1e-4, diff
    assert OnnxModel(tmp_path / "m_opt.onnx").step(_windows(1)).name == "SUCCESS"


def test_cli_export_optimize_and_static_int8_options(trained, tmp_path, capsys):
    _, _, ckpt_path = trained
    out = tmp_path / "opt.onnx"
    assert main(["export", "--checkpoint", str(ckpt_path), "--out", str(out), "--optimize"]) == 0
    text = capsys.readouterr().out
    assert "fusions applied: " in text and (tmp_path / "opt.fp32.onnx").is_file()
    assert read_metadata(out).training["variant"] == "optimized"
    assert "MultiHeadAttention" in text
    for bad, message in ((["--int8", "static"], "--int8 needs --data"),
                         (["--int8", "static", "--data", "d", "--optimize"], "combines with --int8 dynamic only")):
        assert main(["export", "--checkpoint", str(ckpt_path), "--out", str(tmp_path / "x.onnx"), *bad]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit):  # argparse's own usage error
        main(["export", "--checkpoint", str(ckpt_path), "--out", str(tmp_path / "x.onnx"), "--int8", "dense"])
    assert "invalid choice: 'dense'" in capsys.readouterr().err


def test_attention_fusion_replaces_every_attention_and_keeps_the_numbers(trained, tmp_path):
    """The project's pass: each exported attention chain -> one MultiHeadAttention; dynamic int8 on top runs."""
    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.training.fusion import fuse_attention
    from prml2_edge.training.quantize import max_output_difference, optimize_transformer, quantize_prml2

    model, ckpt, _ = trained
    fp32 = export_onnx(model, metadata_for(model, ckpt), tmp_path / "m.onnx", rows=1)
    proto = onnx.load(str(fp32))
    n_attn = 3 * PRESET.model.n_layers  # encoder self, decoder self and cross attention per layer
    assert [n.op_type for n in proto.graph.node].count("Softmax") == n_attn
    assert fuse_attention(proto) == n_attn
    ops = [n.op_type for n in proto.graph.node]
    assert "Softmax" not in ops and ops.count("MultiHeadAttention") == n_attn
    assert fuse_attention(proto) == 0  # nothing left to match
    fused = optimize_transformer(fp32, tmp_path / "opt.onnx")
    assert fused == {"MultiHeadAttention": n_attn}
    assert read_metadata(tmp_path / "opt.onnx").training["variant"] == "optimized"
    diff = max_output_difference(fp32, tmp_path / "opt.onnx", _windows(20, seed=7))
    assert diff["mean"] <= 1e-4 and diff["var"] <= 1e-4, diff
    q = quantize_prml2(tmp_path / "opt.onnx", tmp_path / "opt8.onnx")
    assert "MatMulInteger" in {n.op_type for n in onnx.load(str(q)).graph.node}  # ORT fuses it at load time
    a, b = OnnxModel(fp32), OnnxModel(q)
    w = _windows(1, seed=8)
    assert a.step(w).name == b.step(w).name == "SUCCESS"
    np.testing.assert_allclose(b.mean, a.mean, atol=0.05 * NORM_STD[0])


def test_cli_export_optimize_with_int8_quantises_the_fused_graph(trained, tmp_path, capsys):
    from prml2_edge.data.datasets import generate_dataset

    _, _, ckpt_path = trained
    data = tmp_path / "data"
    generate_dataset(data, {"name": "export-tiny", "drives": [  # short drives: a few validation windows
        {"name": "dry_a", "family": "mixed", "mu": 1.0, "seed": 5, "minutes": 1.5}]}, workers=1, progress=False)
    out = tmp_path / "o8.onnx"
    assert main(["export", "--checkpoint", str(ckpt_path), "--out", str(out), "--optimize", "--int8",
                 "--data", str(data)]) == 0
    text = capsys.readouterr().out
    assert "fusions applied: " in text and "int8 (dynamic, on the optimised graph)" in text
    ops = {n.op_type for n in onnx.load(str(out)).graph.node}
    assert {"MultiHeadAttention", "MatMulInteger"} <= ops
    assert (tmp_path / "o8.opt.onnx").is_file() and (tmp_path / "o8.fp32.onnx").is_file()
    assert read_metadata(out).training["int8"] is True


def _exported_variant(overrides: dict, seed: int, path):
    """A tiny PRML2 model with ``overrides`` on the preset's config and distinct random weights, exported to
    ``path``: ``(model, path)``."""
    from prml2_edge.training.presets import with_overrides

    torch.manual_seed(seed)
    cfg = with_overrides(PRESET.model, overrides)
    model = Prml2Model(cfg, NORM_MEAN, NORM_STD, [12.0, 0.0, 0.0, 0.0, 0.0], [7.0, 0.2, 1.2, 1.8, 0.2]).eval()
    with torch.no_grad():  # distinct weights (the exporter folds identical constants into one)
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    ckpt = make_checkpoint(model, "tiny", PRESET.train, "fp-test", epoch=1, stage="pretrain")
    return model, export_onnx(model, metadata_for(model, ckpt), path)


def test_omega_residual_model_exports_and_reexports_with_the_same_numbers(tmp_path):
    """The residual form's yaw-rate pass-through is in the graph: onnxruntime matches torch, and a re-export from
    the .onnx (config from the metadata, weights from the graph) computes the same numbers."""
    from prml2_edge.training.export_onnx import model_from_onnx

    model, path = _exported_variant({"omega_residual": True}, 4, tmp_path / "r.onnx")
    assert read_metadata(path).config["omega_residual"] is True
    diff = parity(model, path, _windows(20))
    assert diff["mean"] <= 1e-4 and diff["var"] <= 1e-4, diff
    again, _, _ = model_from_onnx(path)
    assert again.cfg.omega_residual
    x = torch.as_tensor(_windows(3, seed=1))
    with torch.no_grad():
        torch.testing.assert_close(again(x)[0], model(x)[0])


def test_a_model_trained_on_debiased_cues_says_so_to_the_runtime_and_keeps_it_on_reexport(tmp_path):
    """``cue_debiased_inputs`` changes what the model reads, not its graph: the metadata carries it, the runtime's
    metadata reader answers it, and a re-export from the .onnx keeps it."""
    import dataclasses

    from prml2_edge.model_meta import ModelMetadata
    from prml2_edge.training.export_onnx import model_from_onnx

    model, path = _exported_variant({"cue_debiased_inputs": True}, 5, tmp_path / "d.onnx")
    meta = read_metadata(path)
    assert isinstance(meta, ModelMetadata) and meta.reads_debiased_cues
    assert model_from_onnx(path)[0].cfg.cue_debiased_inputs
    older = {k: v for k, v in meta.config.items() if k != "cue_debiased_inputs"}
    assert not dataclasses.replace(meta, config=older).reads_debiased_cues  # models exported before read raw rows
