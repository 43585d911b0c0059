"""Learned baselines (issue 5): train briefly, export with the PRML2 contract, run in the runtime."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from test_train_data import toy_windows  # noqa: E402

from prml2_edge import schema  # noqa: E402
from prml2_edge.runtime.inference import OnnxModel  # noqa: E402
from prml2_edge.runtime.status import InferenceStatus  # noqa: E402
from prml2_edge.training.baselines.models import BASELINES, BaselineConfig, build_baseline  # noqa: E402
from prml2_edge.training.baselines.train import (  # noqa: E402
    BaselineTrainConfig,
    export_baseline,
    fit_baseline,
    load_baseline,
)
from prml2_edge.training.trainer import TrainData, z_statistics  # noqa: E402

torch.set_num_threads(1)
TINY = dict(hidden=8, n_heads=2)
TCFG = BaselineTrainConfig(epochs=1, batch_size=4, max_train_windows=8, max_val_windows=4, num_threads=1)


@pytest.fixture(scope="module")
def toy_data() -> TrainData:
    drives, train = toy_windows(n_drives=1, n=700, stride=50)
    _, val = toy_windows(n_drives=1, n=400, stride=100, seed=10)
    z_mean, z_std = z_statistics(np.concatenate([d.z_gt for d in drives]))
    onboard = np.concatenate([d.onboard for d in drives])
    return TrainData(train=train, val=val, norm_mean=onboard.mean(0), norm_std=onboard.std(0), z_mean=z_mean,
                     z_std=z_std, fingerprint="toy", skip_rows=(onboard, np.concatenate([d.z_gt for d in drives])))


@pytest.mark.parametrize("kind", sorted(BASELINES))
def test_forward_shapes_and_positive_variance(kind):
    m = build_baseline(BaselineConfig(kind=kind, **TINY), np.zeros(9), np.ones(9), np.zeros(5), np.ones(5))
    mean, var = m(torch.randn(2, schema.WINDOW_LEN, schema.NUM_SIGNALS))
    assert mean.shape == var.shape == (2, schema.DECODER_LEN, schema.NUM_STATES)
    assert bool((var > 0).all())


def test_decoder_outputs_depend_on_the_encoder_history():
    """The recurrent baselines carry context from the first H steps into the decoder outputs."""
    for kind in ("nn-vdm", "dl-avl", "rnn-ekf"):
        m = build_baseline(BaselineConfig(kind=kind, **TINY), np.zeros(9), np.ones(9), np.zeros(5), np.ones(5))
        x = torch.randn(1, schema.WINDOW_LEN, schema.NUM_SIGNALS)
        y = x.clone()
        y[:, schema.ENCODER_LEN - 20 : schema.ENCODER_LEN] += 3.0  # encoder steps only
        assert not torch.allclose(m(x)[0], m(y)[0])


@pytest.mark.parametrize("kind", ["rnn-ekf", "backprop-kf"])
def test_train_export_and_run_in_the_runtime(kind, toy_data, tmp_path):
    best = fit_baseline(toy_data, tmp_path / kind, BaselineConfig(kind=kind, **TINY), TCFG, progress=False)
    model, ckpt = load_baseline(best)
    assert ckpt["preset"] == f"baseline:{kind}" and np.isfinite(ckpt["metrics"]["val_objective"])
    windows = toy_data.val.get(np.arange(2))[0]
    res = export_baseline(best, tmp_path / f"{kind}.onnx", parity_windows=windows)
    assert res["max_abs_diff"] < 1e-3
    rt = OnnxModel(res["path"])
    assert rt.metadata.preset == f"baseline:{kind}"
    assert rt.step(windows[:1].astype(np.float32)) is InferenceStatus.SUCCESS
    with torch.no_grad():
        mean_t, _ = model(torch.as_tensor(windows[:1], dtype=torch.float32))
    np.testing.assert_allclose(rt.mean, mean_t[0].numpy(), atol=1e-3)


def test_cli_train_model_name_then_export(tmp_path, capsys):
    """``prml2 train --model NAME`` trains a baseline; ``prml2 export`` exports it for the runtime."""
    from prml2_edge.cli.main import main
    from prml2_edge.data.datasets import generate_dataset

    data = generate_dataset(tmp_path / "data", {"name": "b", "drives": [
        {"name": "dry_a", "family": "mixed", "mu": 1.0, "seed": 3, "minutes": 1.0, "role": "dry"}]},
        workers=1, progress=False)
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--model", "nn-vdm", "--hidden", "8",
                 "--epochs", "1", "--batch-size", "4", "--max-train-windows", "4", "--threads", "1",
                 "--window-stride", "100"]) == 0
    assert (run / "best.pt").is_file() and (run / "summary.json").is_file()
    out = tmp_path / "nn-vdm.onnx"
    assert main(["export", "--checkpoint", str(run / "best.pt"), "--out", str(out)]) == 0
    assert OnnxModel(out).metadata.preset == "baseline:nn-vdm"
    assert "nn-vdm" in capsys.readouterr().out
