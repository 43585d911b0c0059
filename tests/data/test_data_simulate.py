"""Simulator: the CLI writes a dataset the loader reads; physics and driver stay plausible."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.cli.main import main
from prml2_edge.data.datasets import load_dataset
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import ConfigError


def _integrate_pose(z: np.ndarray, psi0: float, dt: float = schema.DT_S) -> np.ndarray:
    """Trapezoidal dead reckoning of (x, y, psi) from ground-truth v_x, v_y, omega_z."""
    psi = psi0 + np.concatenate(([0.0], np.cumsum(0.5 * (z[1:, 4] + z[:-1, 4]) * dt)))
    ve = z[:, 0] * np.cos(psi) - z[:, 1] * np.sin(psi)
    vn = z[:, 0] * np.sin(psi) + z[:, 1] * np.cos(psi)
    x = np.concatenate(([0.0], np.cumsum(0.5 * (ve[1:] + ve[:-1]) * dt)))
    y = np.concatenate(([0.0], np.cumsum(0.5 * (vn[1:] + vn[:-1]) * dt)))
    return np.stack([x, y, psi], axis=1)


def test_cli_simulate_then_loader_round_trip_and_pose(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(["simulate", "--out", str(out), "--minutes", "1.5", "--mu", "1.0", "--seed", "5"]) == 0
    assert "wrote 1 drive" in capsys.readouterr().out
    ds = load_dataset(out)
    (drive,) = ds.drives
    assert drive.has_ground_truth and len(drive) == 4500
    assert drive.meta["family"] == "mixed" and drive.meta["seed"] == 5
    pose = _integrate_pose(drive.z_gt, drive.pose_gt[0, 2]) + np.array([*drive.pose_gt[0, :2], 0.0])
    dist = np.sum(np.hypot(*np.diff(drive.pose_gt[:, :2], axis=0).T))
    assert dist > 300.0
    err = np.hypot(*(pose[:, :2] - drive.pose_gt[:, :2]).T)
    assert err.max() < 0.002 * dist, (err.max(), dist)
    assert np.abs(pose[:, 2] - drive.pose_gt[:, 2]).max() < 2e-3


def test_same_seed_same_drive_other_seed_differs():
    a = simulate_drive(0.3, 1.0, seed=9, family="lateral")
    b = simulate_drive(0.3, 1.0, seed=9, family="lateral")
    c = simulate_drive(0.3, 1.0, seed=10, family="lateral")
    assert np.array_equal(a.onboard, b.onboard) and np.array_equal(a.z_gt, b.z_gt)
    assert not np.array_equal(a.onboard, c.onboard)


@pytest.mark.parametrize("family,mu", [("longitudinal", 1.0), ("lateral", 0.9), ("mixed", 1.0), ("snow", 0.3)])
def test_families_stay_within_physics_and_driver_limits(family, mu):
    d = simulate_drive(3.0, mu, seed=2, family=family)
    z = d.z_gt
    assert np.all(np.isfinite(z)) and np.all(np.isfinite(d.onboard))
    assert z[:, 0].min() >= 0.0 and z[:, 0].max() <= schema.V_MAX_MPS
    acc = np.hypot(z[:, 2], z[:, 3])
    assert np.percentile(acc, 99.5) <= mu * schema.G_MPS2 * 1.02
    assert np.abs(z[:, 4]).max() <= schema.OMEGA_MAX_RADPS
    jerk = np.abs(np.diff(z[:, 2])) / schema.DT_S
    assert np.percentile(jerk, 99) < 15.0  # m/s^3: no bang-bang driver
    # standstill phases of several seconds (first is always there)
    assert np.all(z[:100, 0] == 0.0)
    for k, sig in enumerate(schema.SIGNALS):
        assert sig.min <= d.onboard[:, k].min() and d.onboard[:, k].max() <= sig.max


def test_family_character():
    lon = simulate_drive(3.0, 1.0, seed=4, family="longitudinal").z_gt
    lat = simulate_drive(3.0, 1.0, seed=4, family="lateral").z_gt
    assert np.std(lon[:, 2]) > np.std(lat[:, 2])
    assert np.std(lat[:, 3]) > 2 * np.std(lon[:, 3])


def test_wheel_speeds_show_turns_and_slip():
    d = simulate_drive(3.0, 1.0, seed=6, family="mixed")
    idx = {s.name: s.index for s in schema.SIGNALS}
    z, o = d.z_gt, d.onboard
    left_turn = (z[:, 4] > 0.2) & (z[:, 0] > 4.0)
    assert left_turn.sum() > 20
    # inner (left) wheels slower than outer (right) wheels in left turns
    assert np.mean(o[left_turn, idx["wheel_speed_rr_mps"]] - o[left_turn, idx["wheel_speed_rl_mps"]]) > 0.1
    # front-wheel drive: under acceleration the front wheels turn faster than the rear ones
    acc = (z[:, 2] > 1.5) & (np.abs(z[:, 4]) < 0.05) & (z[:, 0] > 5)
    assert acc.sum() > 20
    front = o[acc][:, [idx["wheel_speed_fl_mps"], idx["wheel_speed_fr_mps"]]].mean(axis=1)
    rear = o[acc][:, [idx["wheel_speed_rl_mps"], idx["wheel_speed_rr_mps"]]].mean(axis=1)
    assert np.mean(front / rear) > 1.005


def test_snow_slips_more_than_dry():
    def slip_ratio(drive):
        z, o = drive.z_gt, drive.onboard
        m = (z[:, 0] > 5.0) & (z[:, 2] > 0.8)
        front = o[m][:, [5, 6]].mean(axis=1)
        return np.median(front / z[m, 0] - 1.0)

    assert slip_ratio(simulate_drive(3.0, 0.25, seed=8, family="snow")) > slip_ratio(
        simulate_drive(3.0, 1.0, seed=8, family="mixed"))


def test_bad_arguments_raise_config_error():
    with pytest.raises(ConfigError, match="unknown family"):
        simulate_drive(1.0, 1.0, 0, family="drift")
    with pytest.raises(ConfigError, match="snow"):
        simulate_drive(1.0, 0.9, 0, family="snow")


def test_fleet_cars_have_their_drivetrain_and_sensor_resolution():
    from prml2_edge.data.simulate import CARS, get_car

    assert len(CARS) >= 6 and {c.params.drivetrain for c in CARS.values()} == {"fwd", "rwd", "awd"}
    idx = {s.name: s.index for s in schema.SIGNALS}

    def drive_ratio(name):  # front / rear wheel speed while accelerating straight
        d = simulate_drive(2.0, 1.0, seed=6, family="longitudinal", vehicle=name)
        z, o = d.z_gt, d.onboard
        acc = (z[:, 2] > 1.5) & (np.abs(z[:, 4]) < 0.05) & (z[:, 0] > 5)
        assert acc.sum() > 20 and d.meta["vehicle"] == name
        front = o[acc][:, [idx["wheel_speed_fl_mps"], idx["wheel_speed_fr_mps"]]].mean(axis=1)
        rear = o[acc][:, [idx["wheel_speed_rl_mps"], idx["wheel_speed_rr_mps"]]].mean(axis=1)
        return float(np.median(front / rear)), d

    fwd, _ = drive_ratio("compact_fwd")
    rwd, d_rwd = drive_ratio("rwd_sedan")
    assert fwd > 1.003 and rwd < 0.997  # the driven axle slips
    # the yaw rate is quantised at the car's own step (0.1 deg/s here, ReV-StED's 1.28 on the reference car)
    step = get_car("rwd_sedan").sensors.step(schema.SIGNAL_BY_NAME["yaw_rate_radps"])
    yaw = d_rwd.onboard[:, idx["yaw_rate_radps"]]
    assert step == pytest.approx(np.radians(0.1)) and np.allclose(yaw / step, np.round(yaw / step), atol=1e-6)
    with pytest.raises(ConfigError, match="unknown vehicle 'tesla'; the simulated fleet has reference"):
        simulate_drive(0.1, 1.0, seed=1, vehicle="tesla")


def test_highway_starts_at_speed_never_stops_and_stays_gentle():
    d = simulate_drive(2.0, 1.0, seed=1, family="highway", vehicle="compact_fwd")
    z = d.z_gt
    assert np.all(np.isfinite(d.onboard))
    assert z[0, 0] >= 14.0 and z[:, 0].min() > 10.0  # no standstill, from the first sample on
    assert np.abs(z[:, 3]).max() < 2.5 and np.degrees(np.abs(z[:, 4]).max()) < 6.0
    assert np.degrees(np.abs(z[:, 4]).max()) > 0.5  # it does bend: the curves are what calibrates
    assert "standstill" not in {name for _, name in d.meta["manoeuvres"]}
    for k, sig in enumerate(schema.SIGNALS):
        assert sig.min <= d.onboard[:, k].min() and d.onboard[:, k].max() <= sig.max


@pytest.mark.parametrize("family,mu", [("longitudinal", 1.0), ("lateral", 0.9), ("mixed", 1.0), ("snow", 0.3),
                                       ("highway", 1.0)])
def test_no_standstill_drive_never_stops_and_stays_within_physics(family, mu):
    d = simulate_drive(3.0, mu, seed=2, family=family, standstill=False)
    z = d.z_gt
    assert np.all(np.isfinite(z)) and np.all(np.isfinite(d.onboard))
    assert z[0, 0] >= 8.0 and z[:, 0].min() > 1.0 and z[:, 0].max() <= schema.V_MAX_MPS  # starts at speed, never 0
    wheels = d.onboard[:, [schema.SIGNAL_BY_NAME[n].index for n in schema.WHEEL_SPEED_NAMES]]
    assert wheels.min() > 1.0  # no wheel ever reads standstill: nothing calibrates a gyro at rest
    acc = np.hypot(z[:, 2], z[:, 3])
    assert np.percentile(acc, 99.5) <= mu * schema.G_MPS2 * 1.02
    assert np.abs(z[:, 4]).max() <= schema.OMEGA_MAX_RADPS
    assert np.percentile(np.abs(np.diff(z[:, 2])) / schema.DT_S, 99) < 15.0
    assert not {"standstill", "stop"} & {name for _, name in d.meta["manoeuvres"]}
    assert d.meta["standstill"] is False
    for k, sig in enumerate(schema.SIGNALS):
        assert sig.min <= d.onboard[:, k].min() and d.onboard[:, k].max() <= sig.max
    # the option leaves the default drive alone
    assert "standstill" not in simulate_drive(0.3, mu, seed=2, family=family).meta
