"""Tiny hand-rolled kinematic drives for the training tests (no simulator), and the OSD baseline on them.

Other training tests import :func:`toy_drive` / :func:`toy_windows` from here.
"""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.data.revsted import Drive
from prml2_edge.data.windows import build_windows
from prml2_edge.evaluation.osd import osd_baseline_z, standstill_bias, standstill_mask

YAW_BIAS_RADPS = 0.05
LAT_BIAS_MPS2 = 0.1


def toy_drive(n: int = 1200, seed: int = 0, name: str = "toy", standstill_s: float = 2.0) -> Drive:
    """A planar kinematic drive at 50 Hz: smooth speed and yaw-rate profiles, starting at standstill.

    ``z_gt = [v_x, 0, a_x, a_y = v omega (specific force), omega]``; the onboard yaw rate and lateral
    acceleration carry the biases above; wheel speeds and speedometer follow v_x.
    """
    rng = np.random.default_rng(seed)
    dt = schema.DT_S
    t = np.arange(n) * dt
    k = np.arange(n)
    still = int(standstill_s / dt)
    ramp = np.clip((k - still) / 150.0, 0.0, 1.0)
    v = ramp * (8.0 + 3.0 * np.sin(2 * np.pi * t / (9.0 + rng.uniform(0, 3))) + rng.uniform(0, 4))
    omega = ramp * 0.15 * np.sin(2 * np.pi * t / (7.0 + rng.uniform(0, 4)) + rng.uniform(0, 6))
    a_x = np.gradient(v, dt)
    psi = 0.3 + np.cumsum(omega) * dt
    x = np.cumsum(v * np.cos(psi)) * dt
    y = np.cumsum(v * np.sin(psi)) * dt
    a_y = v * omega
    z = np.stack([v, np.zeros(n), a_x, a_y, omega], axis=1)
    noise = rng.normal(size=(n, 9)) * 0.01
    onboard = np.stack([
        v * 1.03, omega * 2.7 * 15.0 / np.maximum(v, 1.0), omega + YAW_BIAS_RADPS, a_y + LAT_BIAS_MPS2,
        np.maximum(0.0, -a_x) * 8.0, v, v, v, v,
    ], axis=1) + noise
    onboard[:, 5:] = np.where(v[:, None] < 1e-6, 0.0, onboard[:, 5:])  # wheels read 0 at standstill
    onboard[:, 0] = np.maximum(onboard[:, 0], 0.0)
    pose = np.stack([x, y, psi], axis=1)
    return Drive(name=name, path=None, t_s=t, onboard=onboard, z_gt=z, pose_gt=pose, meta={"mu": 1.0})


def toy_windows(n_drives: int = 2, n: int = 1200, stride: int = 50, seed: int = 0):
    drives = [toy_drive(n, seed + i, f"toy_{i}") for i in range(n_drives)]
    return drives, build_windows(drives, stride=stride)


def test_toy_drive_is_kinematically_consistent():
    d = toy_drive()
    speed = np.hypot(*np.diff(d.pose_gt[:, :2], axis=0).T) / schema.DT_S
    np.testing.assert_allclose(speed, d.z_gt[1:, 0], atol=1e-9)
    assert d.onboard.shape == (1200, schema.NUM_SIGNALS)


def test_osd_baseline_removes_standstill_biases():
    d = toy_drive()
    assert standstill_mask(d.onboard)[:50].all()
    bias = standstill_bias(d.onboard)
    assert bias.n_samples >= 50
    assert bias.yaw_rate_radps == pytest.approx(YAW_BIAS_RADPS, abs=0.005)
    assert bias.lat_accel_mps2 == pytest.approx(LAT_BIAS_MPS2, abs=0.005)
    z = osd_baseline_z(d.onboard, bias)
    assert np.isnan(z[:, schema.Z.V_Y]).all() and np.isnan(z[:, schema.Z.A_X]).all()
    err_w = z[:, schema.Z.OMEGA_Z] - d.z_gt[:, schema.Z.OMEGA_Z]
    raw_err_w = d.onboard[:, 2] - d.z_gt[:, schema.Z.OMEGA_Z]
    assert np.sqrt(np.mean(err_w**2)) < 0.5 * np.sqrt(np.mean(raw_err_w**2))
    np.testing.assert_allclose(z[:, schema.Z.V_X], d.onboard[:, 5:9].mean(axis=1))


def test_osd_baseline_without_standstill_has_zero_bias():
    d = toy_drive(standstill_s=0.0)
    assert standstill_bias(d.onboard[300:]).n_samples == 0
    assert standstill_bias(d.onboard[300:]).yaw_rate_radps == 0.0
