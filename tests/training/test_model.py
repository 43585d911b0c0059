"""The PRML2 transformer, its presets and the training losses."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from prml2_edge import schema  # noqa: E402
from prml2_edge.errors import ConfigError, ModelError  # noqa: E402
from prml2_edge.training.losses import (  # noqa: E402
    initial_state,
    nll_loss,
    position_loss,
    to_window_frame,
)
from prml2_edge.training.model import Prml2Model, check_window  # noqa: E402
from prml2_edge.training.presets import (  # noqa: E402
    PRESETS,
    ModelConfig,
    get_preset,
    model_config_from_dict,
    with_overrides,
)

torch.set_num_threads(1)
TINY = get_preset("tiny").model


def _model(seed: int = 0, cfg: ModelConfig = TINY) -> Prml2Model:
    torch.manual_seed(seed)
    return Prml2Model(cfg, np.linspace(0, 8, 9), np.linspace(1, 3, 9), [10.0, 0.0, 0.0, 0.0, 0.0],
                      [5.0, 0.2, 1.0, 2.0, 0.2])


def test_presets_are_valid_and_paper_matches_the_paper():
    for preset in PRESETS.values():
        preset.model.validate()
        preset.train.validate()
    paper = get_preset("paper")
    assert (paper.model.d_model, paper.model.n_heads, paper.model.n_layers) == (512, 8, 2)
    assert (paper.model.window_len, paper.model.encoder_len) == (schema.WINDOW_LEN, schema.ENCODER_LEN)
    assert (paper.train.lr, paper.train.batch_size, paper.train.epochs, paper.train.beta) == (1e-4, 250, 20, 8.0)
    assert paper.train.pretrain_epochs() == 14
    assert with_overrides(paper.train, {"finetune": False}).pretrain_epochs() == 20


def test_config_errors_are_one_line():
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        get_preset("huge")
    with pytest.raises(ConfigError, match="divisible"):
        ModelConfig(d_model=10, n_heads=3).validate()
    with pytest.raises(ConfigError, match="unknown model config key 'depth'"):
        model_config_from_dict({"depth": 3})
    with pytest.raises(ConfigError, match="unknown override"):
        with_overrides(TINY, {"width": 3})


def test_forward_shapes_positive_variance_and_si_outputs(rng):
    model = _model().eval()
    x = torch.as_tensor(rng.normal(size=(3, 250, 9)) * 5, dtype=torch.float32)
    mean, var = model(x)
    assert mean.shape == var.shape == (3, schema.DECODER_LEN, schema.NUM_STATES)
    assert torch.all(var > 0)
    mean_n, var_n = model.forward_normalised(x)
    torch.testing.assert_close(mean, mean_n * model.z_std + model.z_mean)
    torch.testing.assert_close(var, var_n * model.z_std**2)
    assert torch.all(var_n >= TINY.var_floor)


def test_wheel_features_are_axle_means_and_scaled_left_right_differences(rng):
    assert TINY.wheel_diff_gain > 0  # the tests' models (and the edge preset) use them
    model = _model().eval()
    x = torch.as_tensor(rng.normal(size=(2, 7, 9)), dtype=torch.float32)
    f = model.features(x)
    fl, fr, rl, rr = (x[..., i] for i in schema.WHEEL_SPEED_INDICES)
    g = TINY.wheel_diff_gain
    expected = torch.stack([(fl + fr) / 2, (rl + rr) / 2, g * (fr - fl), g * (rr - rl)], -1)
    torch.testing.assert_close(f[..., 5:9], expected)
    torch.testing.assert_close(f[..., :5], x[..., :5])  # the other signals pass through
    swapped = x[..., [0, 1, 2, 3, 4, 6, 5, 8, 7]]  # mirror left and right: the differences change sign
    torch.testing.assert_close(model.features(swapped)[..., 7:9], -f[..., 7:9])
    plain = _model(cfg=with_overrides(TINY, {"wheel_diff_gain": 0.0}))
    assert plain.features(x) is x  # gain 0: the paper's inputs, as models exported before the option
    with pytest.raises(ConfigError, match="wheel_diff_gain"):
        with_overrides(TINY, {"wheel_diff_gain": -1.0}).validate()


def test_decoder_output_depends_on_encoder_context(rng):
    model = _model().eval()
    x = torch.as_tensor(rng.normal(size=(1, 250, 9)), dtype=torch.float32)
    y = x.clone()
    y[:, :150] += 3.0  # change only the encoder part
    with torch.no_grad():
        assert not torch.allclose(model(x)[0], model(y)[0])


def test_same_seed_same_weights_and_batch_independence(rng):
    a, b = _model(7), _model(7)
    for pa, pb in zip(a.parameters(), b.parameters(), strict=True):
        assert torch.equal(pa, pb)
    x = torch.as_tensor(rng.normal(size=(4, 250, 9)), dtype=torch.float32)
    with torch.no_grad():
        full = a.eval()(x)[0]
        single = a(x[2:3])[0]
    torch.testing.assert_close(full[2:3], single, atol=1e-5, rtol=1e-5)


def test_check_window_rejects_wrong_shape():
    with pytest.raises(ModelError, match=r"\(B, 250, 9\)"):
        check_window(torch.zeros(1, 200, 9), TINY)


def test_bad_normalisation_stats_are_rejected():
    with pytest.raises(ModelError, match="norm_std"):
        Prml2Model(TINY, np.zeros(9), np.ones(8), np.zeros(5), np.ones(5))


def test_nll_matches_gaussian_formula(rng):
    mean = torch.as_tensor(rng.normal(size=(2, 4, 5)))
    var = torch.as_tensor(rng.uniform(0.1, 2, size=(2, 4, 5)))
    z = torch.as_tensor(rng.normal(size=(2, 4, 5)))
    std = torch.ones(5, dtype=torch.float64)
    want = ((z - mean) ** 2 / var + torch.log(var)).sum(dim=(1, 2))
    torch.testing.assert_close(nll_loss(mean, var, z, std), want)
    # normalised units change the value by a constant only
    std2 = torch.full((5,), 3.0, dtype=torch.float64)
    diff = nll_loss(mean, var, z, std2) - nll_loss(mean, var, z, std)
    torch.testing.assert_close(diff, torch.full((2,), -4 * 5 * math.log(9.0), dtype=torch.float64))


def test_nll_mean_reduction_is_the_sum_over_the_terms(rng):
    mean = torch.as_tensor(rng.normal(size=(2, 4, 5)))
    var = torch.as_tensor(rng.uniform(0.1, 2, size=(2, 4, 5)))
    z = torch.as_tensor(rng.normal(size=(2, 4, 5)))
    std = torch.ones(5, dtype=torch.float64)
    torch.testing.assert_close(nll_loss(mean, var, z, std, "mean") * 20, nll_loss(mean, var, z, std))
    with pytest.raises(ValueError, match="reduction"):
        nll_loss(mean, var, z, std, "max")


def test_position_loss_is_bounded_by_beta():
    d = torch.zeros(1, 100, 2)
    assert position_loss(d, d, 8.0).item() == 0.0
    assert position_loss(d, d + 100.0, 8.0).item() == pytest.approx(8.0)
    small = position_loss(d, d + 0.01, 8.0).item()
    assert small == pytest.approx(100 * 2 * 1e-4, rel=1e-3)  # tanh(x) ~ x for small x


def test_window_frame_puts_first_decoder_step_at_origin_facing_x():
    psi0 = 0.7
    t = torch.arange(10, dtype=torch.float64) * 0.5
    pose = torch.stack([100 + t * math.cos(psi0), -50 + t * math.sin(psi0), torch.full_like(t, psi0)], -1)[None]
    local = to_window_frame(pose, 3)
    torch.testing.assert_close(local[0, 3], torch.zeros(2, dtype=torch.float64))
    torch.testing.assert_close(local[0, :, 1], torch.zeros(10, dtype=torch.float64), atol=1e-12, rtol=0)
    torch.testing.assert_close(local[0, :, 0], t - t[3])


def test_initial_state_places_z_in_ekf_layout():
    z = torch.tensor([[10.0, 0.5, 1.0, 2.0, 0.1]])
    x0 = initial_state(z)
    assert x0[0, schema.EkfState.POS].abs().sum() == 0 and x0[0, schema.EkfState.YAW].item() == 0
    assert x0[0, schema.EkfState.VEL].tolist() == [10.0, 0.5]
    assert x0[0, schema.EkfState.ACC].tolist() == [1.0, 2.0]
    assert x0[0, schema.EkfState.OMEGA_Z].item() == pytest.approx(0.1)


def test_omega_residual_starts_at_the_can_yaw_rate_and_fits_the_correction(rng):
    """--omega-residual: omega_z's mean is the CAN yaw rate plus the correction; at initialisation the
    transformer's part is zero, so with a zero skip the output is the gyro itself, and init_skip fits the
    correction (a gyro reading 10 % high and 0.01 rad/s off: the least-squares correction undoes both)."""
    cfg = with_overrides(TINY, {"omega_residual": True})
    model = _model(cfg=cfg).eval()
    yaw = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index
    x = torch.as_tensor(rng.normal(size=(2, 250, 9)), dtype=torch.float32)
    with torch.no_grad():
        mean, _ = model(x)
    torch.testing.assert_close(mean[..., schema.Z.OMEGA_Z], x[:, schema.ENCODER_LEN:, yaw], atol=1e-5, rtol=0)
    plain = _model(cfg=TINY).eval()
    with torch.no_grad():
        assert not torch.allclose(plain(x)[0][..., schema.Z.OMEGA_Z], x[:, schema.ENCODER_LEN:, yaw], atol=1e-3)
    rows = rng.normal(size=(4000, 9))
    omega = rng.normal(scale=0.2, size=4000)
    rows[:, yaw] = 1.1 * omega + 0.01
    z = np.zeros((4000, 5))
    z[:, schema.Z.OMEGA_Z] = omega
    model.init_skip(rows, z, ridge=0.0)
    with torch.no_grad():
        out = model.forward_normalised(torch.as_tensor(np.repeat(rows[None, :250], 1, 0), dtype=torch.float32))[0]
        omega_hat = (out * model.z_std + model.z_mean)[0, :, schema.Z.OMEGA_Z].numpy()
    np.testing.assert_allclose(omega_hat, omega[schema.ENCODER_LEN:250], atol=1e-4)
    assert model_config_from_dict({**TINY.__dict__, "omega_residual": True}) == cfg
