"""evo, for real (issue 19): its APE on the TUM files of `prml2 evaluate` and `prml2 replay` equals our RMSE."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("evo")  # the dev extra
from evo.core import metrics, sync  # noqa: E402
from evo.tools import file_interface  # noqa: E402

from prml2_edge.can.encode import encode_drive_to_log  # noqa: E402
from prml2_edge.cli.main import main  # noqa: E402
from prml2_edge.data.datasets import generate_dataset  # noqa: E402
from prml2_edge.data.revsted import write_drive_csv  # noqa: E402
from prml2_edge.data.simulate import simulate_drive  # noqa: E402
from prml2_edge.ekf.numpy_ekf import wrap_angle  # noqa: E402
from prml2_edge.evaluation.tum import write_tum  # noqa: E402
from tests.evaluation.test_eval import RECIPE, WINDOW_S  # noqa: E402
from tests.runtime_models import make_kinematic_model  # noqa: E402

MM = 1e-3


def evo_ape_rmse(ref_path, est_path, t_from: float | None = None) -> tuple[float, int]:
    """evo's APE (translation part, no alignment, as `evo_ape tum REF EST`) RMSE [m] and the poses it compared."""
    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    if t_from is not None:
        ref.reduce_to_time_range(t_from)
        est.reduce_to_time_range(t_from)
    ref, est = sync.associate_trajectories(ref, est)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse)), ref.num_poses


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("evo")
    data = generate_dataset(root / "data", RECIPE, workers=1, progress=False)
    model = make_kinematic_model(root / "kinematic.onnx")
    out = root / "report"
    assert main(["evaluate", "--data", str(data), "--models", f"PRML2={model}", "--out", str(out), "--window-s",
                 str(WINDOW_S), "--max-windows", "1", "--calibration", "off", "--no-plots"]) == 0
    return out, json.loads((out / "metrics.json").read_text())


def test_evo_ape_equals_the_evaluation_reports_rmse_on_3_windows(report):
    out, m = report
    windows = m["tum_windows"]["PRML2"]
    assert len(windows) == 3  # two dry test windows, one snow window
    rmse = {}
    for w in windows:
        got, n = evo_ape_rmse(out / w["groundtruth"], out / w["estimate"])
        assert n == round(WINDOW_S / 0.02)  # every step compared: no timestamp was lost or mismatched
        assert abs(got - w["rmse_m"]) < MM, w
        rmse.setdefault(w["window"].split("/")[0], []).append(got)
    # ... and their means are the report's Table 2 numbers
    dr = {split: m["models"]["PRML2"][split]["dead_reckoning_60s"] for split in ("test", "snow")}
    assert abs(np.mean(rmse["test"]) - dr["test"]["rmse_mean_m"]) < MM and dr["test"]["n_windows"] == 2
    assert abs(rmse["snow"][0] - dr["snow"]["rmse_mean_m"]) < MM and dr["snow"]["n_windows"] == 1
    assert max(max(v) for v in rmse.values()) > 0.01  # the windows do have an error to measure


def test_tum_timestamps_keep_microseconds_at_unix_epoch_times(tmp_path):
    """A real car's CAN log carries Unix times (~1.7e9 s): evo must still see every 20 ms step apart."""
    t = 1.7e9 + 0.123456 + 0.02 * np.arange(500)
    pose = np.column_stack([np.arange(500.0), np.zeros(500), np.linspace(-3.0, 3.0, 500)])
    path = write_tum(tmp_path / "epoch.txt", t, pose)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.timestamps, t, rtol=0, atol=2e-6)
    shifted = write_tum(tmp_path / "shifted.txt", t + 0.0004, pose + [0.5, 0.0, 0.0])
    got, n = evo_ape_rmse(path, shifted)
    assert n == 500 and abs(got - 0.5) < MM


def test_evo_ape_equals_replay_truth_rmse_and_reads_our_heading(tmp_path):
    drive = simulate_drive(0.5, 1.0, 11)  # 30 s, GNSS for 8 s then an outage
    drive_csv = tmp_path / "drive.csv"
    write_drive_csv(drive, drive_csv)
    encode_drive_to_log(drive, tmp_path / "drive.log", gnss_seconds=8.0)
    model = make_kinematic_model(tmp_path / "kinematic.onnx")
    assert main(["replay", str(tmp_path / "drive.log"), "--model", str(model), "--tum", str(tmp_path / "pose.tum"),
                 "--jsonl", str(tmp_path / "pose.jsonl"), "--truth", str(drive_csv),
                 "--truth-tum", str(tmp_path / "truth.tum"), "--summary-json", str(tmp_path / "s.json")]) == 0
    truth = json.loads((tmp_path / "s.json").read_text())["truth"]
    got, n = evo_ape_rmse(tmp_path / "truth.tum", tmp_path / "pose.tum", t_from=truth["outage_start_s"])
    assert n > 1000 and truth["rmse_m"] > 0.05
    assert abs(got - truth["rmse_m"]) < MM, (got, truth["rmse_m"])
    # TUM is `qx qy qz qw`, evo keeps (w, x, y, z): the yaw evo reads is the runtime's psi and the true heading
    records = {round(r["t_s"], 6): r for r in map(json.loads, (tmp_path / "pose.jsonl").read_text().splitlines())}
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "pose.tum"))
    psi = np.array([records[round(t, 6)]["psi_rad"] for t in est.timestamps])
    assert np.max(np.abs(wrap_angle(est.get_orientations_euler()[:, 2] - psi))) < 1e-6
    assert np.ptp(np.unwrap(psi)) > 0.5  # the drive turns, so a swapped order would show
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "truth.tum"))
    k = np.rint((ref.timestamps - drive.t_s[0]) / 0.02).astype(int)
    assert np.max(np.abs(wrap_angle(ref.get_orientations_euler()[:, 2] - drive.pose_gt[k, 2]))) < 1e-6
    assert main(["replay", str(tmp_path / "drive.log"), "--model", str(model), "--truth-tum", "x.tum"]) == 1
