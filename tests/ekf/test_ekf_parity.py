"""Torch EKF (training) against the NumPy EKF (runtime): parity, Jacobian, gradients, numerical health."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from prml2_edge import schema  # noqa: E402
from prml2_edge.ekf import numpy_ekf as ne  # noqa: E402
from prml2_edge.schema import EkfState  # noqa: E402
from prml2_edge.training import ekf_torch as et  # noqa: E402

pytestmark = pytest.mark.torch
DT = schema.DT_S


@pytest.fixture(autouse=True)
def _one_thread():
    torch.set_num_threads(1)


def drive(rng: np.random.Generator, n: int, log10_var_range: tuple[float, float] = (-4.0, 0.0)):
    """A smooth synthetic drive as pseudo-measurements z (n, 5) with variances (n, 5)."""
    t = np.arange(n) * DT
    z = np.empty((n, schema.NUM_STATES))
    z[:, schema.Z.V_X] = 15.0 + 8.0 * np.sin(0.05 * t)
    z[:, schema.Z.V_Y] = 0.3 * np.sin(0.4 * t)
    z[:, schema.Z.A_X] = 0.4 * np.cos(0.05 * t)
    z[:, schema.Z.A_Y] = 3.0 * np.sin(0.2 * t)
    z[:, schema.Z.OMEGA_Z] = 0.25 * np.sin(0.2 * t)
    z += rng.normal(scale=0.05, size=z.shape)
    z_var = 10.0 ** rng.uniform(*log10_var_range, size=z.shape)
    return z, z_var


def numpy_run(x0, P0, z, z_var, Q, update_first=True):
    xs, ps = [], []
    x, P = x0.copy(), P0.copy()
    for t in range(len(z)):
        if t > 0 or not update_first:
            x, P = ne.predict(x, P, Q, DT)
        x, P = ne.update(x, P, z[t], z_var[t])
        xs.append(x)
        ps.append(P)
    return np.array(xs), np.array(ps)


def initial_state(vx: float = 15.0, psi: float = 0.3) -> np.ndarray:
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.YAW] = psi
    x0[EkfState.VEL.start] = vx
    return x0


def test_float64_parity_with_numpy_over_3000_steps() -> None:
    rng = np.random.default_rng(2024)
    n = 3000
    z, z_var = drive(rng, n)
    x0, P0, Q = initial_state(), ne.default_initial_covariance(), ne.default_process_noise(DT)
    xs_np, ps_np = numpy_run(x0, P0, z, z_var, Q)
    with torch.no_grad():
        xs_t, ps_t = et.run_filter(
            torch.tensor(x0)[None], torch.tensor(P0)[None], torch.tensor(z)[None], torch.tensor(z_var)[None]
        )
    assert xs_t.dtype == torch.float64 and xs_t.shape == (1, n, 8) and ps_t.shape == (1, n, 8, 8)
    assert np.abs(xs_t[0].numpy() - xs_np).max() <= 1e-9
    assert np.abs(ps_t[0].numpy() - ps_np).max() <= 1e-9
    # the drive really moved and the position uncertainty really grew (the comparison is not trivial)
    assert np.linalg.norm(xs_np[-1, EkfState.POS]) > 500.0
    assert ps_np[-1, 0, 0] > 10 * ps_np[0, 0, 0]
    # and the Ekf class takes the same path (predict then update every step)
    ekf = ne.Ekf(x0=x0, P0=P0)
    ekf.x, ekf.P = xs_np[0], ps_np[0]
    for t in range(1, 50):
        ekf.step(z[t], z_var[t])
    np.testing.assert_allclose(ekf.x, xs_np[49], rtol=0, atol=1e-12)


def test_batch_elements_are_independent_and_update_first() -> None:
    rng = np.random.default_rng(5)
    z1, v1 = drive(rng, 40)
    z2, v2 = drive(rng, 40, (-8.0, 6.0))
    x0 = torch.tensor(np.stack([initial_state(), initial_state(5.0, -2.0)]))
    P0 = et.default_initial_covariance(torch.float64)
    z = torch.tensor(np.stack([z1, z2]))
    v = torch.tensor(np.stack([v1, v2]))
    with torch.no_grad():
        xs, ps = et.run_filter(x0, P0, z, v)
        xs_b, ps_b = et.run_filter(x0[1:], P0, z[1:], v[1:])
        xs_p, _ = et.run_filter(x0, P0, z, v, update_first=False)
    torch.testing.assert_close(xs[1:], xs_b, rtol=0, atol=1e-12)
    torch.testing.assert_close(ps[1:], ps_b, rtol=0, atol=1e-12)
    x_np, _ = numpy_run(x0[0].numpy(), P0.numpy(), z1, v1, ne.default_process_noise(), update_first=False)
    np.testing.assert_allclose(xs_p[0].numpy(), x_np, rtol=0, atol=1e-9)
    assert not torch.allclose(xs_p, xs)


def test_default_matrices_match_numpy() -> None:
    np.testing.assert_array_equal(et.default_process_noise(DT, torch.float64).numpy(), ne.default_process_noise(DT))
    np.testing.assert_array_equal(et.default_initial_covariance(torch.float64).numpy(), ne.default_initial_covariance())
    np.testing.assert_array_equal(et.measurement_matrix(torch.float64).numpy(), ne.measurement_matrix())
    assert et.default_process_noise().dtype == torch.float32


@pytest.mark.parametrize("dt", [DT, 0.5])
def test_torch_model_and_jacobian(dt: float) -> None:
    rng = np.random.default_rng(17)
    xs = np.stack([initial_state() + rng.normal(scale=[100, 100, 5, 1, 10, 3, 5, 5, ]) for _ in range(6)])
    x_t = torch.tensor(xs)
    f_t = et.process_model(x_t, dt)
    jac_t = et.process_jacobian(x_t, dt)
    for i in range(len(xs)):
        np.testing.assert_allclose(f_t[i].numpy(), ne.process_model(xs[i], dt), rtol=0, atol=1e-12)
        np.testing.assert_allclose(jac_t[i].numpy(), ne.process_jacobian(xs[i], dt), rtol=0, atol=1e-15)
        # autograd of the model and central finite differences
        auto = torch.autograd.functional.jacobian(lambda v: et.process_model(v, dt), x_t[i])
        np.testing.assert_allclose(jac_t[i].numpy(), auto.numpy(), rtol=0, atol=1e-13)
        h = 1e-4
        num = np.stack(
            [
                (et.process_model(x_t[i] + h * e, dt) - et.process_model(x_t[i] - h * e, dt)).numpy() / (2 * h)
                for e in torch.eye(8, dtype=torch.float64)
            ],
            axis=-1,
        )
        np.testing.assert_allclose(jac_t[i].numpy(), num, rtol=0, atol=1e-7)


def test_predict_matches_dense_form() -> None:
    """The block-structured F P F^T equals the dense product."""
    rng = np.random.default_rng(3)
    x = torch.tensor(np.stack([initial_state() + rng.normal(scale=3.0, size=8) for _ in range(4)]))
    a = torch.tensor(rng.normal(size=(4, 8, 8)))
    P = a @ a.transpose(-1, -2) + torch.eye(8, dtype=torch.float64)
    Q = et.default_process_noise(DT, torch.float64)
    x1, p1 = et.predict(x, P, Q, DT)
    F = et.process_jacobian(x, DT)
    torch.testing.assert_close(p1, F @ P @ F.transpose(-1, -2) + Q, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(x1, et.process_model(x, DT))


def test_gradcheck_short_sequence() -> None:
    rng = np.random.default_rng(9)
    z_np, v_np = drive(rng, 4)
    z = torch.tensor(z_np[None], requires_grad=True)
    log_var = torch.tensor(np.log(v_np[None]), requires_grad=True)
    x0 = torch.tensor(initial_state()[None], requires_grad=True)
    P0 = et.default_initial_covariance(torch.float64)

    def f(z_, lv_, x0_):
        xs, ps = et.run_filter(x0_, P0, z_, lv_.exp())
        return xs, ps.diagonal(dim1=-2, dim2=-1)

    assert torch.autograd.gradcheck(f, (z, log_var, x0), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_long_adversarial_sequence_stays_finite_with_finite_gradient(dtype) -> None:
    """3000 steps, variances mixed from 1e-8 to 1e6, speeds and rates at the guard limits."""
    gen = torch.Generator().manual_seed(0)
    b, n = 2, 3000
    lim = torch.tensor([schema.V_MAX_MPS, 3.0, 10.0, 10.0, schema.OMEGA_MAX_RADPS], dtype=dtype)
    z = ((torch.rand(b, n, 5, generator=gen, dtype=dtype) * 2 - 1) * lim).requires_grad_()
    log10_var = torch.rand(b, n, 5, generator=gen, dtype=dtype) * 14 - 8  # 1e-8 .. 1e6
    log10_var[0, ::7] = -8.0  # whole steps with every variance at the floor
    log10_var[1, ::5, :2] = 6.0  # velocity practically unobserved for whole steps
    log10_var[1, ::11, 2:] = -8.0
    log_var = (log10_var * math.log(10.0)).requires_grad_()
    x0 = torch.zeros(b, 8, dtype=dtype)
    P0 = et.default_initial_covariance(dtype)
    xs, ps = et.run_filter(x0, P0, z, log_var.exp())
    assert torch.isfinite(xs).all() and torch.isfinite(ps).all()
    assert torch.equal(ps, ps.transpose(-1, -2))
    with torch.no_grad():
        eig = torch.linalg.eigvalsh(ps.double())
        scale = ps.diagonal(dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).double()
    assert (eig >= -1e-6 * scale).all()  # positive semi-definite at every step, up to rounding
    loss = xs[:, :, EkfState.POS].square().mean() + ps[:, -1].diagonal(dim1=-2, dim2=-1).sum()
    loss.backward()
    assert torch.isfinite(z.grad).all() and torch.isfinite(log_var.grad).all()
    assert z.grad.abs().sum() > 0 and log_var.grad.abs().sum() > 0


def test_float64_long_sequence_is_positive_definite() -> None:
    rng = np.random.default_rng(1)
    z, z_var = drive(rng, 3000, (-8.0, 6.0))
    with torch.no_grad():
        _, ps = et.run_filter(
            torch.tensor(initial_state())[None],
            et.default_initial_covariance(torch.float64),
            torch.tensor(z)[None],
            torch.tensor(z_var)[None],
        )
    assert torch.linalg.cholesky_ex(ps[0])[1].eq(0).all()  # every step positive definite


def test_cholesky_jitter_and_fallback_agree() -> None:
    good = np.diag([1.0, 2.0, 3.0])
    rounding = np.array([[1.0, 1.0, 0.0], [1.0, 1.0 - 1e-17, 0.0], [0.0, 0.0, 1.0]])  # PSD, singular by rounding
    indefinite = np.array([[1.0, 5.0, 0.0], [5.0, 1.0, 0.0], [0.0, 0.0, 4.0]])
    s = np.stack([good, rounding, indefinite])
    l_t = et.cholesky_jittered(torch.tensor(s)).numpy()
    for i in range(3):
        l_n = ne.cholesky_jittered(s[i])
        np.testing.assert_allclose(l_t[i], l_n, rtol=1e-12, atol=1e-15)
        assert np.all(np.isfinite(l_n))
    np.testing.assert_allclose(l_t[0], np.sqrt(good))
    np.testing.assert_allclose(l_t[1] @ l_t[1].T, rounding, atol=1e-9)  # tiny jitter only
    np.testing.assert_allclose(l_t[2], np.diag([1.0, 1.0, 2.0]))  # off-diagonal dropped


def test_run_filter_shape_checks() -> None:
    with pytest.raises(ValueError):
        et.run_filter(torch.zeros(8), torch.eye(8), torch.zeros(2, 3, 4), torch.ones(2, 3, 4))
    with pytest.raises(ValueError):
        et.run_filter(torch.zeros(8), torch.eye(8), torch.zeros(2, 3, 5), torch.ones(2, 3, 4))


@pytest.mark.parametrize("offset_share", [1.0, ne.CalibrationNoise.model_offset_share])
def test_float64_parity_with_numpy_calibrated_over_3000_steps(offset_share: float) -> None:
    """The calibration states, the model bias and the raw cues: both twins agree to 1e-9 over 3000 steps, with the
    model's omega_z carrying the whole CAN yaw-rate offset and with the runtime's share of it."""
    rng = np.random.default_rng(7)
    n = 3000
    z, z_var = drive(rng, n, (-4.0, -1.0))
    yaw = z[:, schema.Z.OMEGA_Z] + 0.007 + rng.normal(scale=0.005, size=n)  # CAN yaw rate with an offset
    wheel = 1.01 * z[:, schema.Z.V_X] + rng.normal(scale=0.01, size=n)  # wheels read 1 % fast
    cues = np.stack([yaw, wheel], axis=1)
    cue_var = np.tile([0.005**2, 0.01**2], (n, 1))
    ekf = ne.Ekf(x0=initial_state(), calibration=True)
    x0, P0, Q = ekf.x.copy(), ekf.P.copy(), ekf.Q.copy()
    xs_np, ps_np = [], []
    for t in range(n):
        if t > 0:
            ekf.x, ekf.P = ne.predict(ekf.x, ekf.P, ekf.Q, DT, ekf.model_bias_decay)
        ekf.x, ekf.P = ne.update_model_calibrated(ekf.x, ekf.P, z[t], z_var[t], offset_share)
        assert ekf.update_cues(yaw[t], cue_var[t, 0], wheel[t], cue_var[t, 1]) is ne.StepStatus.SUCCESS
        xs_np.append(ekf.x.copy())
        ps_np.append(ekf.P.copy())
    xs_np, ps_np = np.array(xs_np), np.array(ps_np)
    with torch.no_grad():
        xs_t, ps_t = et.run_filter_calibrated(
            torch.tensor(x0)[None], torch.tensor(P0)[None], torch.tensor(z)[None], torch.tensor(z_var)[None],
            torch.tensor(cues)[None], torch.tensor(cue_var)[None], torch.tensor(Q),
            model_bias_decay=ekf.model_bias_decay, offset_share=offset_share)
    assert ekf.model_bias_decay < 1.0
    assert xs_t.shape == (1, n, schema.CalState.FULL_DIM)
    # the position variance grows to ~1e3 m^2 here: 1e-9 relative to each entry's size
    np.testing.assert_allclose(xs_t[0].numpy(), xs_np, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(ps_t[0].numpy(), ps_np, rtol=1e-10, atol=1e-9)
    # the calibration states really moved: the model's omega_z bias against the offset CAN yaw rate
    assert abs(xs_np[:, schema.CalState.MODEL_OMEGA_BIAS.start]).max() > 1e-3
    assert np.linalg.norm(xs_np[-1, EkfState.POS]) > 500.0
