"""NumPy EKF (prml2_edge.ekf): model, Jacobian, update algebra, covariance health, step statuses."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prml2_edge import schema
from prml2_edge.ekf import numpy_ekf as ne
from prml2_edge.ekf.numpy_ekf import Ekf, StepStatus
from prml2_edge.schema import EkfState

DT = schema.DT_S


def random_state(rng: np.random.Generator) -> np.ndarray:
    x = np.empty(EkfState.DIM)
    x[EkfState.POS] = rng.uniform(-500.0, 500.0, 2)
    x[EkfState.YAW] = rng.uniform(-20.0, 20.0)  # unwrapped
    x[EkfState.OMEGA_Z] = rng.uniform(-1.5, 1.5)
    x[EkfState.VEL] = rng.uniform(-30.0, 30.0, 2)
    x[EkfState.ACC] = rng.uniform(-10.0, 10.0, 2)
    return x


def random_spd(rng: np.random.Generator, n: int, lo: float = 1e-3, hi: float = 10.0) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (q * rng.uniform(lo, hi, n)) @ q.T


def test_process_model_moves_along_heading() -> None:
    x = np.zeros(EkfState.DIM)
    x[EkfState.YAW] = math.pi / 2  # heading north
    x[EkfState.VEL] = [10.0, 0.0]
    x[EkfState.ACC] = [2.0, 0.0]
    x[EkfState.OMEGA_Z] = 0.5
    out = ne.process_model(x, DT)
    assert out[0] == pytest.approx(0.0, abs=1e-12)
    assert out[1] == pytest.approx(10.0 * DT + 0.5 * 2.0 * DT**2, rel=1e-12)
    assert out[EkfState.YAW][0] == pytest.approx(math.pi / 2 + 0.5 * DT)
    assert out[EkfState.VEL][0] == pytest.approx(10.0 + 2.0 * DT)
    np.testing.assert_array_equal(out[EkfState.ACC], x[EkfState.ACC])
    # left (vehicle +y) while heading north is world west (-x)
    x[EkfState.VEL] = [0.0, 1.0]
    x[EkfState.ACC] = 0.0
    assert ne.process_model(x, DT)[0] == pytest.approx(-DT)


def test_psi_stays_unwrapped() -> None:
    x = np.zeros(EkfState.DIM)
    x[EkfState.YAW] = 3.1
    x[EkfState.OMEGA_Z] = 1.5
    for _ in range(50):
        x = ne.process_model(x, DT)
    assert x[EkfState.YAW][0] == pytest.approx(3.1 + 1.5 * 50 * DT)
    assert x[EkfState.YAW][0] > math.pi


@pytest.mark.parametrize("seed", range(5))
def test_jacobian_matches_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x = random_state(rng)
    dt = 0.02 if seed < 3 else 0.5  # also a long step, where the dt^2 terms matter
    f = ne.process_jacobian(x, dt)
    h = 1e-4  # central differences: truncation ~h^2, rounding ~eps |x| / h
    num = np.empty_like(f)
    for j in range(EkfState.DIM):
        e = np.zeros(EkfState.DIM)
        e[j] = h
        num[:, j] = (ne.process_model(x + e, dt) - ne.process_model(x - e, dt)) / (2 * h)
    np.testing.assert_allclose(f, num, rtol=0, atol=1e-7)


def test_measurement_matrix_selects_schema_order() -> None:
    h = ne.measurement_matrix()
    assert h.shape == (schema.NUM_STATES, EkfState.DIM)
    x = np.arange(EkfState.DIM, dtype=float)
    np.testing.assert_array_equal(h @ x, x[list(schema.Z_TO_EKF_INDEX)])
    assert schema.STATE_NAMES[schema.Z.OMEGA_Z] == "omega_z_radps"
    assert EkfState.NAMES[schema.Z_TO_EKF_INDEX[schema.Z.OMEGA_Z]] == "omega_z_radps"


def test_default_noise_matrices() -> None:
    q = ne.default_process_noise(DT)
    np.testing.assert_array_equal(q, q.T)
    assert np.linalg.eigvalsh(q).min() >= 0.0
    pn = ne.ProcessNoise()
    ax = EkfState.ACC.start
    assert q[ax, ax] == pytest.approx(pn.jerk_psd_m2ps5 * DT)
    assert q[EkfState.VEL.start, ax] == pytest.approx(pn.jerk_psd_m2ps5 * DT**2 / 2)
    assert q[0, 0] == pytest.approx(pn.pos_psd_m2ps * DT)
    np.testing.assert_allclose(ne.ProcessNoise(jerk_psd_m2ps5=4.0).matrix(DT)[ax, ax], 2 * q[ax, ax])
    p0 = ne.default_initial_covariance()
    assert np.all(np.linalg.eigvalsh(p0) > 0)
    with pytest.raises(ValueError):
        ne.ProcessNoise(pos_psd_m2ps=-1.0).matrix(DT)


@pytest.mark.parametrize("seed", range(3))
def test_update_equals_textbook_form(seed: int) -> None:
    """Selection/Cholesky/Joseph update == K = P H^T inv(S), P = (I - K H) P (optimal gain)."""
    rng = np.random.default_rng(seed)
    x = random_state(rng)
    p = random_spd(rng, EkfState.DIM)
    z = rng.normal(size=5)
    r = rng.uniform(0.01, 2.0, 5)
    h = ne.measurement_matrix()
    s = h @ p @ h.T + np.diag(r)
    k = p @ h.T @ np.linalg.inv(s)
    x_ref = x + k @ (z - h @ x)
    p_ref = (np.eye(8) - k @ h) @ p
    x_new, p_new = ne.update(x, p, z, r)
    np.testing.assert_allclose(x_new, x_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(p_new, p_ref, rtol=1e-9, atol=1e-10)


def test_predict_covariance() -> None:
    rng = np.random.default_rng(7)
    x = random_state(rng)
    p = random_spd(rng, EkfState.DIM)
    q = ne.default_process_noise()
    x1, p1 = ne.predict(x, p, q, DT)
    f = ne.process_jacobian(x, DT)
    np.testing.assert_allclose(x1, ne.process_model(x, DT))
    np.testing.assert_allclose(p1, f @ p @ f.T + q, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(p1, p1.T)


def test_update_pose_wraps_heading_innovation() -> None:
    x = np.zeros(EkfState.DIM)
    x[EkfState.YAW] = 6 * math.pi + 0.1  # three turns, unwrapped
    p = ne.default_initial_covariance() * 100
    x1, p1 = ne.update_pose(x, p, [3.0, -4.0], 1e-4, yaw_rad=0.05 - 2 * math.pi, yaw_var=1e-6)
    assert x1[EkfState.YAW][0] == pytest.approx(6 * math.pi + 0.05, abs=1e-3)
    np.testing.assert_allclose(x1[EkfState.POS], [3.0, -4.0], atol=1e-3)
    assert p1[0, 0] < 1e-4 and p1[2, 2] < 1e-6
    x2, _ = ne.update_pose(x, p, [3.0, -4.0], [1e-4, 1e-4])
    assert x2[EkfState.YAW][0] == x[EkfState.YAW][0]
    with pytest.raises(ValueError):
        ne.update_pose(x, p, [0.0, 0.0], 0.0)


def test_course_over_ground_is_the_yaw_plus_the_sideslip() -> None:
    """A receiver's course (the direction of travel) fused as such leaves a sliding car's yaw where it is; fused
    as the yaw, it turns the car by the sideslip angle (5.7 deg here)."""
    x = np.zeros(EkfState.DIM)
    x[EkfState.VEL] = (10.0, 1.0)  # beta = atan(0.1)
    p = ne.default_initial_covariance()
    p[EkfState.VEL, EkfState.VEL] = np.diag([1e-6, 1e-6])  # the velocity known: only the yaw can move
    beta = math.atan2(1.0, 10.0)
    pred, h = ne.course_measurement(x)
    assert pred == pytest.approx(beta) and h[EkfState.YAW.start] == 1.0
    assert h[EkfState.VEL.start + 1] == pytest.approx(10.0 / 101.0)  # d(course)/d(v_y) = v_x / v^2
    course, _ = ne.update_pose(x, p, [0.0, 0.0], 1.0, yaw_rad=beta, yaw_var=1e-6, course=True)
    as_yaw, _ = ne.update_pose(x, p, [0.0, 0.0], 1.0, yaw_rad=beta, yaw_var=1e-6)
    assert abs(course[EkfState.YAW][0]) < 1e-6
    assert as_yaw[EkfState.YAW][0] == pytest.approx(beta, rel=0.01)
    # the course also tells the sideslip where the yaw is known and v_y is not
    p2 = ne.default_initial_covariance()
    p2[EkfState.YAW, EkfState.YAW] = 1e-8
    x[EkfState.VEL] = (10.0, 0.0)
    slid, _ = ne.update_pose(x, p2, [0.0, 0.0], 1.0, yaw_rad=beta, yaw_var=1e-6, course=True)
    assert slid[EkfState.VEL.start + 1] == pytest.approx(1.0, rel=0.02)
    ekf = Ekf(x0=x)
    assert ekf.fuse_pose([0.0, 0.0], 1.0, yaw_rad=beta, yaw_var=1e-4, course=True) is StepStatus.SUCCESS


def test_circle_dead_reckoning() -> None:
    """Noise-free steady circle (a = 0 in the model's sense): 20 s, position within Euler error."""
    v, w = 10.0, 0.2
    ekf = Ekf(x0=np.array([0.0, 0.0, 0.0, w, v, 0.0, 0.0, 0.0]))
    z_var = np.array([0.01, 0.01, 0.1, 0.1, 1e-4])
    n = 1000
    for _ in range(n):
        assert ekf.step(np.array([v, 0.0, 0.0, 0.0, w]), z_var) is StepStatus.SUCCESS
    t = n * DT
    truth = np.array([v / w * math.sin(w * t), v / w * (1 - math.cos(w * t))])
    px, py, psi = ekf.pose
    # first-order (Euler) integration of the heading: error ~ v dt / 2 per radian turned
    assert math.hypot(px - truth[0], py - truth[1]) < 0.3
    assert psi == pytest.approx(w * t, abs=1e-9)
    pos_std, yaw_std = ekf.pose_std
    assert 0.0 < yaw_std < 0.1 and pos_std > ne.InitialStd().pos_m


def test_step_statuses() -> None:
    ekf = Ekf()
    z = np.array([5.0, 0.0, 0.0, 0.0, 0.0])
    r = np.full(5, 0.1)
    assert ekf.step() is StepStatus.PREDICT_ONLY
    assert ekf.step(z, r) is StepStatus.SUCCESS
    x_before = ekf.x.copy()
    for bad_z, bad_r in [
        (np.array([np.nan, 0, 0, 0, 0.0]), r),
        (z, np.array([0.1, 0.1, 0.0, 0.1, 0.1])),
        (z, -r),
        (z[:4], r[:4]),
        (z, None),
        (None, r),
        (z, np.array([0.1, 0.1, np.inf, 0.1, 0.1])),
    ]:
        assert ekf.step(bad_z, bad_r) is StepStatus.INPUT_INVALID
    # invalid input still predicts
    assert ekf.x[EkfState.POS][0] > x_before[0]
    assert ekf.fuse_pose([1.0, 2.0], 0.5) is StepStatus.SUCCESS
    assert ekf.fuse_pose([1.0, np.nan], 0.5) is StepStatus.INPUT_INVALID
    assert ekf.fuse_pose([1.0, 2.0], 0.5, yaw_rad=0.1) is StepStatus.INPUT_INVALID
    assert ekf.fuse_pose([1.0, 2.0], [0.5, 0.5, 0.5]) is StepStatus.INPUT_INVALID
    assert ekf.fuse_pose([1.0, 2.0], 0.5, yaw_rad=0.1, yaw_var=0.01) is StepStatus.SUCCESS
    assert ekf.n_resets == 0


def test_non_finite_state_resets_to_last_finite_pose() -> None:
    ekf = Ekf()
    r = np.full(5, 0.1)
    for _ in range(20):
        ekf.step(np.array([5.0, 0.0, 0.0, 0.0, 0.1]), r)
    good_pose = ekf.pose
    good_p = ekf.P.copy()
    # a state corrupted from outside is caught by the next step
    ekf.x[EkfState.VEL.start] = np.inf
    assert ekf.step() is StepStatus.RESET
    assert ekf.n_resets == 1
    assert ekf.pose == good_pose
    assert np.all(np.isfinite(ekf.P))
    assert np.all(np.diag(ekf.P) >= np.diag(good_p) * ne.RESET_COV_INFLATION * (1 - 1e-12))
    assert ekf.step(np.array([5.0, 0.0, 0.0, 0.0, 0.1]), r) is StepStatus.SUCCESS
    # a huge but finite measurement with a tiny variance: the next prediction overflows
    statuses = [ekf.step(np.full(5, 1e200), np.full(5, 1e-8)) for _ in range(3)]
    assert StepStatus.RESET in statuses
    assert ekf.n_resets >= 2
    assert np.all(np.isfinite(ekf.x)) and np.all(np.isfinite(ekf.P))
    assert ekf.step() in (StepStatus.PREDICT_ONLY, StepStatus.RESET)


def test_reset_and_shape_checks() -> None:
    ekf = Ekf()
    ekf.step(np.ones(5), np.ones(5))
    x0 = np.arange(8.0)
    ekf.reset(x0, np.eye(8))
    np.testing.assert_array_equal(ekf.x, x0)
    np.testing.assert_array_equal(ekf.P, np.eye(8))
    with pytest.raises(ValueError):
        ekf.reset(np.zeros(7))
    with pytest.raises(ValueError):
        Ekf(Q=np.eye(5))
    with pytest.raises(ValueError):
        ne.update(np.zeros(8), np.eye(8), np.zeros(4), np.ones(4))


log_var = st.floats(min_value=-8.0, max_value=6.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    log_vars=st.lists(st.lists(log_var, min_size=5, max_size=5), min_size=1, max_size=6),
    n_steps=st.integers(1, 200),
    predict_only_every=st.integers(0, 7),
)
def test_covariance_stays_symmetric_positive_definite(
    seed: int, log_vars: list[list[float]], n_steps: int, predict_only_every: int
) -> None:
    """Variances mixed from 1e-8 to 1e6, arbitrary legal states: P stays symmetric and PD."""
    rng = np.random.default_rng(seed)
    ekf = Ekf(x0=random_state(rng))
    var_table = 10.0 ** np.asarray(log_vars)
    for t in range(n_steps):
        z = random_state(rng)[list(schema.Z_TO_EKF_INDEX)]
        if predict_only_every and t % predict_only_every == 0:
            status = ekf.step()
        else:
            status = ekf.step(z, var_table[t % len(var_table)])
        assert status in (StepStatus.SUCCESS, StepStatus.PREDICT_ONLY)
        np.testing.assert_array_equal(ekf.P, ekf.P.T)
        np.linalg.cholesky(ekf.P)  # raises if not positive definite
    assert np.all(np.isfinite(ekf.x))


def test_edge_modules_import_without_torch() -> None:
    """The runtime side (EKF, guard) must not need torch."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import prml2_edge.ekf, prml2_edge.guard\n"
        "assert 'torch' not in [m.split('.')[0] for m in sys.modules if sys.modules[m] is not None]\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


# ---- calibration states ---------------------------------------------------------------------------

def _calibrated_run(offset: float, scale: float, steps: int, seed: int = 0, standstill: bool = False):
    """A filter fed the raw cues of a car with a known yaw-rate offset and wheel scale error, plus GNSS heading
    and position at 10 Hz (or, with ``standstill``, parked: zero-velocity updates only)."""
    rng = np.random.default_rng(seed)
    ekf = ne.Ekf(calibration=True)
    x_true = np.zeros(EkfState.DIM)
    x_true[EkfState.VEL.start] = 0.0 if standstill else 12.0
    for k in range(steps):
        omega = 0.0 if standstill else 0.15 * math.sin(0.3 * k * DT)
        x_true[EkfState.OMEGA_Z] = omega
        x_true = ne.process_model(x_true, DT)
        ekf.step()
        yaw = omega + offset + rng.normal(scale=0.003)
        wheel = (1.0 + scale) * x_true[EkfState.VEL.start] + rng.normal(scale=0.02)
        ekf.update_cues(yaw, 0.003**2, None if standstill else wheel, 0.02**2)
        if standstill:
            ekf.update_standstill(1e-4, 1e-6)
        elif k % 5 == 0:
            ekf.fuse_pose(x_true[EkfState.POS] + rng.normal(scale=0.5, size=2), 0.25,
                          float(x_true[EkfState.YAW][0]) + rng.normal(scale=0.01), 1e-4)
    return ekf


def test_calibration_converges_to_known_offsets_with_gnss() -> None:
    ekf = _calibrated_run(offset=math.radians(-0.4), scale=0.01, steps=1500)  # 30 s of GNSS
    b = ekf.cal[0]
    assert abs(math.degrees(b) + 0.4) < 0.05
    assert math.sqrt(ekf.cal_cov[0, 0]) < math.radians(0.05)  # and it knows it
    # the wheel scale is a known correction in the cues; only its direct measurement teaches it
    assert ekf.cal[1] == 0.0
    for _ in range(10):
        ekf.update_wheel_scale(0.01, 0.003**2)
    assert ekf.cal[1] == pytest.approx(0.01, abs=1e-4) and math.sqrt(ekf.cal_cov[1, 1]) < 0.002


def test_standstill_reveals_the_yaw_offset_without_gnss() -> None:
    ekf = _calibrated_run(offset=math.radians(0.3), scale=0.0, steps=250, standstill=True)
    assert abs(math.degrees(ekf.cal[0]) - 0.3) < 0.05  # 5 s parked, 0.17 deg/s noise per sample
    np.testing.assert_allclose(ekf.x[EkfState.VEL], 0.0, atol=1e-3)
    # the wheel scale is not observable at standstill: its uncertainty stays at the prior
    assert math.sqrt(ekf.cal_cov[1, 1]) == pytest.approx(ne.CalibrationStd().wheel_scale, rel=1e-3)


def test_calibrated_filter_with_known_zero_errors_matches_the_plain_filter() -> None:
    """Calibration states pinned at zero (a vanishing prior and process noise): the plain filter's numbers."""
    rng = np.random.default_rng(3)
    tiny = 1e-12
    plain = ne.Ekf()
    cal = ne.Ekf(calibration=True, cal_std=ne.CalibrationStd(tiny, tiny, tiny),
                 cal_noise=ne.CalibrationNoise(0.0, 0.0, tiny, 5.0))
    assert cal.x.shape == (schema.CalState.FULL_DIM,) and cal.P.shape == (11, 11)
    for _ in range(200):
        z = rng.normal(size=5)
        var = 10.0 ** rng.uniform(-3, 0, 5)
        plain.step(z, var)
        cal.step(z, var)
    np.testing.assert_allclose(cal.x[: EkfState.DIM], plain.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cal.P[: EkfState.DIM, : EkfState.DIM], plain.P, rtol=0, atol=1e-9)
    with pytest.raises(RuntimeError, match="calibration"):
        plain.update_cues(0.1, 1e-4)


def test_set_calibration_restores_states_and_covariance() -> None:
    ekf = ne.Ekf(calibration=True)
    ekf.set_calibration([0.01, -0.02, 0.0], np.diag([1e-6, 1e-6, 1e-5]))
    np.testing.assert_array_equal(ekf.cal, [0.01, -0.02, 0.0])
    np.testing.assert_allclose(np.diag(ekf.cal_cov), [1e-6, 1e-6, 1e-5])
    assert ekf.update_cues(float("nan"), 1e-4) is ne.StepStatus.INPUT_INVALID
    assert ekf.update_standstill(-1.0) is ne.StepStatus.INPUT_INVALID


def test_one_update_of_model_and_cues_is_the_two_updates_in_turn() -> None:
    """Ekf.step_with_cues (the runtime's hot path) against step + update_cues: the same estimate over a drive
    with an offset gyro and fast wheels, and the same statuses when the model's z or a cue is missing or bad."""
    rng = np.random.default_rng(11)
    joint, seq = ne.Ekf(calibration=True), ne.Ekf(calibration=True)
    for ekf in (joint, seq):
        ekf.x[EkfState.VEL.start] = 12.0
    for k in range(1500):
        omega = 0.15 * math.sin(0.3 * k * DT)
        z = np.array([12.0, 0.0, 0.0, 0.0, omega]) + rng.normal(scale=0.01, size=5)
        z_var = np.full(5, 1e-3) if k % 7 else np.full(5, np.nan)  # now and then an invalid model output
        yaw = omega + 0.007 + rng.normal(scale=0.003) if k % 11 else None  # now and then no gyro
        wheel = 12.12 + rng.normal(scale=0.02)
        status, cues = joint.step_with_cues(z, z_var, yaw, 0.003**2, wheel, 0.02**2)
        assert status is seq.step(z, z_var)
        assert cues == (seq.update_cues(yaw, 0.003**2, wheel, 0.02**2) is StepStatus.SUCCESS)
    np.testing.assert_allclose(joint.x, seq.x, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(joint.P, seq.P, rtol=1e-7, atol=1e-12)
    assert abs(joint.cal[0] - 0.007) < 0.002  # the offset was learned from the model against the gyro
    assert joint.step_with_cues(None, None) == (StepStatus.PREDICT_ONLY, False)
    assert joint.step_with_cues(None, None, float("nan"), 1e-4) == (StepStatus.PREDICT_ONLY, False)
    assert joint.step_with_cues(np.zeros(5), -np.ones(5), 0.0, 1e-4) == (StepStatus.INPUT_INVALID, True)
    with pytest.raises(RuntimeError, match="calibration"):
        ne.Ekf().step_with_cues(np.zeros(5), np.ones(5), 0.0, 1e-4)


def test_the_innovation_log_keeps_each_cues_innovation_and_its_predicted_variance() -> None:
    """Ekf.innovation_log (benchmarks/innovation_check.py): per update, which rows were there, the innovations and
    diag(H P H^T + R); on a consistent simulated drive the normalised innovations have unit variance."""
    rng = np.random.default_rng(5)
    ekf = ne.Ekf(calibration=True)
    ekf.x[EkfState.VEL.start] = 10.0
    ekf.innovation_log = []
    for k in range(3000):
        yaw = 0.01 + rng.normal(scale=0.003) if k % 2 else None
        ekf.step_with_cues(np.array([10.0, 0.0, 0.0, 0.0, 0.0]) + rng.normal(scale=0.05, size=5), np.full(5, 0.05**2),
                           yaw, 0.003**2, 10.0 + rng.normal(scale=0.02), 0.02**2)
    keys = {key for key, _, _ in ekf.innovation_log}
    assert keys == {(True, True, True), (True, False, True)}
    for (model, yaw, wheel), nu, s in ekf.innovation_log[:2]:
        assert nu.shape == s.shape == (5 * model + yaw + wheel,) and (s > 0).all()
    e = np.array([nu[:5] / np.sqrt(s[:5]) for _, nu, s in ekf.innovation_log[500:]])
    np.testing.assert_allclose((e**2).mean(axis=0)[[0, 1]], 1.0, atol=0.15)  # v_x, v_y: nothing else measures v_y
    assert ne.Ekf(calibration=True).innovation_log is None  # off unless asked
