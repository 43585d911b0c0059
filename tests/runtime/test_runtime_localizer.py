"""StreamingLocalizer: the one streaming path (window -> model -> guard -> EKF), on plain arrays."""

from __future__ import annotations

import json

import numpy as np
import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.inference import OnnxModel
from prml2_edge.runtime.initial_pose import InitialPose, initial_state
from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer
from prml2_edge.runtime.rows import GnssFix
from prml2_edge.runtime.status import PoseStatus
from prml2_edge.schema import EkfState, psi_rad_to_heading_deg

L = schema.WINDOW_LEN


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return make_kinematic_model(tmp_path_factory.mktemp("m") / "kinematic.onnx")


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(0.6, 1.0, 11)  # 36 s


def gt_state(drive, i: int) -> np.ndarray:
    x0 = np.zeros(EkfState.DIM)
    x0[:3] = drive.pose_gt[i]
    x0[list(schema.Z_TO_EKF_INDEX)] = drive.z_gt[i]
    return x0


def test_dead_reckoning_from_the_true_state_stays_within_the_baseline_error_level(model_path, drive):
    loc = StreamingLocalizer(OnnxModel(model_path))
    start = L - 1  # the model is warm at the first step
    traj = loc.run_arrays(drive.onboard, gt_state(drive, start), start_index=start)
    assert np.isnan(traj.x[:start]).all()
    np.testing.assert_allclose(traj.x[start], gt_state(drive, start))
    assert traj.model_used[start + 1:].all()
    err = np.hypot(*(traj.pose[start:, :2] - drive.pose_gt[start:, :2]).T)
    dist = float(np.sum(np.hypot(*np.diff(drive.pose_gt[start:, :2], axis=0).T)))
    # the closed-form model is an odometry baseline (paper OSD: 5.3 m RMSE over 60 s); here ~31 s
    assert dist > 100.0
    assert float(err[-1]) < 0.05 * dist and float(np.sqrt(np.mean(err ** 2))) < 8.0
    assert traj.pos_std_m[-1] > 5 * traj.pos_std_m[start]  # no absolute fix: the uncertainty grows


def test_step_by_step_equals_run_arrays(model_path, drive):
    n = 400
    pose = InitialPose(float(drive.pose_gt[0, 0]), float(drive.pose_gt[0, 1]),
                       psi_rad_to_heading_deg(float(drive.pose_gt[0, 2])))
    x0, p0 = initial_state(pose, drive.onboard[0])
    ref = StreamingLocalizer(OnnxModel(model_path)).run_arrays(drive.onboard[:n], x0, p0)
    loc = StreamingLocalizer(OnnxModel(model_path), initial_pose=pose)
    valid = np.ones(schema.NUM_SIGNALS, dtype=bool)
    outs = [loc.step(drive.onboard[i], valid, i * schema.DT_S) for i in range(n)]
    np.testing.assert_array_equal(np.array([o.x for o in outs]), ref.x)
    status = [o.status for o in outs]
    # window filling: predict only, except parked (the zero-velocity update is a measurement)
    assert status[1:L - 1] == [PoseStatus.DEAD_RECKONING if o.standstill else PoseStatus.PREDICT_ONLY
                               for o in outs[1:L - 1]]
    assert any(o.standstill for o in outs[1:L - 1]) and not all(o.standstill for o in outs[1:L - 1])
    assert all(s is PoseStatus.DEAD_RECKONING for s in status[L:])
    first_moving = next(i for i in range(L - 1, n) if not outs[i].standstill)
    assert [o.model_used for o in outs].index(True) == first_moving


def test_stride_uses_older_windows_between_inferences(model_path, drive):
    loc = StreamingLocalizer(OnnxModel(model_path), LocalizerConfig(stride=10))
    traj = loc.run_arrays(drive.onboard[:600], gt_state(drive, L - 1), start_index=L - 1)
    assert loc.n_inferences == 1 + (600 - L) // 10
    assert traj.model_used[L:].all()


