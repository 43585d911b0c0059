"""The gyro's offset from the cues that do not contain it (runtime/cue_offset.py), on rows with known errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.ekf.numpy_ekf import Ekf
from prml2_edge.runtime.cue_offset import NOMINAL_TRACK_M, NOMINAL_WHEELBASE_M, RESTORE_STD_FLOOR, CueOffset
from prml2_edge.schema import EkfState

_SIG = schema.SIGNAL_BY_NAME
RATIO = 15.0


def rows(n: int, b: float, c: float, k: float, d: float, seed: int = 0, a_y: float = 0.0, speed: float = 15.0,
         swing: float | None = None):
    """``n`` 50 Hz rows driving straight at a speed swinging about ``speed`` (by ``swing``, default 8 m/s or half
    the speed) over a minute, the gyro offset ``b`` [rad/s], a_y offset ``c`` [m/s^2] (plus ``a_y`` of true
    lateral acceleration), a rear radius difference of ``k`` [rad/m] and a steering offset of ``d`` [rad/m]; noise
    on the gyro and a_y."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * schema.DT_S
    v = speed + (min(8.0, speed / 2) if swing is None else swing) * np.sin(2 * math.pi * t / 60.0)
    out = np.zeros((n, schema.NUM_SIGNALS))
    out[:, _SIG["yaw_rate_radps"].index] = b + rng.normal(0.0, math.radians(0.1), n)
    out[:, _SIG["lat_accel_mps2"].index] = a_y + c + rng.normal(0.0, 0.05, n)
    out[:, _SIG["wheel_speed_rl_mps"].index] = v - k * NOMINAL_TRACK_M * v / 2
    out[:, _SIG["wheel_speed_rr_mps"].index] = v + k * NOMINAL_TRACK_M * v / 2
    out[:, _SIG["steering_wheel_angle_rad"].index] = RATIO * math.atan(d * NOMINAL_WHEELBASE_M)
    return out


def feed(est: CueOffset, values: np.ndarray) -> list[tuple[float, float]]:
    valid = np.ones(values.shape[1], dtype=bool)
    exports = []
    for row in values:
        if est.row(row, valid):
            e = est.export()
            if e is not None:
                exports.append(e)
    return exports


def test_the_offset_is_told_from_the_cues_own_errors_over_minutes_of_driving() -> None:
    b, c, k, d = math.radians(0.4), 0.2, 0.004, 0.001  # each cue alone would call b wrong by more than b
    assert abs(c / 15.0) > b and k * 15.0 > b and d * 15.0 > b
    est = CueOffset(math.radians(0.5), RATIO)
    feed(est, rows(5 * 60 * 50, b, c, k, d))
    got, std = est.offset
    assert abs(got - b) < math.radians(0.05)
    assert abs(got - b) < 3 * std
    assert est.theta[1:] == pytest.approx([c, k, d], rel=0.2)


def test_a_restored_car_tells_the_offset_within_a_minute_at_one_speed() -> None:
    """At one steady speed b does not separate from the cues' offsets: a cold start is left near its prior's 0.
    Started from the offsets an earlier drive of the car learned, the same minute tells b."""
    b, c, k, d = math.radians(0.4), 0.1, 0.002, 0.0005
    earlier = CueOffset(math.radians(0.5), RATIO)
    feed(earlier, rows(10 * 60 * 50, math.radians(-0.2), c, k, d, seed=3))  # another day, another gyro offset
    steady = rows(60 * 50, b, c, k, d, seed=4, speed=14.0, swing=0.5)
    cold, warm = CueOffset(math.radians(0.5), RATIO), CueOffset(math.radians(0.5), RATIO)
    warm.restore(*earlier.nuisance())
    feed(cold, steady)
    feed(warm, steady)
    assert abs(warm.offset[0] - b) < math.radians(0.05) and warm.offset[1] < math.radians(0.1)
    assert abs(cold.offset[0] - b) > math.radians(0.15)  # the cold one cannot tell b from c, k, d here
    assert warm.summary()["restored"] and not cold.summary()["restored"]


