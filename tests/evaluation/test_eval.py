"""Evaluation protocol (issue 5): one streaming code path, metrics, report, TUM files, the CLI."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.cli.main import main
from prml2_edge.data.datasets import generate_dataset, load_dataset
from prml2_edge.ekf.numpy_ekf import Ekf, default_initial_covariance
from prml2_edge.evaluation.metrics import dr_summary, paired_comparison, z_rmse
from prml2_edge.evaluation.protocol import ModelSpec, WindowResult, run_window, split_tasks
from prml2_edge.evaluation.tum import read_tum, write_tum
from prml2_edge.schema import EkfState
from tests.runtime_models import KINEMATIC_STD, kinematic_weights, make_kinematic_model

WINDOW_S = 4.0  # short dead-reckoning windows keep the drives (and the test) tiny
RECIPE = {"name": "eval-tiny", "drives": [
    {"name": "dry_a", "family": "mixed", "mu": 1.0, "seed": 5, "minutes": 0.8, "role": "dry"},
    {"name": "dry_b", "family": "lateral", "mu": 0.9, "seed": 6, "minutes": 0.8, "role": "dry"},
    {"name": "snow_a", "family": "snow", "mu": 0.3, "seed": 7, "minutes": 0.3, "role": "snow"},
]}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    data = generate_dataset(root / "data", RECIPE, workers=1, progress=False)
    model = make_kinematic_model(root / "kinematic.onnx")
    return data, model


def test_windows_are_non_overlapping_and_have_history(tiny):
    data, _ = tiny
    ds = load_dataset(data)
    tasks = split_tasks(ds, "test", WINDOW_S)
    steps = int(WINDOW_S / schema.DT_S)
    assert len(tasks) == 4  # a 9.6 s test split per dry drive holds two 4 s windows
    for t in tasks:
        assert t.onboard.shape == (schema.WINDOW_LEN - 1 + steps, schema.NUM_SIGNALS)
        assert t.pose_gt.shape == (steps, 3)
    by_drive = {}
    for t in tasks:
        by_drive.setdefault(t.drive, []).append(t.start)
    for starts in by_drive.values():
        assert all(b - a >= steps for a, b in zip(starts, starts[1:], strict=False))


def test_run_window_matches_a_hand_written_ekf_loop(tiny):
    """The localiser path (window -> ONNX -> guard -> EKF) equals feeding the NumPy EKF the model's z by hand."""
    data, model = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S)[0]
    res = run_window(ModelSpec("kin", "onnx", str(model)), task)
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.POS] = task.pose_gt[0, :2]
    x0[EkfState.YAW] = task.pose_gt[0, 2]
    x0[list(schema.Z_TO_EKF_INDEX)] = task.z_gt[0]
    from prml2_edge.ekf.numpy_ekf import default_process_noise

    ekf = Ekf(x0, default_initial_covariance(), default_process_noise(schema.DT_S), schema.DT_S)
    z_all = task.onboard.astype(np.float32).astype(np.float64) @ kinematic_weights().astype(np.float64)
    var = np.square(KINEMATIC_STD)
    errors = [0.0]
    for k in range(1, len(task.t_s)):
        ekf.step(z_all[task.history + k], var)
        errors.append(math.hypot(ekf.x[0] - task.pose_gt[k, 0], ekf.x[1] - task.pose_gt[k, 1]))
    np.testing.assert_allclose(res.pos_error_m, errors, atol=1e-3)
    assert res.model_steps == len(task.t_s) - 1
    # Table 1 uses exactly the z the EKF consumed
    np.testing.assert_allclose(res.z, z_all[task.history:], atol=1e-4)


def test_guard_ablation_changes_a_model_that_violates_the_friction_circle(tiny, tmp_path):
    data, _ = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S)[0]
    bad = make_kinematic_model(tmp_path / "bad.onnx", bias=np.array([0.0, 0.0, 15.0, 0.0, 0.0]))
    on = run_window(ModelSpec("on", "onnx", str(bad)), task)
    off = run_window(ModelSpec("off", "onnx", str(bad), guard=False), task)
    assert on.guard_fired > 0 and off.guard_fired == 0
    assert on.model_steps == off.model_steps == len(task.t_s) - 1
    assert np.max(np.abs(on.z[:, schema.Z.A_X])) <= 10.0 + 1e-6
    assert np.max(np.abs(off.z[:, schema.Z.A_X])) > 14.0
    assert not np.allclose(on.pos_error_m, off.pos_error_m)