def test_invalid_inputs_degrade_to_predict_only_and_recover(model_path, drive):
    n = 760
    valid = np.ones((n, schema.NUM_SIGNALS), dtype=bool)
    valid[400:460, 2] = False  # yaw rate invalid for 1.2 s
    loc = StreamingLocalizer(OnnxModel(model_path), LocalizerConfig(max_invalid_fraction=0.1))
    traj = loc.run_arrays(drive.onboard[:n], gt_state(drive, L - 1), start_index=L - 1, valid=valid)
    assert (traj.status[400:460] == PoseStatus.DEGRADED).all() and not traj.model_used[400:460].any()
    # afterwards the window holds > 10 % invalid rows (60 of 250): predict only until at most 25 are left,
    # i.e. until the window starts at row 435 (row 684)
    assert not traj.model_used[460:684].any() and (traj.status[460:684] == PoseStatus.PREDICT_ONLY).all()
    assert traj.model_used[684:].all()
    assert np.isfinite(traj.x[L - 1:]).all()


def test_broken_model_output_means_predict_only_never_an_exception(tmp_path, drive):
    bad = OnnxModel(make_kinematic_model(tmp_path / "nan.onnx", bias=[0, 0, 0, 0, np.nan]))
    loc = StreamingLocalizer(bad)
    traj = loc.run_arrays(drive.onboard[:300], gt_state(drive, L - 1), start_index=L - 1)
    assert not traj.model_used.any() and loc.n_inference_failures == (300 - L) // loc.config.stride + 1
    assert (traj.status[L:] == PoseStatus.PREDICT_ONLY).all() and np.isfinite(traj.x[L - 1:]).all()


def test_gnss_initialises_aids_and_its_loss_is_flagged(model_path, drive):
    loc = StreamingLocalizer(OnnxModel(model_path), LocalizerConfig(gnss_timeout_s=0.5))
    valid = np.ones(schema.NUM_SIGNALS, dtype=bool)
    outs = []
    for i in range(400):
        t = i * schema.DT_S
        fix = None
        if i % 5 == 0 and 3 <= i <= 300:  # 10 Hz fixes from row 3 to 6 s
            x, y, psi = drive.pose_gt[i]
            fix = GnssFix(t, float(x), float(y), psi_rad_to_heading_deg(float(psi)), True)
        outs.append(loc.step(drive.onboard[i], valid, t, fix))
    assert [o.status for o in outs[:5]] == [PoseStatus.INITIALISING] * 5
    assert outs[5].status is PoseStatus.GNSS_AIDED and outs[5].gnss_fused
    assert all(o.status is PoseStatus.GNSS_AIDED for o in outs[5:326])
    assert not outs[325].gnss_outage and outs[326].gnss_outage and outs[-1].gnss_outage
    assert outs[-1].status is PoseStatus.DEAD_RECKONING
    assert outs[-1].outage_s == pytest.approx((399 - 300) * schema.DT_S)
    err = np.hypot(*(outs[300].x[:2] - drive.pose_gt[300, :2]))
    assert err < 0.5
    rec = json.loads(json.dumps(outs[0].record()))  # initialising: no pose, valid JSON
    assert rec["p_x_m"] is None and rec["status"] == "INITIALISING"


def test_physics_guard_bounds_what_the_filter_consumes(tmp_path, drive):
    from runtime_models import kinematic_weights

    w = kinematic_weights()
    w[:, schema.Z.V_X] *= 4.0  # a model that overestimates speed 4x: up to ~80 m/s
    # calibration off: the raw wheel-speed cue would pull v_x back on its own; this isolates the guard
    # stride 1: a prediction per row, so the guard's verdict can be checked row by row
    loc = StreamingLocalizer(OnnxModel(make_kinematic_model(tmp_path / "fast.onnx", weights=w)),
                             LocalizerConfig(calibration=False, stride=1))
    traj = loc.run_arrays(drive.onboard, gt_state(drive, L - 1), start_index=L - 1)
    fast = 4.0 * drive.onboard[L:, 5:9].mean(axis=1) > schema.V_MAX_MPS
    assert fast.any() and traj.guard_fired[L:][fast].all() and not traj.guard_fired[L:][~fast].any()
    assert np.nanmax(traj.x[:, EkfState.VEL.start]) < schema.V_MAX_MPS + 0.5
    assert loc.guard_stats.n_predictions == len(drive) - L + 1 and loc.guard_stats.n_fired == fast.sum()


