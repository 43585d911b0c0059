"""Two-stage training on tiny toy data: stages, checkpoints, resume, skipped steps, streaming validation."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from test_train_data import toy_drive, toy_windows  # noqa: E402

from prml2_edge import schema  # noqa: E402
from prml2_edge.errors import ConfigError, ModelError  # noqa: E402
from prml2_edge.training.checkpoint import load_model, read_checkpoint  # noqa: E402
from prml2_edge.training.presets import get_preset  # noqa: E402
from prml2_edge.training.trainer import TrainData, fit, z_statistics  # noqa: E402
from prml2_edge.training.validate import (  # noqa: E402
    Segment,
    dead_reckon,
    evaluate_segments,
    stream_predict,
)

torch.set_num_threads(1)
PRESET = get_preset("tiny")
CFG = replace(PRESET.train, epochs=2, batch_size=8, max_train_windows=24, num_threads=1)


@pytest.fixture(scope="module")
def toy_data() -> TrainData:
    drives, train = toy_windows(n_drives=2, n=1200, stride=25)
    _, val = toy_windows(n_drives=1, n=600, stride=50, seed=10)
    z_mean, z_std = z_statistics(np.concatenate([d.z_gt for d in drives]))
    onboard = np.concatenate([d.onboard for d in drives])
    return TrainData(train=train, val=val, norm_mean=onboard.mean(0), norm_std=onboard.std(0), z_mean=z_mean,
                     z_std=z_std, fingerprint="toy")


def _weights(path) -> dict:
    return read_checkpoint(path)["model"]


def test_two_stages_write_self_describing_checkpoints(toy_data, tmp_path):
    result = fit(toy_data, tmp_path / "run", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)
    records = [json.loads(line) for line in result.metrics_path.read_text().splitlines()]
    assert [r["stage"] for r in records] == ["pretrain", "finetune"]
    assert np.isnan(records[0]["train_pos"]) and np.isfinite(records[1]["train_pos"])
    assert np.isfinite(records[1]["val_pos"]) and records[1]["val_pos"] >= 0
    assert all(np.isfinite(r["val_nll"]) and r["train_windows"] == 24 for r in records)
    assert (tmp_path / "run" / "loss_curve.png").stat().st_size > 1000
    # weights only: a plain torch.load(weights_only=True) reads it, and it says what it is
    raw = torch.load(result.best_path, weights_only=True)
    assert raw["signal_names"] == list(schema.SIGNAL_NAMES) and raw["schema_hash"] == schema.SCHEMA_HASH
    assert raw["dataset_fingerprint"] == "toy" and raw["preset"] == "tiny" and raw["stage"] == "finetune"
    assert raw["model_config"]["d_model"] == PRESET.model.d_model and raw["train_config"]["epochs"] == 2
    assert len(raw["norm_mean"]) == 9 and len(raw["z_std"]) == 5 and "prml2-edge" in raw["code_version"]
    assert "optimizer" not in raw and "optimizer" in torch.load(result.last_path, weights_only=True)
    model, _ = load_model(result.best_path)
    assert not model.training


def test_same_seed_is_repeatable_and_resume_equals_uninterrupted(toy_data, tmp_path):
    full = fit(toy_data, tmp_path / "full", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)

    class Crash(Exception):
        pass

    def crash(record):
        raise Crash

    with pytest.raises(Crash):  # dies after writing epoch 1
        fit(toy_data, tmp_path / "cut", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False,
            on_epoch=crash)
    resumed = fit(toy_data, tmp_path / "cut", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG,
                  progress=False, resume=tmp_path / "cut" / "last.pt")
    a, b = _weights(full.last_path), _weights(resumed.last_path)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert len(resumed.metrics_path.read_text().splitlines()) == 2
    with pytest.raises(ConfigError, match="other training options"):
        fit(toy_data, tmp_path / "cut", preset="tiny", model_cfg=PRESET.model, train_cfg=replace(CFG, lr=0.5),
            progress=False, resume=tmp_path / "cut" / "last.pt")
    with pytest.raises(ModelError, match="optimizer"):
        fit(toy_data, tmp_path / "cut", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG,
            progress=False, resume=full.best_path)


def test_nonfinite_batches_are_skipped_and_counted(toy_data, tmp_path):
    bad = toy_windows(n_drives=2, n=1200, stride=25)[1]
    bad.onboard = bad.onboard.copy()
    bad.onboard[100:110, 3] = np.nan  # a few windows carry NaN
    data = replace(toy_data, train=bad)
    cfg = replace(CFG, epochs=1, max_train_windows=0, finetune=False)
    result = fit(data, tmp_path / "nan", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg, progress=False)
    assert result.counters["skipped_nonfinite"] > 0
    assert result.counters["skipped_nonfinite"] < result.counters["steps"]
    assert all(torch.isfinite(v).all() for v in _weights(result.last_path).values())


def test_training_lowers_validation_nll(toy_data, tmp_path):
    cfg = replace(CFG, epochs=4, finetune=False, lr=3e-3, max_train_windows=0)
    result = fit(toy_data, tmp_path / "learn", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg,
                 progress=False)
    nll = [h["val_nll"] for h in result.history]
    assert nll[-1] < nll[0] - 50, nll


def test_streaming_uses_newest_window_output(toy_data, tmp_path):
    from prml2_edge.training.model import Prml2Model

    torch.manual_seed(0)
    model = Prml2Model(PRESET.model, toy_data.norm_mean, toy_data.norm_std, toy_data.z_mean, toy_data.z_std).eval()
    drive = toy_drive(400, seed=3)
    out = stream_predict(model, drive.onboard, stride=1, batch_size=64)
    assert np.isnan(out.mean[:249]).all() and out.valid[249:].all()
    with torch.no_grad():
        m, v = model(torch.as_tensor(drive.onboard[300 - 249 : 301][None], dtype=torch.float32))
    np.testing.assert_allclose(out.mean[300], m[0, -1].numpy(), atol=1e-5)
    np.testing.assert_allclose(out.var[300], v[0, -1].numpy(), rtol=1e-5)
    held = stream_predict(model, drive.onboard, stride=10, batch_size=64)
    np.testing.assert_allclose(held.mean[249:259], np.repeat(out.mean[249:250], 10, axis=0), atol=1e-5)
    np.testing.assert_allclose(held.mean[259], out.mean[259], atol=1e-5)


def test_dead_reckoning_with_true_dynamics_stays_close():
    drive = toy_drive(1200, seed=4)
    var = np.tile([0.01, 0.01, 0.1, 0.1, 1e-4], (len(drive), 1))
    errors = dead_reckon(drive.z_gt, var, drive.z_gt, drive.pose_gt, 300, 500)
    assert errors[0] == 0.0 and errors.max() < 0.5


def test_evaluate_segments_reports_rmse_osd_and_dead_reckoning(toy_data):
    from prml2_edge.training.model import Prml2Model

    torch.manual_seed(0)
    model = Prml2Model(PRESET.model, toy_data.norm_mean, toy_data.norm_std, toy_data.z_mean, toy_data.z_std)
    drive = toy_drive(1200, seed=5)
    report = evaluate_segments(model, [Segment(drive, 600, 1200, 1.0)], stride=1, window_s=4.0, progress=False)
    assert report.n_samples == 600  # context from before the segment: every sample has an estimate
    assert all(np.isfinite(v) for v in report.z_rmse.values())
    assert np.isnan(report.osd_z_rmse["v_y_mps"]) and report.osd_z_rmse["v_x_mps"] < 0.1
    assert report.dr_summary()["n_windows"] == 3
    assert 0.0 <= report.guard_fire_rate <= 1.0


def test_exploding_steps_are_skipped_and_counted(toy_data, tmp_path):
    wild = toy_windows(n_drives=2, n=1200, stride=25)[1]
    wild.onboard = wild.onboard.copy()
    wild.onboard[900:1000] *= 1e7  # windows over these rows give gradients far beyond the running norm
    data = replace(toy_data, train=wild)
    cfg = replace(CFG, epochs=1, max_train_windows=0, finetune=False, batch_size=4)
    result = fit(data, tmp_path / "wild", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg, progress=False)
    assert result.counters["skipped_exploding"] > 0
    assert result.counters["skipped_exploding"] < result.counters["steps"] // 2


def test_cli_train_on_a_folder_of_csv_drives(tmp_path, capsys):
    from prml2_edge.cli.main import main
    from prml2_edge.data.revsted import write_drive_csv

    data_dir = tmp_path / "data"
    data_dir.mkdir()
    for i in range(2):
        write_drive_csv(toy_drive(3000, seed=20 + i, name=f"toy_{i}"), data_dir / f"toy_{i}.csv")
    out = tmp_path / "run"
    code = main(["train", "--data", str(data_dir), "--out", str(out), "--preset", "tiny", "--epochs", "2",
                 "--max-train-windows", "16", "--eval-stride", "5"])
    assert code == 0
    text = capsys.readouterr().out
    assert "1 pretraining + 1 fine-tuning epochs" in text and "val z RMSE" in text and "OSD baseline" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["val"]["n_samples"] == 2 * 300 and summary["train_config"]["epochs"] == 2
    assert all(np.isfinite(v) for v in summary["val"]["z_rmse"].values())
    assert (out / "best.pt").is_file() and (out / "loss_curve.png").is_file()
    assert main(["train", "--data", str(tmp_path / "nope"), "--out", str(out), "--preset", "tiny"]) == 1
    assert "dataset folder not found" in capsys.readouterr().err


def test_prml2_and_prml2_star_agree_until_the_switch(toy_data, tmp_path):
    """One cosine over the whole run and the same seed: only the fine-tuning loss differs."""
    star = fit(toy_data, tmp_path / "star", preset="tiny", model_cfg=PRESET.model,
               train_cfg=replace(CFG, finetune=False), progress=False)
    full = fit(toy_data, tmp_path / "full", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)
    assert star.history[0]["val_nll"] == full.history[0]["val_nll"]
    assert star.history[0]["lr_end"] == full.history[0]["lr_end"]
    assert star.history[1]["stage"] == "pretrain" and full.history[1]["stage"] == "finetune"
    assert star.history[1]["val_nll"] != full.history[1]["val_nll"]


def test_mean_nll_reduction_trains_and_is_recorded(toy_data, tmp_path):
    from dataclasses import replace

    from prml2_edge.errors import ConfigError

    cfg = replace(CFG, nll_reduction="mean")
    result = fit(toy_data, tmp_path / "run", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg, progress=False)
    records = [json.loads(line) for line in result.metrics_path.read_text().splitlines()]
    assert all(np.isfinite(r["val_nll"]) for r in records)
    # per term, not per window: a window's 100 x 5 terms average to a few units
    assert all(abs(r["val_nll"]) < 50 for r in records)
    assert torch.load(result.best_path, weights_only=True)["train_config"]["nll_reduction"] == "mean"
    with pytest.raises(ConfigError, match="nll_reduction"):
        replace(CFG, nll_reduction="median").validate()


def test_segments_tile_the_samples_with_the_windows_that_end_at_them():
    drives, ws = toy_windows(n_drives=2, n=900, stride=25)
    starts = ws.segment_starts(200, 50)
    n0 = len(drives[0])
    assert np.all((starts >= ws.L - 1) & ((starts < n0 - 200 + 1) | (starts >= n0 + ws.L - 1)))  # inside a drive
    assert np.all((starts + 200 <= n0) | (starts >= n0))  # never across the boundary
    onboard, z, pose = ws.get_segments(starts[[0, -1]], 200, 10)
    assert onboard.shape == (2 * 20, ws.L, schema.NUM_SIGNALS) and z.shape == (2, 200, 5) and pose.shape == (2, 200, 3)
    s = starts[-1]
    for j in (0, 7, 19):  # window j of the second segment ends at the segment's sample 10 j + 9
        np.testing.assert_array_equal(onboard[20 + j, -1], ws.onboard[s + 10 * j + 9])
        np.testing.assert_array_equal(onboard[20 + j, 0], ws.onboard[s + 10 * j + 9 - ws.L + 1])
    np.testing.assert_array_equal(z[1], ws.z[s : s + 200])
    with pytest.raises(ValueError, match="multiple"):
        ws.get_segments(starts[:1], 205, 10)


def test_long_horizon_finetuning_runs_the_filter_across_windows(toy_data, tmp_path):
    cfg = replace(CFG, ft_horizon_s=2.0, ft_rows=10, ft_segments=2)
    assert cfg.ft_horizon_steps() == 100
    result = fit(toy_data, tmp_path / "seq", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg, progress=False)
    records = [json.loads(line) for line in result.metrics_path.read_text().splitlines()]
    assert [r["stage"] for r in records] == ["pretrain", "finetune"]
    assert np.isfinite(records[1]["train_pos"]) and records[1]["train_pos"] >= 0
    # as many windows as a window epoch: 24 windows -> round(24 * 10 / 100) = 2 segments of 10 windows
    assert records[1]["train_windows"] == 20
    plain = fit(toy_data, tmp_path / "plain", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)
    assert plain.history[0]["val_nll"] == result.history[0]["val_nll"]  # the same up to the switch
    assert plain.history[1]["val_nll"] != result.history[1]["val_nll"]
    assert torch.load(result.best_path, weights_only=True)["train_config"]["ft_horizon_s"] == 2.0
    with pytest.raises(ConfigError, match="ft_horizon_s"):
        replace(CFG, ft_horizon_s=-1.0).validate()
    assert replace(CFG, ft_horizon_s=0.1, ft_rows=10).ft_horizon_steps() == 10  # at least one window's rows
    with pytest.raises(ConfigError, match="no training segment"):
        fit(toy_data, tmp_path / "long", preset="tiny", model_cfg=PRESET.model,
            train_cfg=replace(CFG, ft_horizon_s=60.0), progress=False)


def test_init_starts_from_the_given_model_and_keeps_its_statistics(toy_data, tmp_path):
    first = fit(toy_data, tmp_path / "first", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)
    init, _ = load_model(first.best_path)
    start = {k: v.clone() for k, v in init.state_dict().items()}
    other = replace(toy_data, norm_mean=toy_data.norm_mean + 1.0)  # a new car's data: its statistics are not used
    cfg = replace(CFG, epochs=1, finetune=False, lr=1e-12)  # (almost) no step: the result is the initial model
    result = fit(other, tmp_path / "ft", preset="tiny", model_cfg=PRESET.model, train_cfg=cfg, progress=False,
                 init=init)
    tuned = result.model.state_dict()
    assert torch.allclose(tuned["in_mean"], start["in_mean"]) and not torch.allclose(
        tuned["in_mean"], torch.as_tensor(other.norm_mean, dtype=tuned["in_mean"].dtype))
    assert all(torch.allclose(tuned[k], start[k], atol=1e-6) for k in start)
    with pytest.raises(ConfigError, match="initial model's config"):
        fit(toy_data, tmp_path / "bad", preset="tiny", model_cfg=replace(PRESET.model, d_model=32), train_cfg=cfg,
            progress=False, init=init)


def test_a_transfer_that_only_gets_worse_on_the_new_cars_validation_hands_back_the_initial_model(toy_data, tmp_path):
    """A transfer run validates the model it starts from as epoch 0 (logged, saved as best.pt); an epoch replaces it
    only when it is better on the new car's validation windows, so a wrecking learning rate returns it unchanged."""
    first = fit(toy_data, tmp_path / "first", preset="tiny", model_cfg=PRESET.model, train_cfg=CFG, progress=False)
    init, _ = load_model(first.best_path)
    start = {k: v.clone() for k, v in init.state_dict().items()}
    result = fit(toy_data, tmp_path / "ft", preset="tiny", model_cfg=PRESET.model, train_cfg=replace(CFG, lr=3.0),
                 progress=False, init=init)
    records = [json.loads(line) for line in result.metrics_path.read_text().splitlines()]
    assert [(r["epoch"], r["stage"]) for r in records] == [(0, "initial"), (1, "pretrain"), (2, "finetune")]
    assert records[0]["best"] and not records[2]["best"]
    assert records[2]["val_objective"] > records[0]["val_objective"]
    best = torch.load(result.best_path, weights_only=True)
    assert best["epoch"] == 0 and all(torch.allclose(best["model"][k], start[k]) for k in start)
    assert not all(torch.allclose(result.model.state_dict()[k], start[k]) for k in start)  # it did train