def test_metrics_on_known_errors():
    err = np.linspace(0.0, 3.0, 4)  # 0, 1, 2, 3 m
    r = WindowResult("m", "k", "test", np.zeros((4, 3)), err, np.zeros(4), 100.0, np.zeros((4, 5)))
    assert r.rmse_m == pytest.approx(math.sqrt(14 / 4))
    assert r.max_error_m == 3.0 and r.drift_pct == pytest.approx(3.0)
    s = dr_summary([r, r])
    assert s["n_windows"] == 2 and s["rmse_std_m"] == 0.0 and s["drift_mean_pct"] == pytest.approx(3.0)


def _result(key: str, rmse: float) -> WindowResult:
    err = np.full(3, rmse)
    return WindowResult("m", key, "test", np.zeros((3, 3)), err, np.zeros(3), 100.0, np.zeros((3, 5)))


def test_paired_comparison_separates_a_real_gap_from_the_spread():
    rng = np.random.default_rng(1)
    base = rng.uniform(2.0, 20.0, 30)  # windows differ by far more than the models do
    ref = [_result(f"w{i}", b) for i, b in enumerate(base)]
    better = paired_comparison(ref, [_result(f"w{i}", b + 1.0) for i, b in enumerate(base)])
    assert better["n_windows"] == 30 and better["reference_wins"] == 1.0
    assert better["rmse_diff_mean_m"] == pytest.approx(1.0)
    lo, hi = better["rmse_diff_ci95_m"]
    assert lo == pytest.approx(1.0) and hi == pytest.approx(1.0)  # the same gap on every window
    assert better["rmse_ratio"] < 1.0 and better["rmse_ratio_ci95"][1] < 1.0
    noise = rng.normal(0.0, 3.0, 30)
    tie = paired_comparison(ref, [_result(f"w{i}", b + n) for i, (b, n) in enumerate(zip(base, noise, strict=True))])
    lo, hi = tie["rmse_diff_ci95_m"]
    assert lo < tie["rmse_diff_mean_m"] < hi and lo < 0.0 < hi  # no real gap: the interval holds 0
    # only windows both models ran are paired
    assert paired_comparison(ref[:5], ref[3:])["n_windows"] == 2
    assert paired_comparison(ref[:2], ref[2:4]) == {"n_windows": 0}


def test_tum_round_trip(tmp_path):
    t = np.arange(5) * 0.02
    pose = np.column_stack([np.arange(5.0), -np.arange(5.0), np.linspace(-3.0, 3.0, 5)])
    t2, pose2 = read_tum(write_tum(tmp_path / "a.txt", t, pose))
    np.testing.assert_allclose(t2, t)
    np.testing.assert_allclose(pose2, pose, atol=1e-4)
    line = (tmp_path / "a.txt").read_text().splitlines()[0].split()
    assert len(line) == 8  # timestamp x y z qx qy qz qw


def test_cli_writes_tables_metrics_plots_and_tum(tiny, tmp_path, capsys):
    data, model = tiny
    out = tmp_path / "report"
    rc = main(["evaluate", "--data", str(data), "--models", "osd", f"PRML2={model}", "--out", str(out),
               "--window-s", str(WINDOW_S), "--max-windows", "1"])
    assert rc == 0
    report = (out / "report.md").read_text()
    for title in ("Table 1", "Table 2", "Table 3"):
        assert title in report
    metrics = json.loads((out / "metrics.json").read_text())
    # every model with and without the filter's calibration (default --calibration both)
    assert set(metrics["models"]) == {"OSD-Baseline", "PRML2", "OSD-Baseline +cal", "PRML2 +cal"}
    assert metrics["specs"]["PRML2 +cal"]["calibration"] and not metrics["specs"]["PRML2"]["calibration"]
    # the deployment protocol (GNSS pre-roll, then the outage) and the coverage of the reported ellipses
    dep = metrics["models"]["PRML2 +cal"]["deployment"]
    assert dep["dead_reckoning_60s"]["n_windows"] >= 1 and "calibration_at_outage" in dep
    assert 0.0 <= metrics["models"]["PRML2"]["test"]["dead_reckoning_60s"]["coverage_2sigma_pct"] <= 100.0
    assert "Table 2c" in report
    dry = metrics["models"]["PRML2"]["test"]
    assert dry["dead_reckoning_60s"]["n_windows"] == 2
    assert metrics["models"]["PRML2"]["snow"]["dead_reckoning_60s"]["n_windows"] == 1
    assert metrics["models"]["OSD-Baseline"]["test"]["z_rmse"]["v_y_mps"] is None  # a dash in Table 1
    assert [r["guard"] for r in metrics["ablation"]["rows"]] == [False, False, True]
    pair = metrics["paired"]["test"]["OSD-Baseline"]
    assert metrics["paired"]["reference"] == "PRML2" and pair["n_windows"] == 2
    assert "Table 2b" in report
    assert metrics["tuning"]["OSD-Baseline"]["q_scale"] > 0
    for fig in metrics["figures"]:
        assert (out / fig).stat().st_size > 1000
    gt = sorted((out / "tum" / "groundtruth").glob("*.txt"))
    est = sorted((out / "tum" / "PRML2").glob("*.txt"))
    assert len(gt) == 3 and [p.name for p in est] == [p.name for p in gt]
    assert "PRML2" in capsys.readouterr().out