def test_a_parked_start_does_not_take_the_receivers_course_as_the_yaw(model_path):
    """Parked, a receiver's course is stale or noise (here 90 deg off the car): the start takes the fix's position
    only, and the first course while driving sets the heading."""
    d = simulate_drive(1.0, 0.9, 5, "mixed", name="parked_start")
    first_moving = int(np.argmax(d.z_gt[:, schema.Z.V_X] > 3.0))
    assert first_moving > 50  # the drive starts parked

    def run(stale_course: bool) -> np.ndarray:
        loc = StreamingLocalizer(OnnxModel(model_path))
        valid = np.ones(schema.NUM_SIGNALS, dtype=bool)
        yaw = []
        for i in range(first_moving + 100):
            fix = None
            if i % 5 == 0:
                x, y, psi = d.pose_gt[i]
                vx, vy = d.z_gt[i, schema.Z.V_X], d.z_gt[i, schema.Z.V_Y]
                moving = np.hypot(vx, vy) >= 2.0
                course = psi + np.arctan2(vy, vx) if moving else psi + (np.pi / 2 if stale_course else 0.0)
                fix = GnssFix(i * schema.DT_S, float(x), float(y), psi_rad_to_heading_deg(float(course)), True)
            out = loc.step(d.onboard[i], valid, i * schema.DT_S, fix)
            yaw.append(out.x[EkfState.YAW.start] if out.x is not None else np.nan)
        return np.degrees(np.abs(np.angle(np.exp(1j * (np.array(yaw) - d.pose_gt[:len(yaw), 2])))))

    err = run(stale_course=True)
    assert err[first_moving + 50:].max() < 3.0, err[first_moving + 50:].max()  # 1 s after moving off
    assert run(stale_course=False)[first_moving + 50:].max() < 3.0


def test_a_stray_first_fix_is_replaced_by_the_next(model_path, drive):
    """A spoofed fix 300 m off, then true ones: the start is provisional until two fixes agree with each
    other and the wheels; the disagreeing second fix restarts the filter at once (not after 20 gated fixes)."""
    loc = StreamingLocalizer(OnnxModel(model_path))
    valid = np.ones(schema.NUM_SIGNALS, dtype=bool)
    outs = []
    for i in range(60):
        t = i * schema.DT_S
        fix = None
        if i % 5 == 0:
            x, y, psi = drive.pose_gt[i]
            fix = GnssFix(t, float(x) + (300.0 if i == 0 else 0.0), float(y), psi_rad_to_heading_deg(float(psi)),
                          True)
        outs.append(loc.step(drive.onboard[i], valid, t, fix))
    assert loc.filter.n_gnss_init_rejected == 1 and loc.filter.n_gnss_rejected == 0
    assert outs[0].status is PoseStatus.GNSS_AIDED and abs(outs[0].x[0] - drive.pose_gt[0, 0] - 300.0) < 1.0
    for o in outs[5:]:
        assert np.hypot(*(o.x[:2] - drive.pose_gt[o.k, :2])) < 1.0
    # the velocity comes from the wheel speeds at the restart
    assert outs[5].x[schema.EkfState.VEL.start] == pytest.approx(drive.onboard[5, 5:9].mean(), abs=0.3)


def test_gnss_waits_for_the_wheels(model_path, drive):
    """A fix before any wheel speed (cold start): no start with v_x = 0 from nothing."""
    loc = StreamingLocalizer(OnnxModel(model_path))
    none_valid = np.zeros(schema.NUM_SIGNALS, dtype=bool)
    x, y, psi = drive.pose_gt[0]
    out = loc.step(drive.onboard[0], none_valid, 0.0, GnssFix(0.0, float(x), float(y), 0.0, True))
    assert out.status is PoseStatus.INITIALISING and loc.ekf is None


def _gnss_fixes(drive, until_s: float, pos_noise_m: float = 0.0, seed: int = 0) -> dict[int, GnssFix]:
    rng = np.random.default_rng(seed)
    fixes = {}
    for i in range(5, int(until_s / schema.DT_S), 5):  # 10 Hz
        x, y, psi = drive.pose_gt[i]
        n = rng.normal(0.0, pos_noise_m, 2) if pos_noise_m else (0.0, 0.0)
        heading = psi_rad_to_heading_deg(float(psi)) if drive.z_gt[i, schema.Z.V_X] > 2.0 else None
        fixes[i] = GnssFix(i * schema.DT_S, float(x + n[0]), float(y + n[1]), heading, True)
    return fixes


