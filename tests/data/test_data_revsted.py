"""ReV-StED loader: the real sample, SI conversion, repairs that are counted, errors that name file/column/row."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.data.revsted import MAX_HELD_NONFINITE, load_drive, write_drive_csv
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.errors import DataError

HEADER = ("INS_time_sec,LatAcc_obd,brake_pressure_obd,speedo_obd,SW_pos_obd,"
          "VelFR_obd,VelFL_obd,VelRR_obd,VelRL_obd,yaw_rate")


def _csv(tmp_path, rows, header=HEADER, name="drive.csv"):
    p = tmp_path / name
    p.write_text(header + "\n" + "\n".join(rows) + "\n")
    return p


def _rows(n=20, t0=100.0, dt=0.02):
    return [f"{t0 + i * dt:.2f},0.5,1.0,36.0,10.0,35.0,35.0,35.0,35.0,2.56" for i in range(n)]


def test_real_obd_sample_loads_onboard_only(shared_dir):
    drive = load_drive(shared_dir / "data/revsted/OBD_Sample.csv")
    assert len(drive) == 999
    assert drive.onboard.shape == (999, schema.NUM_SIGNALS)
    assert not drive.has_ground_truth and drive.z_gt is None and drive.pose_gt is None
    assert drive.repairs == {}
    idx = {s.name: s.index for s in schema.SIGNALS}
    # first row: speedo 20.875 km/h, SW 54.863 deg, yaw_rate 6.4 deg/s (alias), FL 19.55 km/h
    assert drive.onboard[0, idx["speedometer_mps"]] == pytest.approx(20.875 / 3.6)
    assert drive.onboard[0, idx["steering_wheel_angle_rad"]] == pytest.approx(np.radians(54.863))
    assert drive.onboard[0, idx["yaw_rate_radps"]] == pytest.approx(np.radians(6.4))
    assert drive.onboard[0, idx["wheel_speed_fl_mps"]] == pytest.approx(19.55 / 3.6)
    # LatAcc_obd is right-positive in ReV-StED; the schema is left-positive (see schema.py)
    assert drive.onboard[0, idx["lat_accel_mps2"]] == pytest.approx(0.675)
    with pytest.raises(DataError, match="ground truth required"):
        load_drive(shared_dir / "data/revsted/OBD_Sample.csv", require_ground_truth=True)


def test_simulated_csv_round_trips_with_ground_truth(tmp_path):
    drive = simulate_drive(0.5, 1.0, seed=3, family="mixed")
    write_drive_csv(drive, tmp_path / "sim.csv")
    back = load_drive(tmp_path / "sim.csv", require_ground_truth=True)
    assert back.has_ground_truth and back.repairs == {}
    assert back.meta["seed"] == 3 and back.meta["family"] == "mixed"
    steps = np.array([s.revsted_step for s in schema.SIGNALS])
    assert np.all(np.abs(back.onboard - drive.onboard) <= 1e-3 * steps)
    assert np.allclose(back.z_gt, drive.z_gt, atol=1e-5)
    assert np.allclose(back.pose_gt[:, :2], drive.pose_gt[:, :2], atol=1e-4)
    # ins_yaw is written wrapped to [0, 360); the loader unwraps psi again
    dpsi = back.pose_gt[:, 2] - drive.pose_gt[:, 2]
    assert np.allclose(dpsi - dpsi[0], 0.0, atol=1e-6)
    assert abs(dpsi[0] / (2 * np.pi) - round(dpsi[0] / (2 * np.pi))) < 1e-6


def test_single_missing_sample_is_inserted_and_counted(tmp_path):
    rows = _rows(20)
    del rows[7]
    drive = load_drive(_csv(tmp_path, rows))
    assert len(drive) == 20
    assert drive.repairs == {"gap_rows_inserted": 1}
    assert np.allclose(np.diff(drive.t_s), 0.02)


def test_long_gap_names_file_column_and_row(tmp_path):
    rows = _rows(20)
    del rows[7:10]
    with pytest.raises(DataError, match=r"drive\.csv: column 'INS_time_sec' row 8: time step of 80\.0 ms"):
        load_drive(_csv(tmp_path, rows))


def test_non_monotonic_time_names_the_row(tmp_path):
    rows = _rows(20)
    rows[5], rows[6] = rows[6], rows[5]
    with pytest.raises(DataError, match=r"row 7: time .* does not increase"):
        load_drive(_csv(tmp_path, rows))


def test_short_nan_runs_are_held_and_counted(tmp_path):
    rows = _rows(20)
    for i in (4, 5):
        f = rows[i].split(",")
        f[4] = "nan" if i == 4 else ""
        rows[i] = ",".join(f)
    drive = load_drive(_csv(tmp_path, rows))
    assert drive.repairs == {"nonfinite_held:SW_pos_obd": 2}
    assert np.all(np.isfinite(drive.onboard))


def test_long_nan_run_names_column_and_rows(tmp_path):
    rows = _rows(20)
    for i in range(3, 4 + MAX_HELD_NONFINITE):
        f = rows[i].split(",")
        f[9] = "inf"
        rows[i] = ",".join(f)
    with pytest.raises(DataError, match=r"column 'yaw_rate' rows 4-9: 6 consecutive non-finite"):
        load_drive(_csv(tmp_path, rows))


def test_text_in_a_cell_names_the_row(tmp_path):
    rows = _rows(10)
    rows[3] = rows[3].replace(",36.0,", ",fast,")
    with pytest.raises(DataError, match=r"column 'speedo_obd' row 4: 'fast' is not a number"):
        load_drive(_csv(tmp_path, rows))


def test_missing_column_and_partial_ground_truth(tmp_path):
    header = HEADER.replace(",yaw_rate", ",other")
    with pytest.raises(DataError, match=r"missing onboard column 'Yawrate_obd' \(or yaw_rate\)"):
        load_drive(_csv(tmp_path, _rows(5), header=header))
    rows = [r + ",1.0,0.0" for r in _rows(5)]
    with pytest.raises(DataError, match=r"lacks acc_hor_x"):
        load_drive(_csv(tmp_path, rows, header=HEADER + ",INS_velCOG_hor_x,INS_velCOG_hor_y", name="p.csv"))


def test_wrong_sample_rate_is_refused(tmp_path):
    with pytest.raises(DataError, match="must be at 50 Hz"):
        load_drive(_csv(tmp_path, _rows(10, dt=0.01)))


def test_slice_keeps_alignment():
    drive = simulate_drive(0.2, 1.0, seed=1)
    part = drive.slice(100, 250)
    assert len(part) == 150 and part.has_ground_truth
    assert np.array_equal(part.onboard, drive.onboard[100:250])
    assert part.meta["slice"] == [100, 250]