def test_z_rmse_ignores_missing_components(tiny):
    data, _ = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S)[0]
    res = run_window(ModelSpec("osd", "osd"), task)
    z, n = z_rmse([res], [task])
    assert z["v_y_mps"] is None and z["a_x_mps2"] is None and z["v_x_mps"] is not None
    assert n == len(task.t_s)


def test_noise_grid_is_extended_until_its_minimum_is_inside():
    from prml2_edge.evaluation.tuning import _extend_grid

    calls = []

    def loss(q):  # minimum at q = 1000, past the top of the grid
        calls.append(q)
        return (np.log10(q) - 3.0) ** 2

    scores = {q: loss(q) for q in (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)}
    best, inside = _extend_grid(scores, loss)
    assert inside and best == pytest.approx(100.0 * (100 / 30) ** 2)  # 100 -> 333 -> 1111 (-> 3704, worse)
    assert max(scores) > best and len(calls) > 6
    flat = {q: 1.0 for q in (1.0, 10.0, 100.0)}
    flat[1.0] = 0.5  # falls forever towards 0: extended MAX_GRID_EXTENSIONS times, then reported as not inside
    best, inside = _extend_grid(flat, lambda q: 0.5 - 1.0 / (1.0 + q))
    assert not inside and best == min(flat)