def test_gnss_teaches_the_wheel_scale_and_it_carries_the_outage(model_path):
    """Wheels 1 % fast on a drive: 40 s of GNSS learn the scale from wheel against GNSS distance; without
    calibration the same model and log drift further once GNSS stops."""
    drive = simulate_drive(1.5, 1.0, 21, sensor_errors={"wheel_radius_error": 0.01, "yaw_offset_radps": 0.0})
    x0 = gt_state(drive, 0)
    fixes = _gnss_fixes(drive, 40.0, pos_noise_m=0.5)
    cfg = LocalizerConfig(gnss_pos_std_m=0.5)
    on = StreamingLocalizer(OnnxModel(model_path), cfg).run_arrays(drive.onboard, x0, gnss=fixes)
    off = StreamingLocalizer(OnnxModel(model_path), LocalizerConfig(gnss_pos_std_m=0.5, calibration=False)
                             ).run_arrays(drive.onboard, x0, gnss=fixes)
    k_out = int(40.0 / schema.DT_S)
    scale = on.cal[k_out, schema.CalState.WHEEL_SCALE.start - EkfState.DIM]
    assert 0.006 < scale < 0.012  # the rear wheels' effective error: 1 % less their slip
    assert np.isnan(off.cal).all()

    def final_error(tr):
        return float(np.hypot(*(tr.x[-1, :2] - drive.pose_gt[-1, :2])))

    assert final_error(on) < final_error(off)


def test_standstill_holds_the_pose_and_reveals_the_offset_of_a_fine_yaw_sensor(model_path):
    """Parked with a yaw-rate sensor of fine resolution reading a 0.3 deg/s offset: the zero-velocity update
    keeps the pose still and the offset is learned without GNSS."""
    n = 600
    onboard = np.zeros((n, schema.NUM_SIGNALS))
    rng = np.random.default_rng(4)
    yaw = np.radians(0.3) + rng.normal(0.0, np.radians(0.05), n)
    onboard[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index] = np.round(yaw / 1e-4) * 1e-4  # 0.006 deg/s steps
    traj = StreamingLocalizer(OnnxModel(model_path)).run_arrays(onboard, np.zeros(EkfState.DIM))
    assert np.hypot(*traj.x[-1, :2]) < 0.01 and abs(traj.x[-1, EkfState.YAW.start]) < np.radians(0.05)
    offset = np.degrees(traj.cal[-1, 0])
    assert abs(offset - 0.3) < 0.05


def test_on_a_low_mu_road_the_raw_cues_carry_more_than_the_model(tmp_path, drive):
    """The model was trained on dry roads: on snow (``mu`` <= 0.5) its variance is inflated
    (``low_mu_model_var_scale``), so a model that reads 1 m/s too fast moves the filter's v_x less off the wheels."""
    biased = OnnxModel(make_kinematic_model(tmp_path / "fast.onnx", bias=[1.0, 0, 0, 0, 0]))
    n, start = L + 250, L - 1
    vx_err = {}
    for mu in (1.0, 0.3):
        loc = StreamingLocalizer(biased, LocalizerConfig(mu=mu))
        traj = loc.run_arrays(drive.onboard[:n], gt_state(drive, start), start_index=start)
        vx_err[mu] = float(np.mean(traj.x[start + 50:, EkfState.VEL.start] - drive.z_gt[start + 50:n, schema.Z.V_X]))
    assert 0.0 < vx_err[0.3] < 0.5 * vx_err[1.0]
    off = StreamingLocalizer(biased, LocalizerConfig(mu=0.3, low_mu_model_var_scale=1.0))
    traj = off.run_arrays(drive.onboard[:n], gt_state(drive, start), start_index=start)
    assert float(np.mean(traj.x[start + 50:, EkfState.VEL.start] - drive.z_gt[start + 50:n, schema.Z.V_X])) \
        == pytest.approx(vx_err[1.0], rel=0.2)