def test_restore_floors_the_covariance_starts_b_from_its_prior_and_refuses_bad_values() -> None:
    est = CueOffset(math.radians(0.5), RATIO)
    feed(est, rows(5 * 60 * 50, math.radians(0.3), 0.2, 0.003, 0.001))
    values, cov = est.nuisance()
    est.new_drive()  # what the next drive of the car starts from
    assert est.offset == (0.0, pytest.approx(math.radians(0.5)))
    np.testing.assert_allclose(est.theta[1:], values)
    np.testing.assert_allclose(np.diag(est.P)[1:], np.diag(cov) + np.square(RESTORE_STD_FLOOR))
    assert np.all(est.P[0, 1:] == 0.0) and est.blocks == 0
    indefinite = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) * 1e-6
    for bad in ((values[:2], cov), (values, cov[:2, :2]), ([np.nan, 0, 0], cov), (values, np.zeros((3, 3))),
                (values, indefinite)):
        with pytest.raises(ValueError):
            CueOffset(math.radians(0.5), RATIO).restore(*bad)


def test_the_a_y_and_steering_restore_floors_are_settings_of_the_runtime() -> None:
    from prml2_edge.runtime.cue_offset import CueOffsetConfig
    from prml2_edge.runtime.localizer_config import LocalizerConfig

    assert CueOffsetConfig.from_localizer(LocalizerConfig()) == CueOffsetConfig()  # the default: RESTORE_STD_FLOOR
    est = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig.from_localizer(
        LocalizerConfig(cue_steer_restore_floor_deg=1.0)))
    est.restore(np.zeros(3), np.eye(3) * 1e-20)
    assert math.sqrt(est.P[3, 3]) == pytest.approx(math.radians(1.0) / (15.0 * NOMINAL_WHEELBASE_M))
    assert math.sqrt(est.P[1, 1]) == pytest.approx(RESTORE_STD_FLOOR[0])  # the other cues' floors unchanged
    est = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig.from_localizer(
        LocalizerConfig(cue_ay_restore_floor_mps2=0.3)))
    est.restore(np.zeros(3), np.eye(3) * 1e-20)
    assert math.sqrt(est.P[1, 1]) == pytest.approx(0.3) and math.sqrt(est.P[3, 3]) == pytest.approx(
        RESTORE_STD_FLOOR[2])
    with pytest.raises(ValueError, match="cue_steer_restore_floor_deg must be a finite number >= 0"):
        LocalizerConfig(cue_steer_restore_floor_deg=float("nan"))


def test_turning_slow_or_missing_rows_teach_nothing() -> None:
    b = math.radians(0.4)
    for values, valid in ((rows(3000, b, 0, 0, 0, a_y=2.0), None),  # cornering: understeer, slip
                          (rows(3000, b, 0, 0, 0, speed=3.0), None),  # crawling
                          (rows(3000, b, 0, 0, 0), _SIG["steering_wheel_angle_rad"].index)):
        est = CueOffset(math.radians(0.5), RATIO)
        ok = np.ones(values.shape[1], dtype=bool)
        if valid is not None:
            ok[valid] = False
        for row in values:
            est.row(row, ok)
        assert est.blocks == 0 and est.offset[0] == 0.0


def test_exports_hand_over_the_information_once() -> None:
    """Fused one after another into a state that starts at the prior, the exports give the estimator's own b and
    variance: nothing is counted twice, however often it exports."""
    prior = math.radians(0.5)
    est = CueOffset(prior, RATIO)
    exports = feed(est, rows(3 * 60 * 50, math.radians(-0.3), 0.1, 0.002, -0.0005, seed=1))
    assert len(exports) > 3
    x, p = 0.0, prior ** 2
    for m, r in exports:
        g = p / (p + r)
        x, p = x + g * (m - x), (1 - g) * p
    b, std = est.offset
    assert x == pytest.approx(b, abs=math.radians(0.01))
    assert math.sqrt(p) == pytest.approx(std, rel=0.1)