def test_evaluate_without_matplotlib_says_so_in_one_line_and_writes_everything_else(tiny, tmp_path):
    import subprocess
    import sys

    data, model = tiny
    out = tmp_path / "report"
    code = ("import sys; sys.modules['matplotlib'] = None\n"
            "from prml2_edge.cli.main import main\n"
            f"sys.exit(main(['evaluate', '--data', {str(data)!r}, '--models', 'PRML2={model}', '--out', {str(out)!r}, "
            f"'--window-s', '{WINDOW_S}', '--max-windows', '1', '--calibration', 'off']))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={"PRML2_NO_PROGRESS": "1", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    hint = [line for line in (proc.stdout + proc.stderr).splitlines() if "matplotlib" in line]
    assert len(hint) == 1 and "'.[plot]'" in hint[0], proc.stdout + proc.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["figures"] == [] and not list(out.glob("*.png"))
    assert (out / "report.md").is_file() and len(list((out / "tum" / "PRML2").glob("*.txt"))) == 3


def test_per_vehicle_breakdown_says_on_which_car_a_model_helps(tmp_path):
    from prml2_edge.evaluation.run import evaluate

    recipe = {"name": "eval-two-cars", "drives": [
        {"name": "ref_a", "family": "mixed", "mu": 1.0, "seed": 5, "minutes": 0.8, "role": "dry",
         "vehicle": "reference"},
        {"name": "city_a", "family": "lateral", "mu": 0.9, "seed": 6, "minutes": 0.8, "role": "dry",
         "vehicle": "city_fwd"},
    ]}
    data = generate_dataset(tmp_path / "data", recipe, workers=1, progress=False)
    model = make_kinematic_model(tmp_path / "kinematic.onnx")
    specs = [ModelSpec("OSD-Baseline", "osd"), ModelSpec("PRML2", "onnx", str(model))]
    metrics = evaluate(data, specs, tmp_path / "rep", window_s=WINDOW_S, snow=False, tum=False, plots=False,
                       calibration="off", preroll_s=2.0, progress=False)
    per = metrics["per_vehicle"]["test"]
    assert set(per) == {"reference", "city_fwd"}
    for name in ("OSD-Baseline", "PRML2"):  # the cars' windows add up to the split's
        total = metrics["models"][name]["test"]["dead_reckoning_60s"]["n_windows"]
        assert sum(per[car][name]["n_windows"] for car in per) == total == 4
        assert per["city_fwd"][name]["rmse_mean_m"] != per["reference"][name]["rmse_mean_m"]
    report = (tmp_path / "rep" / "report.md").read_text()
    row = next(ln for ln in report.splitlines() if ln.startswith("| test | city_fwd | PRML2 |"))
    ratio = per["city_fwd"]["PRML2"]["rmse_mean_m"] / per["city_fwd"]["OSD-Baseline"]["rmse_mean_m"]
    assert f"| {ratio:.2f} |" in row
    dep = metrics["per_vehicle"]["deployment"]  # the deployment protocol's windows, by car too
    assert set(dep) == {"reference", "city_fwd"}
    assert sum(dep[car]["PRML2"]["n_windows"] for car in dep) == \
        metrics["models"]["PRML2"]["deployment"]["dead_reckoning_60s"]["n_windows"]
    assert any(ln.startswith("| deployment | city_fwd | PRML2 |") for ln in report.splitlines())


def test_filter_variants_replay_the_models_outputs_exactly(tiny):
    """A model's z does not depend on the filter: replaying the recorded outputs gives the pose the model gives,
    and a filter override (a ModelSpec's ``filter``) reaches the localiser."""
    from dataclasses import replace

    from prml2_edge.evaluation.models import RecordingModel, ReplayModel
    from prml2_edge.evaluation.protocol import build_model

    data, model = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S)[0]
    spec = ModelSpec("kin", "onnx", str(model), calibration=True)
    rec = RecordingModel(build_model(spec, task.bias))
    direct = run_window(spec, task, model=rec)
    replayed = run_window(spec, task, model=ReplayModel(rec.records, rec.metadata))
    np.testing.assert_array_equal(replayed.pose, direct.pose)
    assert replayed.z_var is not None and np.isfinite(replayed.z_var[1:]).all()
    no_cues = run_window(replace(spec, filter=(("cue_min_speed_mps", 1e9), ("substitute_yaw_cue", False))), task,
                         model=ReplayModel(rec.records, rec.metadata))
    assert not np.array_equal(no_cues.pose, direct.pose)
    silent = run_window(spec, task, model=ReplayModel([], rec.metadata))  # nothing recorded: no model step
    assert silent.model_steps == 0


def test_calibration_on_keeps_the_osd_reference_and_runs_table_3_through_the_same_filter(tiny, tmp_path):
    """``--calibration on``: the learned model through the calibrating filter, OSD as the paper's baseline (the
    reference of every ratio), and Table 3's guard-less variants through the calibrating filter too: the guard
    never fires on this model, so "no guard" is the full model's row to the metre."""
    data, model = tiny
    out = tmp_path / "report"
    rc = main(["evaluate", "--data", str(data), "--models", "osd", f"PRML2={model}", "--out", str(out),
               "--window-s", str(WINDOW_S), "--max-windows", "1", "--calibration", "on", "--preroll-s", "0",
               "--no-tum", "--no-plots"])
    assert rc == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["models"]) == {"OSD-Baseline", "PRML2"}
    assert metrics["specs"]["PRML2"]["calibration"] and not metrics["specs"]["OSD-Baseline"]["calibration"]
    rows = {(r["guard"], r["uncertainty"]): r["dead_reckoning_60s"] for r in metrics["ablation"]["rows"]}
    assert rows[(True, True)]["guard_fire_rate"] == 0.0
    assert rows[(False, True)]["rmse_mean_m"] == pytest.approx(rows[(True, True)]["rmse_mean_m"], abs=1e-9)