def test_pretrain_physics_terms_penalise_inconsistent_and_jerky_predictions():
    from prml2_edge.training.losses import physics_consistency_loss

    t = torch.arange(50, dtype=torch.float64) * schema.DT_S
    z = torch.zeros(1, 50, 5, dtype=torch.float64)
    z[0, :, 0], z[0, :, 2] = 10.0 + 2.0 * t, 2.0  # v_x grows at exactly a_x
    assert float(physics_consistency_loss(z, schema.DT_S)) == pytest.approx(0.0, abs=1e-12)
    wrong = z.clone()
    wrong[0, :, 2] = 0.0  # a_x disagrees with dv_x/dt
    jerky = z.clone()
    jerky[0, ::2, 3] = 1.0  # a_y alternating 0 / 1 m/s^2
    assert float(physics_consistency_loss(wrong, schema.DT_S)) == pytest.approx(4.0 * schema.DT_S**2, rel=1e-6)
    assert float(physics_consistency_loss(jerky, schema.DT_S)) > 0.9
    cfg = replace(CFG, epochs=1, pretrain_physics=0.5)
    cfg.validate()
    with pytest.raises(ConfigError, match="pretrain_physics"):
        replace(CFG, pretrain_physics=-1.0).validate()


def test_yaw_offset_augmentation_moves_only_the_yaw_rate_by_one_offset_per_window():
    import math

    import torch

    from prml2_edge import schema
    from prml2_edge.training.augment import yaw_offset_augment as _yaw_offset_augment
    from prml2_edge.training.presets import TrainConfig

    onboard = torch.randn(64, 20, schema.NUM_SIGNALS)
    assert _yaw_offset_augment(onboard, TrainConfig(), 3) is onboard  # off by default
    cfg = TrainConfig(yaw_offset_aug_dps=0.6)
    out = _yaw_offset_augment(onboard, cfg, 3)
    yaw = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
    diff = (out - onboard).numpy()
    others = [i for i in range(schema.NUM_SIGNALS) if i != yaw]
    assert np.all(diff[:, :, others] == 0.0)
    per_window = diff[:, :, yaw]
    assert np.allclose(per_window, per_window[:, :1], atol=1e-6)  # constant within a window
    assert np.abs(per_window).max() <= math.radians(0.6) + 1e-6 and per_window[:, 0].std() > math.radians(0.2)
    assert torch.equal(out, _yaw_offset_augment(onboard, cfg, 3))  # seeded by the step: a resume draws the same
    assert not torch.equal(out, _yaw_offset_augment(onboard, cfg, 4))