def test_a_floor_caps_what_the_exports_tell_however_long_the_cues_agree() -> None:
    """With ``systematic_std_radps`` the exports, fused one after another, never tell b better than the floor (the
    cues' errors that do not average out), while the estimator itself grows more certain than that."""
    from prml2_edge.runtime.cue_offset import CueOffsetConfig

    prior, floor = math.radians(0.5), math.radians(0.1)
    est = CueOffset(prior, RATIO, CueOffsetConfig(systematic_std_radps=floor))
    exports = feed(est, rows(5 * 60 * 50, math.radians(0.3), 0.1, 0.002, -0.0005, seed=2))
    x, p = 0.0, prior ** 2
    for m, r in exports:
        g = p / (p + r)
        x, p = x + g * (m - x), (1 - g) * p
    assert est.offset[1] < 0.5 * floor
    assert math.sqrt(p) > 0.95 * floor and x == pytest.approx(est.offset[0], abs=math.radians(0.02))
    assert math.sqrt(p) == pytest.approx(math.hypot(est.offset[1], floor), rel=0.05)  # the estimate's and the floor's


def weaving(n: int, b: float, step: float, amp_dps: float = 0.3, speed: float = 15.0, seed: int = 3):
    """``n`` rows of a gentle weave (yaw rate ``amp_dps`` over 20 s, the speed swinging as in :func:`rows`) on a gyro
    rounded to ``step`` [rad/s] with an offset ``b``: the cues (a_y, wheels, steering) follow the true yaw rate
    without offsets of their own."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * schema.DT_S
    w = math.radians(amp_dps) * np.sin(2 * math.pi * t / 20.0)
    out = rows(n, 0.0, 0.0, 0.0, 0.0, seed=seed, speed=speed)
    v = out[:, _SIG["wheel_speed_rl_mps"].index].copy()
    gyro = w + b + rng.normal(0.0, math.radians(0.06), n)
    out[:, _SIG["yaw_rate_radps"].index] = np.round(gyro / step) * step
    out[:, _SIG["lat_accel_mps2"].index] += v * w
    out[:, _SIG["wheel_speed_rl_mps"].index] = v - w * NOMINAL_TRACK_M / 2
    out[:, _SIG["wheel_speed_rr_mps"].index] = v + w * NOMINAL_TRACK_M / 2
    out[:, _SIG["steering_wheel_angle_rad"].index] = RATIO * np.arctan(w * NOMINAL_WHEELBASE_M / v)
    return out


@pytest.mark.parametrize("b_dps", [-0.4, 0.0, 0.3])
def test_a_coarse_gyro_tells_its_offset_through_the_intervals_its_readings_allow(b_dps: float) -> None:
    """A 1.28 deg/s gyro reads 0 on most of a gentle weave whatever its offset within half a step: its block means
    are confidently wrong with an offset; the intervals its runs of one reading allow (the grid) say where it can be,
    pinned where the rate plus the offset crosses half a step (−0.4), wide where it never does (0, +0.3: the weave's
    0.3 deg/s only bound it). A fine gyro keeps its blocks (the setting's threshold)."""
    from prml2_edge.runtime.cue_offset import CueOffsetConfig

    step, b = math.radians(1.28), math.radians(b_dps)
    values = weaving(5 * 60 * 50, b, step)
    blocks = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig(coarse_min_step_radps=math.inf))  # the grid off
    grid = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig(coarse_min_offset_radps=0.0))  # from the first run
    blocks.rows(values, 1.0, step)
    grid.rows(values, 1.0, step)
    (wrong, wrong_std), (got, std) = blocks.offset, grid.offset
    assert grid.coarse.runs > 100 and grid.summary()["coarse_runs"] == grid.coarse.runs
    assert abs(got - b) < 2.5 * std, (math.degrees(got), math.degrees(std))  # honest, whatever the offset
    if b_dps == -0.4:  # the weave's rate plus the offset crosses half a step: the crossings pin it
        assert abs(wrong - b) > 4 * wrong_std  # the blocks: surer, not righter
        assert abs(got - b) < math.radians(0.05) and std < math.radians(0.1)
    fine = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig(coarse_min_step_radps=math.radians(1.0)))
    fine.rows(weaving(60 * 50, b, math.radians(0.01)), 1.0, math.radians(0.01))
    assert fine.coarse.runs == 0 and fine.blocks == 30 and fine.offset == (fine.theta[0], math.sqrt(fine.P[0, 0]))