def test_a_filter_override_wins_over_the_protocols_receiver_settings(tiny):
    """The deployment protocol sets the receiver's heading speed; an ablation that switches heading fixes off
    overrides it (it used to raise 'multiple values for keyword argument'), and the pre-roll then fuses positions
    only, which changes the pose."""
    from dataclasses import replace

    from prml2_edge.evaluation.models import RecordingModel, ReplayModel
    from prml2_edge.evaluation.protocol import build_model

    data, model = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S, preroll_s=2.0)[0]
    spec = ModelSpec("kin", "onnx", str(model), calibration=True)
    rec = RecordingModel(build_model(spec, task.bias))
    with_heading = run_window(spec, task, model=rec)
    no_heading = run_window(replace(spec, filter=(("gnss_heading_min_speed_mps", 1e9),)), task,
                            model=ReplayModel(rec.records, rec.metadata))
    assert np.isfinite(no_heading.pose).all()
    assert not np.array_equal(no_heading.pose, with_heading.pose)


def test_the_deployment_fixes_carry_the_course_over_ground(tiny):
    """A single-antenna receiver gives the direction of travel, not the yaw: each of the protocol's fixes is the
    true course psi + atan2(v_y, v_x) plus its drawn noise (the generator redrawn with the task's seed)."""
    import zlib

    from prml2_edge.evaluation.protocol import simulated_fixes
    from prml2_edge.schema import heading_deg_to_psi_rad

    data, _ = tiny
    task = split_tasks(load_dataset(data), "test", WINDOW_S, preroll_s=2.0)[0]
    rng = np.random.default_rng(zlib.crc32(task.key.encode()))
    beta, checked = [], 0
    for row, fix in sorted(simulated_fixes(task).items()):
        j = row - task.history
        rng.normal(0.0, 1.5, 2)  # the position's noise
        noise = math.radians(rng.normal(0.0, 2.0))
        if fix.heading_deg is None:
            continue
        vx, vy = task.pre_z_gt[j, 0], task.pre_z_gt[j, 1]
        course = task.pre_pose_gt[j, 2] + math.atan2(vy, vx)
        err = math.remainder(heading_deg_to_psi_rad(fix.heading_deg) - course - noise, 2 * math.pi)
        assert abs(err) < 1e-7
        beta.append(abs(math.atan2(vy, vx)))
        checked += 1
    assert checked >= 10 and max(beta) > 1e-5  # the sideslip (100x the tolerance) tells the course from the yaw


def test_filter_override_parses_a_field_and_says_what_is_wrong_in_one_line():
    from prml2_edge.evaluation.protocol import filter_override

    assert filter_override("scale_min_speed_mps=1e9") == ("scale_min_speed_mps", 1e9)
    with pytest.raises(ValueError, match="LocalizerConfig field"):
        filter_override("no_such_field=1")
    with pytest.raises(ValueError, match="must be a number"):
        filter_override("scale_min_speed_mps=fast")
    with pytest.raises(ValueError, match="cue_offset_floor_radps must be >= 0"):  # refused before any window runs
        filter_override("cue_offset_floor_radps=-1")
    with pytest.raises(ValueError, match="cal_yaw_offset_psd must be a finite number >= 0"):
        filter_override("cal_yaw_offset_psd=-1e-10")


def test_the_low_mu_inflation_is_for_the_learned_model_not_the_osd_baseline():
    """On snow the runtime inflates the model's variance (it was trained on dry roads); OSD's noise was tuned on
    validation as it is, so the evaluation runs it without the inflation (an override still wins)."""
    from prml2_edge.evaluation.protocol import _localizer_config

    task = SimpleNamespace(mu=0.3, preroll=0, vehicle="")
    assert _localizer_config(ModelSpec("OSD", "osd"), task, 1).low_mu_model_var_scale == 1.0
    assert _localizer_config(ModelSpec("m", "onnx", "m.onnx"), task, 1).low_mu_model_var_scale == 10.0
    spec = ModelSpec("OSD", "osd", filter=(("low_mu_model_var_scale", 3.0),))
    assert _localizer_config(spec, task, 1).low_mu_model_var_scale == 3.0