def test_on_a_low_mu_road_the_position_widens_along_the_track_with_traction(model_path, drive):
    """Tyres on snow slip with the force asked of them, and the model and the wheels read the same speed: the
    position's along-track sigma grows with |v_x| a / (mu g) (``low_mu_slip_gain``), a the braking deceleration
    for a wheel cue on a free-rolling axle, |a_x| when that axle drives too (AWD); on a dry road nothing."""
    n, start = len(drive.t_s), L - 1  # the drive accelerates in its first 10 s and brakes after

    def run(**kw):
        loc = StreamingLocalizer(OnnxModel(model_path), LocalizerConfig(**kw))
        return loc.run_arrays(drive.onboard[:n], gt_state(drive, start), start_index=start)

    def along_var(traj):
        c, s = np.cos(traj.pose[-1, 2]), np.sin(traj.pose[-1, 2])
        return float(np.array([c, s]) @ traj.pos_cov[-1] @ np.array([c, s]))

    snow, snow_awd, snow_off = run(mu=0.3), run(mu=0.3, driven_axle="all"), run(mu=0.3, low_mu_slip_gain=0.0)
    # the uncertainty only, not the estimate (an AWD car's cue is the rear axle too)
    assert np.array_equal(snow.pose, snow_off.pose, equal_nan=True)
    assert np.array_equal(snow_awd.pose, snow_off.pose, equal_nan=True)
    grow_fwd, grow_awd = along_var(snow) - along_var(snow_off), along_var(snow_awd) - along_var(snow_off)
    assert grow_awd > 2.0 * grow_fwd and grow_fwd > 0.1  # [m^2]: braking only, against braking and traction
    dry, dry_off = run(mu=1.0), run(mu=1.0, low_mu_slip_gain=0.0)
    assert np.array_equal(dry.pos_cov, dry_off.pos_cov, equal_nan=True)


def test_a_rear_driven_car_takes_its_wheel_cue_from_the_free_rolling_front_axle(model_path):
    """On snow a RWD car's rear wheels spin up with the traction and read v_x a few per cent high; its front wheels
    roll freely. With ``driven_axle="rear"`` the filter's v_x follows the front axle and is closer to the truth
    while the car accelerates than with the rear axle's cue (``driven_axle="front"``, the FWD default)."""
    from prml2_edge.data.simulate.fleet import CARS

    car = CARS["rwd_sedan"]
    snow = simulate_drive(1.0, 0.3, 5, "snow", vehicle="rwd_sedan")
    start = L - 1
    traction = snow.z_gt[start:, schema.Z.A_X] > 0.3
    assert traction.sum() > 200  # the drive accelerates for more than 4 s

    def vx_error(axle: str) -> float:
        cfg = LocalizerConfig(mu=0.3, driven_axle=axle, steering_ratio=car.params.steering_ratio)
        traj = StreamingLocalizer(OnnxModel(model_path), cfg).run_arrays(snow.onboard, gt_state(snow, start),
                                                                         start_index=start)
        err = traj.x[start:, EkfState.VEL.start] - snow.z_gt[start:, schema.Z.V_X]
        return float(np.mean(err[traction]))

    front_cue, rear_cue = vx_error("rear"), vx_error("front")
    assert rear_cue > 0.1  # the slipping rear axle: more than 0.1 m/s high on average
    assert abs(front_cue) < 0.5 * rear_cue


def test_the_front_axle_cue_is_steer_corrected():
    """Steered front wheels roll along their own heading at v_x / cos(delta) (kinematic single track): the cue is
    their mean times cos(steering wheel angle / steering ratio); a missing steering angle means no cue."""
    from prml2_edge.runtime.axle_speed import front_speed

    sig = schema.SIGNAL_BY_NAME
    values, valid = np.zeros(schema.NUM_SIGNALS), np.ones(schema.NUM_SIGNALS, dtype=bool)
    delta = 0.3
    values[sig["steering_wheel_angle_rad"].index] = 15.0 * delta
    values[sig["wheel_speed_fl_mps"].index] = 4.9 / np.cos(delta)
    values[sig["wheel_speed_fr_mps"].index] = 5.1 / np.cos(delta)
    assert front_speed(values, valid, 15.0) == pytest.approx(5.0)
    valid[sig["steering_wheel_angle_rad"].index] = False
    assert front_speed(values, valid, 15.0) is None