def test_on_a_low_friction_road_a_coarse_gyro_keeps_its_blocks() -> None:
    """a_y / v does not tell a sliding car's yaw rate: on a road the runtime is told is low-mu, no grid."""
    from prml2_edge.runtime.cue_offset import CueOffsetConfig
    from prml2_edge.runtime.localizer import LocalizerConfig

    on = math.radians(1.0)
    assert CueOffsetConfig.from_localizer(LocalizerConfig(cue_offset_coarse_min_step_radps=on)).coarse_min_step_radps \
        == on
    snow = CueOffsetConfig.from_localizer(LocalizerConfig(cue_offset_coarse_min_step_radps=on, mu=0.3))
    assert snow.coarse_min_step_radps == math.inf
    for bad in (float("nan"), 0.0, -1.0):
        with pytest.raises(ValueError, match="cue_offset_coarse_min_step_radps must be > 0"):
            LocalizerConfig(cue_offset_coarse_min_step_radps=bad)


@pytest.mark.parametrize("b_dps", [-0.4, 0.0])
def test_a_coarse_gyros_grid_takes_over_once_it_tells_a_large_offset(b_dps: float) -> None:
    """With ``coarse_min_offset_radps`` the grid listens alongside the blocks and takes over only once it tells an
    offset that large beyond two of its sigmas: a −0.4 deg/s offset under a weave does, no offset never does (the
    blocks then run exactly as they would without the grid). At the handover the filter forgets what the blocks told
    it and takes the grid's whole estimate: fused, the exports say what the grid says, no surer (they once said it
    2 x too surely, the blocks' and each widening of the grid counted again)."""
    from prml2_edge.runtime.cue_offset import CueOffsetConfig
    from prml2_edge.runtime.localizer import LocalizerConfig

    step, b = math.radians(1.28), math.radians(b_dps)
    values = weaving(5 * 60 * 50, b, step)
    gated = CueOffset(math.radians(0.5), RATIO)  # the default: 1 deg/s steps, 0.1 deg/s
    blocks = CueOffset(math.radians(0.5), RATIO, CueOffsetConfig(coarse_min_step_radps=math.inf))
    x, p = 0.0, math.radians(0.5) ** 2  # the exports fused one after another, as the pose filter's offset state does
    handovers = 0
    for values_row in values:
        if not gated.row(values_row, np.isfinite(values_row), 1.0, step):
            continue
        if gated.handed_over:  # the blocks' word forgotten, the grid's whole estimate instead (PoseFilter)
            handovers += 1
            p += math.radians(0.5) ** 2
            gated.restart_export()
        if (m := gated.export()) is not None:
            g = p / (p + m[1])
            x, p = x + g * (m[0] - x), (1 - g) * p
    blocks.rows(values, 1.0, step)
    assert gated.coarse.runs > 100
    assert gated.summary()["coarse_grid"] is (b_dps == -0.4)
    if b_dps == -0.4:
        assert gated.offset == gated.coarse.offset and abs(gated.offset[0] - b) < math.radians(0.05)
        assert handovers == 1
        # what the filter was told is the grid's, not the grid's on top of the blocks' it replaced
        assert x == pytest.approx(gated.offset[0], abs=math.radians(0.02))
        assert math.sqrt(p) > 0.85 * gated.offset[1]
    else:
        assert handovers == 0 and gated.offset == blocks.offset and np.array_equal(gated.theta, blocks.theta)
    for bad in (float("nan"), -0.1, math.inf):
        with pytest.raises(ValueError, match="cue_offset_coarse_min_offset_radps must be >= 0"):
            LocalizerConfig(cue_offset_coarse_min_offset_radps=bad)


