"""Physics guard: NumPy (edge) and torch (training) twins, limits from the schema."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.guard import GuardStats, norm_clamp_factor, physics_guard
from prml2_edge.schema import Z

A_DRY = schema.accel_limit_mps2(1.0)


def z_vec(vx=0.0, vy=0.0, ax=0.0, ay=0.0, w=0.0) -> np.ndarray:
    z = np.zeros(schema.NUM_STATES)
    z[Z.V_X], z[Z.V_Y], z[Z.A_X], z[Z.A_Y], z[Z.OMEGA_Z] = vx, vy, ax, ay, w
    return z


def test_inside_limits_is_identity() -> None:
    mean = z_vec(20.0, 1.0, -3.0, 4.0, 0.5)
    var = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    m, v, fired = physics_guard(mean, var, A_DRY)
    np.testing.assert_array_equal(m, mean)
    np.testing.assert_array_equal(v, var)
    assert fired.shape == () and not fired


def test_velocity_norm_clamp_scales_variance_by_factor_squared() -> None:
    mean = z_vec(40.0, 30.0)  # |v| = 50 m/s
    var = np.ones(5)
    m, v, fired = physics_guard(mean, var, A_DRY)
    f = schema.V_MAX_MPS / (50.0 + schema.GUARD_EPS)
    np.testing.assert_allclose(m[Z.VEL], [40.0 * f, 30.0 * f], rtol=1e-15)
    assert np.linalg.norm(m[Z.VEL]) <= schema.V_MAX_MPS
    np.testing.assert_allclose(v[Z.VEL], [f**2, f**2], rtol=1e-15)
    np.testing.assert_array_equal(v[2:], 1.0)
    assert fired


@pytest.mark.parametrize("mu, a_max", [(1.0, 10.0), (0.9, 10.0), (0.5, 5.0), (0.3, 5.0)])
def test_kamms_circle_depends_on_mu(mu: float, a_max: float) -> None:
    assert schema.accel_limit_mps2(mu) == a_max
    mean = z_vec(ax=6.0, ay=-6.0)  # |a| = 8.49 m/s^2
    m, v, fired = physics_guard(mean, np.ones(5), schema.accel_limit_mps2(mu))
    assert bool(fired) == (a_max < 8.485)
    assert np.linalg.norm(m[Z.ACC]) <= a_max
    # direction kept
    assert m[Z.A_X] == pytest.approx(-m[Z.A_Y])


def test_yaw_rate_clip_and_zero_safe() -> None:
    mean = np.stack([z_vec(w=3.0), z_vec(w=-6.0), z_vec(w=0.0), z_vec(w=1.5)])
    var = np.full((4, 5), 2.0)
    m, v, fired = physics_guard(mean, var, A_DRY)
    np.testing.assert_array_equal(m[:, Z.OMEGA_Z], [1.5, -1.5, 0.0, 1.5])
    np.testing.assert_allclose(v[:, Z.OMEGA_Z], [2.0 * 0.25, 2.0 / 16, 2.0, 2.0])
    np.testing.assert_array_equal(fired, [True, True, False, False])
    assert np.all(np.isfinite(v))


def test_batched_shapes_and_fired_any() -> None:
    rng = np.random.default_rng(3)
    mean = rng.normal(scale=[25, 25, 8, 8, 1.2], size=(4, 7, 5))
    var = rng.uniform(0.1, 1.0, size=(4, 7, 5))
    m, v, fired = physics_guard(mean, var, A_DRY)
    assert m.shape == v.shape == (4, 7, 5) and fired.shape == (4, 7)
    expect = (
        (np.linalg.norm(mean[..., Z.VEL], axis=-1) + schema.GUARD_EPS > schema.V_MAX_MPS)
        | (np.linalg.norm(mean[..., Z.ACC], axis=-1) + schema.GUARD_EPS > A_DRY)
        | (np.abs(mean[..., Z.OMEGA_Z]) > schema.OMEGA_MAX_RADPS)
    )
    np.testing.assert_array_equal(fired, expect)
    assert 0 < fired.sum() < fired.size
    assert np.all(np.linalg.norm(m[..., Z.VEL], axis=-1) <= schema.V_MAX_MPS)
    assert np.all(np.linalg.norm(m[..., Z.ACC], axis=-1) <= A_DRY)
    assert np.all(v <= var) and np.all(v > 0)
    with pytest.raises(ValueError):
        physics_guard(mean[..., :4], var[..., :4], A_DRY)
    with pytest.raises(ValueError):
        physics_guard(mean, var, 0.0)


def test_norm_clamp_factor_zero_vector() -> None:
    assert norm_clamp_factor(np.zeros(2), 1.0) == 1.0


def test_guard_stats() -> None:
    stats = GuardStats()
    assert stats.fire_rate == 0.0
    stats.update(np.array([[True, False], [False, False]]))
    stats.update(np.array(False))
    assert (stats.n_predictions, stats.n_fired) == (5, 1)
    assert stats.fire_rate == pytest.approx(0.2)
    stats.reset()
    assert stats.n_predictions == 0


# ---- torch twin ----------------------------------------------------------------------------------


@pytest.fixture
def torch_mod():
    torch = pytest.importorskip("torch")
    torch.set_num_threads(1)
    return torch


@pytest.mark.torch
@pytest.mark.parametrize("mu", [1.0, 0.4])
def test_torch_guard_matches_numpy(torch_mod, mu: float) -> None:
    torch = torch_mod
    from prml2_edge.training.guard_torch import PhysicsGuard

    rng = np.random.default_rng(11)
    mean = rng.normal(scale=[25, 25, 8, 8, 1.2], size=(6, 9, 5))
    mean[0, 0] = 0.0  # exact zero vectors and yaw rate
    mean[0, 1, Z.OMEGA_Z] = 1.5  # on the limit
    var = rng.uniform(1e-3, 10.0, size=(6, 9, 5))
    guard = PhysicsGuard(mu=mu)
    m_t, v_t = guard(torch.from_numpy(mean), torch.from_numpy(var))
    m_n, v_n, fired = physics_guard(mean, var, schema.accel_limit_mps2(mu))
    np.testing.assert_allclose(m_t.numpy(), m_n, rtol=1e-15, atol=0)
    np.testing.assert_allclose(v_t.numpy(), v_n, rtol=1e-15, atol=0)
    assert guard.n_predictions == 54 and guard.n_fired == int(fired.sum())
    assert guard.fire_rate() == pytest.approx(fired.mean())
    assert "n_fired" not in guard.state_dict() and len(guard.state_dict()) == 0
    guard.reset_stats()
    assert guard.n_predictions == 0 and guard.fire_rate() == 0.0
    # float32 too
    m32, _ = guard(torch.from_numpy(mean).float(), torch.from_numpy(var).float())
    assert m32.dtype == torch.float32
    np.testing.assert_allclose(m32.numpy(), m_n, rtol=1e-6, atol=1e-6)


@pytest.mark.torch
def test_torch_guard_gradients(torch_mod) -> None:
    torch = torch_mod
    from prml2_edge.training.guard_torch import PhysicsGuard

    guard = PhysicsGuard(mu=1.0)
    rng = np.random.default_rng(5)
    mean = torch.tensor(rng.normal(scale=[25, 25, 8, 8, 1.2], size=(4, 5)), requires_grad=True)
    var = torch.tensor(rng.uniform(0.1, 2.0, size=(4, 5)), requires_grad=True)

    def f(m, v):
        gm, gv = guard(m, v)
        return gm, gv

    # away from the kinks (|omega| = omega_max exactly) the guard is smooth
    assert torch.autograd.gradcheck(f, (mean, var))
    zero = torch.zeros(2, 5, dtype=torch.float64, requires_grad=True)
    gm, gv = guard(zero, torch.ones(2, 5, dtype=torch.float64))
    (gm.sum() + gv.sum()).backward()
    assert torch.all(torch.isfinite(zero.grad))
    np.testing.assert_array_equal(zero.grad.numpy(), 1.0)


def test_row_guard_matches_the_array_guard_bit_for_bit():
    """physics_guard_row (the runtime's one prediction per step) gives exactly physics_guard's numbers."""
    from prml2_edge.guard import physics_guard_row

    rng = np.random.default_rng(7)
    mean = rng.normal(0.0, 1.0, (4000, 5)) * np.array([40.0, 5.0, 12.0, 12.0, 2.0])
    var = rng.uniform(1e-6, 10.0, (4000, 5))
    mean[::97, 4] = np.nan
    mean[::89, 0] = 0.0
    mean[::89, 1] = 0.0
    for a_max in (10.0, 5.0):
        ref_mean, ref_var, ref_fired = physics_guard(mean, var, a_max)
        for i in range(mean.shape[0]):
            m, v, fired = physics_guard_row(mean[i], var[i], a_max)
            np.testing.assert_array_equal(m, ref_mean[i])
            np.testing.assert_array_equal(v, ref_var[i])
            assert fired == bool(ref_fired[i])
