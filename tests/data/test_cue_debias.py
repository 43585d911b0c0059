"""Simulated drives with a_y and steering less the car's offsets: what a ``cue_debiased_inputs`` model trains on."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.data.cue_debias import AY_RESIDUAL_STD_MPS2, debiased_dataset, debiased_drive
from prml2_edge.data.datasets import generate_dataset, load_dataset
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import ConfigError

AY = schema.SIGNAL_BY_NAME["lat_accel_mps2"].index
STEER = schema.SIGNAL_BY_NAME["steering_wheel_angle_rad"].index
OTHERS = [i for i in range(schema.NUM_SIGNALS) if i not in (AY, STEER)]


def test_a_drive_less_its_simulated_offsets_reads_a_y_and_steering_as_the_truth_does():
    """Exact: a_y and the steering-wheel angle lose the drive's own offsets, nothing else moves and the drive given
    is untouched; with a generator each drive keeps a small residual of its own."""
    drive = simulate_drive(0.2, 1.0, 3, sensor_errors={"lat_offset_mps2": 0.3, "steer_offset_rad": np.radians(4.0)})
    raw = drive.onboard.copy()
    exact = debiased_drive(drive)
    np.testing.assert_array_equal(drive.onboard, raw)
    np.testing.assert_allclose(raw[:, AY] - exact.onboard[:, AY], 0.3, atol=1e-12)
    np.testing.assert_allclose(raw[:, STEER] - exact.onboard[:, STEER], np.radians(4.0), atol=1e-12)
    np.testing.assert_array_equal(exact.onboard[:, OTHERS], raw[:, OTHERS])
    # the truth: a_y's mean error over the drive is the sensor's white noise and lag, not the 0.3 offset
    assert abs(np.mean(exact.onboard[:, AY] - drive.z_gt[:, schema.Z.A_Y])) < 0.02 < 0.3
    resid = debiased_drive(drive, np.random.default_rng(1)).onboard[:, AY] - exact.onboard[:, AY]
    assert np.ptp(resid) < 1e-12 and 0 < abs(resid[0]) < 4 * AY_RESIDUAL_STD_MPS2


def test_a_drive_without_simulated_offsets_is_refused_by_name():
    drive = simulate_drive(0.1, 1.0, 4)
    drive.meta.pop("sensor_errors")
    with pytest.raises(ConfigError, match=r"^sim_mixed_s4: no simulated a_y and steering offsets"):
        debiased_drive(drive)


def test_a_debiased_dataset_builds_its_splits_from_the_new_drives(tmp_path):
    recipe = {"name": "deb", "drives": [{"name": "dry_a", "family": "mixed", "mu": 1.0, "seed": 5, "minutes": 0.5,
                                         "role": "dry"}]}
    data = load_dataset(generate_dataset(tmp_path / "data", recipe, workers=1, progress=False))
    raw = data.split("train")[0].onboard
    new = debiased_dataset(data, seed=0)
    shift = raw[:, AY] - new.split("train")[0].onboard[:, AY]
    offset = data.drives[0].meta["sensor_errors"]["lat_offset_mps2"]
    assert np.ptp(shift) < 1e-12 and abs(shift[0] - offset) < 4 * AY_RESIDUAL_STD_MPS2
    np.testing.assert_array_equal(data.split("train")[0].onboard, raw)  # the loaded dataset is left as it was