def test_a_grid_from_its_first_run_hands_over_from_blocks_that_saw_the_gyro_before_its_step_was_known() -> None:
    """``coarse_min_offset_radps=0``: the grid from its first run. A gyro whose step the filter learns only after
    some blocks (a replay's first minutes) had those blocks fused with its readings; when the grid comes on, the
    filter is told to forget them as at any handover, once. With the step known from the first row there is nothing
    to forget."""
    from prml2_edge.runtime.cue_offset import CueOffsetConfig

    step, b = math.radians(1.28), math.radians(-0.4)
    values = weaving(3 * 60 * 50, b, step)
    cfg = CueOffsetConfig(coarse_min_offset_radps=0.0)
    late, known = CueOffset(math.radians(0.5), RATIO, cfg), CueOffset(math.radians(0.5), RATIO, cfg)
    handovers = {"late": 0, "known": 0}
    for i, row in enumerate(values):
        for name, est, step_now in (("late", late, step if i >= 60 * 50 else None), ("known", known, step)):
            est.row(row, np.isfinite(row), 1.0, step_now)
            if est.handed_over:
                handovers[name] += 1
                est.restart_export()
    assert late.summary()["coarse_grid"] and known.summary()["coarse_grid"]
    assert handovers == {"late": 1, "known": 0}


def test_the_ekf_takes_the_offset_as_a_measurement_of_its_state() -> None:
    ekf = Ekf(np.zeros(EkfState.DIM), np.eye(EkfState.DIM), calibration=True)
    before = ekf.cal_cov[0, 0]
    ekf.update_yaw_offset(0.007, 1e-6)
    assert ekf.cal[0] == pytest.approx(0.007 * before / (before + 1e-6))
    assert ekf.cal_cov[0, 0] < before
    assert ekf.update_yaw_offset(float("nan"), 1e-6).name == "INPUT_INVALID"


def test_the_summary_says_what_the_cues_told() -> None:
    est = CueOffset(math.radians(0.5), RATIO)
    assert est.summary()["blocks"] == 0 and est.summary()["nis"] is None
    feed(est, rows(60 * 50, math.radians(0.4), 0.0, 0.0, 0.0))
    s = est.summary()
    assert s["blocks"] == 30 and s["yaw_rate_offset_dps"] == pytest.approx(0.4, abs=0.1)
    assert all(0.0 < x < 5.0 for x in s["nis"])


@pytest.fixture(scope="module")
def offset_drive():
    """Three minutes of a fine-gyro car with no stop and an uncalibrated +0.4 deg/s on its CAN yaw rate."""
    from prml2_edge.data.simulate import simulate_drive

    return simulate_drive(3.0, 1.0, 4242, "mixed", name="no_stop", vehicle="compact_fwd", standstill=False,
                          sensor_errors={"yaw_offset_radps": math.radians(0.4)})


@pytest.mark.parametrize("cues", [True, False])
def test_the_filter_learns_a_fine_gyros_offset_while_driving_only_from_the_cues(tmp_path, offset_drive, cues):
    """A model that reads the gyro (here the closed-form one: its omega_z is the gyro) passes the offset through:
    without the cues the filter learns next to nothing of it in three minutes; with them most of it."""
    from runtime_models import make_kinematic_model

    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer

    loc = StreamingLocalizer(OnnxModel(make_kinematic_model(tmp_path / "k.onnx")), LocalizerConfig(cue_offset=cues))
    start = schema.WINDOW_LEN - 1
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.VEL.start] = offset_drive.onboard[start, _SIG["wheel_speed_rl_mps"].index]
    traj = loc.run_arrays(offset_drive.onboard, x0, start_index=start, gnss={})
    learned = math.degrees(traj.cal[-1, 0])
    if cues:
        assert abs(learned - 0.4) < 0.15
        assert loc.filter.summary()["calibration"]["cue_offset"]["blocks"] > 20
    else:
        assert abs(learned) < 0.15
        assert "cue_offset" not in loc.filter.summary()["calibration"]