def test_yaw_quant_augmentation_rounds_a_share_of_fine_windows_to_a_coarse_step_and_leaves_coarse_ones():
    import math

    import torch

    from prml2_edge import schema
    from prml2_edge.training.augment import QUANT_STEP_RANGE_DPS, yaw_quant_augment
    from prml2_edge.training.presets import TrainConfig

    yaw = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
    g = torch.Generator().manual_seed(0)
    onboard = torch.randn(400, 50, schema.NUM_SIGNALS, generator=g, dtype=torch.float64) * 0.05
    coarse_step = math.radians(1.28)
    onboard[200:, :, yaw] = torch.round(onboard[200:, :, yaw] / coarse_step) * coarse_step  # a 1.28 deg/s gyro
    assert yaw_quant_augment(onboard, TrainConfig(), 3) is onboard  # off by default
    with pytest.raises(ConfigError, match="share"):
        TrainConfig(yaw_quant_aug=1.5).validate()
    cfg = TrainConfig(yaw_quant_aug=0.5)
    out = yaw_quant_augment(onboard, cfg, 3)
    others = [i for i in range(schema.NUM_SIGNALS) if i != yaw]
    assert torch.equal(out[:, :, others], onboard[:, :, others])
    assert torch.equal(out[200:], onboard[200:])  # already coarser than half of any drawn step: kept
    changed = (out[:200, :, yaw] != onboard[:200, :, yaw]).any(dim=1)
    assert 0.35 < changed.double().mean() < 0.65  # about the share asked for
    lo, hi = (math.radians(d) for d in QUANT_STEP_RANGE_DPS)
    for row in out[:200][changed, :, yaw]:  # each changed window lies on one grid within the range
        levels = torch.unique(row)
        step = (levels[1:] - levels[:-1]).min() if len(levels) > 1 else torch.tensor(hi)
        assert lo * 0.999 <= step <= 2 * hi
        assert torch.allclose(torch.round(levels / step) * step, levels)
    assert (out[:200, :, yaw] - onboard[:200, :, yaw]).abs().max() <= hi / 2 + 1e-12  # rounding, nothing more
    assert torch.equal(out, yaw_quant_augment(onboard, cfg, 3))  # seeded by the step