def test_only_a_calibrated_learned_model_reads_its_inputs_less_the_cues_offsets(tmp_path):
    """``model_inputs_from_cues``, or a model trained on such rows (``cue_debiased_inputs``), changes what the model
    reads, so a benchmark must not replay one way's outputs for the other (benchmarks/filter_ablation.py): it needs
    the calibrating filter's cue estimator, and the OSD baseline always integrates the raw values."""
    from prml2_edge.evaluation.protocol import _localizer_config, model_reads_cues

    m = str(make_kinematic_model(tmp_path / "m.onnx"))
    trained = str(make_kinematic_model(tmp_path / "d.onnx", meta_overrides={"config": {"cue_debiased_inputs": True}}))
    on = (("model_inputs_from_cues", 1.0),)
    assert not model_reads_cues(ModelSpec("m", "onnx", m, calibration=True))
    assert model_reads_cues(ModelSpec("m", "onnx", m, calibration=True, filter=on))
    assert model_reads_cues(ModelSpec("d", "onnx", trained, calibration=True))
    assert not model_reads_cues(ModelSpec("d", "onnx", trained))  # the paper filter: no cue estimator
    assert not model_reads_cues(ModelSpec("m", "onnx", m, calibration=True, filter=on + (("cue_offset", 0.0),)))
    assert not model_reads_cues(ModelSpec("m", "onnx", m, filter=on))
    assert not model_reads_cues(ModelSpec("OSD", "osd", calibration=True, filter=on))
    task = SimpleNamespace(mu=1.0, preroll=0, vehicle="")
    assert not _localizer_config(ModelSpec("OSD", "osd", calibration=True), task, 1).model_inputs_from_cues


def test_a_fleet_cars_drive_runs_with_its_driven_axle_and_steering_ratio():
    """A user tells the runtime the car's driven axle; the evaluation does the same for the fleet's cars (the RWD
    sedan's wheel cue from its front axle), a car it does not know keeps the defaults, and an ablation's override
    wins."""
    from prml2_edge.data.simulate.fleet import CARS
    from prml2_edge.evaluation.protocol import _localizer_config

    spec = ModelSpec("m", "onnx", "m.onnx")
    cfg = _localizer_config(spec, SimpleNamespace(mu=1.0, preroll=0, vehicle="rwd_sedan"), 1)
    assert (cfg.driven_axle, cfg.steering_ratio) == ("rear", CARS["rwd_sedan"].params.steering_ratio)
    assert _localizer_config(spec, SimpleNamespace(mu=1.0, preroll=0, vehicle="suv_awd"), 1).driven_axle == "all"
    assert _localizer_config(spec, SimpleNamespace(mu=1.0, preroll=0, vehicle=""), 1).driven_axle == "front"
    rear_cue = ModelSpec("m", "onnx", "m.onnx", filter=(("driven_axle", "front"),))
    assert _localizer_config(rear_cue, SimpleNamespace(mu=1.0, preroll=0, vehicle="rwd_sedan"), 1).driven_axle \
        == "front"


def test_a_window_mid_drive_starts_from_the_cue_estimator_the_drive_so_far_taught(tmp_path):
    """The runtime's cue estimator has run over the drive before a window starts: each task keeps the drive's rows
    before its own, and a spec replays them (with the task's history rows) into the estimator, as a runtime that had
    run since the drive's start would hold it; with ``cue_drive_so_far`` off (before) the window starts cold."""
    from dataclasses import replace

    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.evaluation.protocol import InMemorySplits, localizer_for
    from prml2_edge.runtime.cue_offset import CueOffset

    drive = simulate_drive(2.5, 1.0, 4242, "mixed", name="so_far", vehicle="compact_fwd", standstill=False)
    model = make_kinematic_model(tmp_path / "k.onnx")
    tasks = split_tasks(InMemorySplits({"test": [drive]}), "test", preroll_s=10.0)
    assert len(tasks) == 2
    for task in tasks:  # the rows before the task's own, then its own: the drive as it was
        whole = np.concatenate([task.before, task.onboard])
        assert np.array_equal(whole, drive.onboard[: len(whole)])
    spec = ModelSpec("kin", "onnx", str(model), calibration=True)
    late = tasks[1]
    warm, _ = localizer_for(spec, late)  # the benchmark's default
    cold, _ = localizer_for(replace(spec, cue_drive_so_far=False), late)
    ref = CueOffset(cold.config.cal_yaw_offset_prior_std_radps, cold.config.steering_ratio,
                    cold.filter.cue_offset.config)
    ref.rows(drive.onboard[: late.start - late.preroll], warm.filter.yaw_gain_factor)
    assert cold.filter.cue_offset.blocks == 0
    assert warm.filter.cue_offset.blocks == ref.blocks > 10
    assert np.array_equal(warm.filter.cue_offset.theta, ref.theta)