@pytest.mark.parametrize("so_far", [True, False])
def test_a_filter_started_mid_drive_hears_at_once_what_the_cues_learned_of_the_drive_so_far(tmp_path, offset_drive,
                                                                                           so_far):
    """The EKF (re)started two minutes into the drive: the offset the cue estimator learned over those minutes is
    in its offset state from the first row, not only after the next straight block. Without the drive so far the
    start knows nothing of it."""
    from runtime_models import make_kinematic_model

    from prml2_edge.runtime.inference import OnnxModel
    from prml2_edge.runtime.localizer import LocalizerConfig, StreamingLocalizer

    loc = StreamingLocalizer(OnnxModel(make_kinematic_model(tmp_path / "k.onnx")), LocalizerConfig())
    split, start = 2 * 60 * 50, schema.WINDOW_LEN - 1
    if so_far:
        assert loc.filter.cue_offset.rows(offset_drive.onboard[:split - start]) > 10
    rest = offset_drive.onboard[split - start:]
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.VEL.start] = rest[start, _SIG["wheel_speed_rl_mps"].index]
    traj = loc.run_arrays(rest, x0, start_index=start, gnss={})
    first = math.degrees(traj.cal[start, 0])
    assert abs(first - 0.4) < 0.15 if so_far else abs(first) < 1e-9


def test_a_cars_history_teaches_the_file_the_cues_own_offsets() -> None:
    """The simulated history keeps the car's accelerometer and steering offsets (each drive a little off them) and
    its tyres: the cue estimator run over it, each drive's gyro offset its own, finds the car's offsets."""
    from prml2_edge.data.simulate import simulate_drive
    from prml2_edge.data.simulate.fleet import get_car
    from prml2_edge.evaluation.unit_history import cue_evidence

    steer = math.radians(2.0)
    drive = simulate_drive(0.5, 1.0, 5, "mixed", "cues_car", vehicle="compact_fwd",
                           sensor_errors={"lat_offset_mps2": 0.2, "steer_offset_rad": steer,
                                          "wheel_radius_error": (0.0, 0.0, -0.003, 0.003)})
    ratio = get_car("compact_fwd").params.steering_ratio
    values, cov = cue_evidence(drive, minutes=8.0, drives=2)
    assert values[0] == pytest.approx(0.2, abs=0.06)
    assert values[1] == pytest.approx(0.006 / NOMINAL_TRACK_M, rel=0.1)
    assert values[2] == pytest.approx(steer / (ratio * NOMINAL_WHEELBASE_M), rel=0.1)
    assert np.all(np.sqrt(np.diag(cov)) < [0.05, 0.0003, 0.0003])


def test_a_blur_wider_than_the_grid_still_gives_an_offset() -> None:
    """The cue's common error can be wider than the grid (a_y's offset barely known, slow rows): the posterior is
    then the prior's, not a shape error (it once raised inside the runtime's filter on a fault-injection drive)."""
    from prml2_edge.runtime.coarse_offset import CoarseOffset

    grid = CoarseOffset(math.radians(0.5))
    step = math.radians(1.28)
    readings = np.repeat([0.0, step, 0.0], 20)
    rate = np.full(len(readings), math.radians(0.6))
    assert grid.block(readings, rate, step, rate_std_radps=math.radians(50.0)) > 0
    b, std = grid.offset
    assert math.isfinite(b) and 0.0 < std <= math.radians(0.5)



def test_a_model_next_to_the_estimator_reads_the_cues_less_their_learned_offsets() -> None:
    """The rows ``rows`` makes carry an a_y offset c and a steering offset d: learned over minutes of driving,
    :meth:`CueOffset.debiased` takes them out of a row (a copy), leaving every other signal as it was."""
    b, c, k, d = math.radians(0.3), 0.15, 0.002, 0.0008
    drive = rows(5 * 60 * 50, b, c, k, d, seed=5)
    est = CueOffset(math.radians(0.5), RATIO)
    row = drive[-1].copy()
    np.testing.assert_array_equal(est.debiased(row), row)  # nothing learned yet: the row as it is
    feed(est, drive)
    out = est.debiased(row)
    np.testing.assert_array_equal(row, drive[-1])  # the caller's row is not touched
    ay, steer = _SIG["lat_accel_mps2"].index, _SIG["steering_wheel_angle_rad"].index
    assert out[ay] == pytest.approx(row[ay] - c, abs=0.02)
    assert out[steer] == pytest.approx(0.0, abs=math.radians(0.1))  # the straight's steering less its offset
    others = [i for i in range(schema.NUM_SIGNALS) if i not in (ay, steer)]
    np.testing.assert_array_equal(out[others], row[others])