def test_an_unknown_driven_axle_is_refused():
    with pytest.raises(ValueError, match="driven_axle must be 'front' \\(FWD\\), 'rear' \\(RWD\\) or 'all'"):
        LocalizerConfig(driven_axle="fwd")


class _Reads:
    """The real model, keeping the newest row of every window it was given."""

    def __init__(self, inner) -> None:
        self.inner, self.rows = inner, []
        self.window_len, self.decoder_len = inner.window_len, inner.decoder_len

    mean = property(lambda self: self.inner.mean)
    var = property(lambda self: self.inner.var)
    metadata = property(lambda self: self.inner.metadata)

    def step(self, window):
        self.rows.append(np.array(window[0, -1]))
        return self.inner.step(window)


@pytest.mark.parametrize("asked_by", ["config", "model"])
def test_the_model_reads_a_y_and_steering_less_the_offsets_the_car_taught(model_path, drive, asked_by, tmp_path):
    """With ``model_inputs_from_cues``, or a model whose metadata says it was trained so (``cue_debiased_inputs``),
    the model's window holds the CAN rows less the cue estimator's a_y and steering offsets (here restored from the
    calibration file); the filter and the default read them raw."""
    from prml2_edge.runtime.cue_offset import NOMINAL_WHEELBASE_M, steering_offset

    c, steer_deg = 0.2, 2.0
    ay, st = schema.SIGNAL_BY_NAME["lat_accel_mps2"].index, schema.SIGNAL_BY_NAME["steering_wheel_angle_rad"].index
    n = L + 20
    seen = {}
    for on in (False, True):
        if asked_by == "model":
            config = {"cue_debiased_inputs": on}
            path = make_kinematic_model(tmp_path / f"m{on}.onnx", meta_overrides={"config": config})
            model, cfg = _Reads(OnnxModel(path)), LocalizerConfig()
        else:
            model, cfg = _Reads(OnnxModel(model_path)), LocalizerConfig(model_inputs_from_cues=on)
        loc = StreamingLocalizer(model, cfg)
        assert loc.model_reads_cues is on
        assert loc.restore_cue_offsets([c, 0.0, steering_offset(steer_deg)], np.eye(3) * 1e-8)
        loc.run_arrays(drive.onboard[:n], gt_state(drive, L - 1), start_index=L - 1)
        seen[on] = np.array(model.rows)
    assert len(seen[True]) == len(seen[False]) > 0
    assert not np.allclose(seen[False][:, ay], seen[False][0, ay])  # the drive's own a_y moves under the shift
    shift = seen[False] - seen[True]
    np.testing.assert_allclose(shift[:, ay], c, atol=1e-6)
    d = steering_offset(steer_deg) * LocalizerConfig().steering_ratio * NOMINAL_WHEELBASE_M
    assert d == pytest.approx(np.radians(steer_deg))  # the nominal ratio: the steering-wheel offset itself
    np.testing.assert_allclose(shift[:, st], d, atol=1e-6)
    others = [i for i in range(schema.NUM_SIGNALS) if i not in (ay, st)]
    np.testing.assert_allclose(shift[:, others], 0.0)


def test_a_model_trained_on_debiased_cues_without_calibration_says_it_reads_raw_rows(tmp_path, caplog):
    """Nothing learns the offsets without calibration: a run a user starts says so once instead of feeding raw rows
    quietly (the benchmark's paper-filter windows, and the export's error model on pre-debiased rows, stay quiet)."""
    from prml2_edge.runtime.pipeline import Pipeline

    path = make_kinematic_model(tmp_path / "d.onnx", meta_overrides={"config": {"cue_debiased_inputs": True}})
    with caplog.at_level("WARNING"):
        Pipeline.build(model=path, calibration=False, external_gnss=True)
    assert "reads the raw CAN values" in caplog.text and "turn calibration on" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        StreamingLocalizer(OnnxModel(path), LocalizerConfig(calibration=False))
        Pipeline.build(model=path, external_gnss=True)
    assert "raw CAN values" not in caplog.text
