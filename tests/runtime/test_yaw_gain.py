"""The CAN yaw rate's gain learned from GNSS heading over drives (issue 26): the estimator, the unit's history the
evaluation gives a drive, the calibration file's section and the filter dividing the cue by it."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.evaluation.unit_history import WheelScaleHistory, feed, gain_evidence, wheel_scale_evidence
from prml2_edge.runtime.calibration import CalibrationFile
from prml2_edge.runtime.yaw_gain import YawGainEstimator

HEADING_STD = math.radians(2.0)
YAW = schema.SIGNAL_BY_NAME["yaw_rate_radps"].index


@pytest.mark.parametrize("vehicle, gain", [("compact_fwd", 0.02), ("rwd_sedan", -0.015)])
def test_the_gain_is_learned_from_course_over_ground_on_a_simulated_drive(vehicle, gain):
    """Five minutes of mixed driving with 2 deg course-over-ground fixes: the gain to 0.3 % (measured rms error
    0.06 % over seeds; the sideslip regressors matter: without them the course's sideslip left up to 1.2 %)."""
    drive = simulate_drive(5.0, 1.0, 11, "mixed", "gain_test", sensor_errors={"yaw_scale_error": gain},
                           vehicle=vehicle)
    est = YawGainEstimator(HEADING_STD)
    feed(est, drive, np.random.default_rng(0))
    assert est.n_chunks >= 3
    assert est.gain == pytest.approx(gain, abs=0.003)
    assert est.std < 0.003


def _turning_chunk(est: YawGainEstimator, gain: float, jump_at: float | None = None) -> None:
    """40 s of S-curves (+-10 deg/s) at 10 +- 2 m/s, the gyro reading (1 + gain) times it, exact 10 Hz heading
    fixes (no sideslip). A steady turn would teach nothing: its heading rate is the offset's too."""
    rate, dt = math.radians(10.0), schema.DT_S
    for i in range(2000):
        t = i * dt
        r = rate * math.sin(0.2 * t)
        est.yaw_rate((1.0 + gain) * r, dt)
        if i % 5 == 0:
            psi = rate * (1.0 - math.cos(0.2 * t)) / 0.2
            if jump_at is not None and t >= jump_at:
                psi += math.radians(30.0)
            est.heading(t, psi, r, 10.0 + 2.0 * math.sin(0.5 * t))
    est.close_chunk()


def test_a_chunk_with_a_heading_jump_is_dropped_and_straight_driving_teaches_nothing():
    est = YawGainEstimator(math.radians(0.5))
    _turning_chunk(est, 0.03)
    assert est.n_chunks == 1 and est.gain == pytest.approx(0.03, abs=0.002)
    _turning_chunk(est, 0.03, jump_at=20.0)
    assert est.n_dropped == 1 and est.n_chunks == 1
    straight = YawGainEstimator(HEADING_STD)
    for i in range(3000):
        straight.yaw_rate(0.0, schema.DT_S)
        if i % 5 == 0:
            straight.heading(i * schema.DT_S, 0.2, 0.0, 10.0)
    straight.close_chunk()
    assert straight.gain == 0.0 and straight.info == 0.0


def test_a_coarse_gyro_has_no_history_and_a_fine_one_has_some():
    """The reference car's 1.28 deg/s steps follow the turn: the runtime does not learn its gain, nor does its
    simulated history; a fine gyro's history is evidence the estimator restores."""
    coarse = simulate_drive(0.5, 1.0, 3, "mixed", "coarse", sensor_errors={"yaw_scale_error": 0.01},
                            vehicle="reference")
    coarse.meta.setdefault("vehicle", "reference")
    assert gain_evidence(coarse, minutes=2.0) is None
    fine = simulate_drive(0.5, 1.0, 3, "mixed", "fine", sensor_errors={"yaw_scale_error": 0.02},
                          vehicle="compact_fwd")
    info, info_c = gain_evidence(fine, minutes=4.0, drives=2)
    est = YawGainEstimator(HEADING_STD)
    est.restore(info, info_c)
    assert info > 0.0 and est.gain == pytest.approx(0.02, abs=0.006)


def test_a_cars_history_keeps_its_tyres_and_teaches_the_file_its_wheel_scale():
    """Tyres 1 % large on every wheel: the history's GNSS baselines (the runtime's rule: the cue axle rolling free,
    not braking) find the tyres' scale, which a coarse gyro does not prevent; a RWD car's cue is its front axle,
    steer-corrected. Braking rows would read it low: the brake's slip is not the tyres'."""
    for vehicle, error in (("reference", 0.01), ("rwd_sedan", -0.01)):
        drive = simulate_drive(0.5, 1.0, 5, "mixed", f"tyres_{vehicle}", sensor_errors={"wheel_radius_error": error},
                               vehicle=vehicle)
        scale, var = wheel_scale_evidence(drive, minutes=8.0, drives=2)
        sd = math.sqrt(var)
        cue = WheelScaleHistory(**({"driven_axle": "rear"} if vehicle == "rwd_sedan" else {})).cue_speed(drive.onboard)
        moving = cue > 5.0
        free = moving & (np.abs(drive.z_gt[:, schema.Z.A_X]) <= 0.3)
        ratio = {name: cue[m].sum() / drive.z_gt[m, 0].sum() - 1.0 for name, m in (("free", free), ("all", moving))}
        assert abs(ratio["free"] - error) < 0.0005 and ratio["all"] < ratio["free"] - 0.0005  # braking reads low
        assert sd < 0.005 and abs(scale - error) < 3 * sd and abs(scale) > 2 * sd, (vehicle, scale, sd)


def test_the_calibration_file_keeps_the_gain_evidence_and_reads_files_without_it(tmp_path, caplog):
    cal, cov = np.array([0.001, 0.01, 0.0]), np.diag([1e-8, 1e-6, 1e-6])
    est = YawGainEstimator(math.radians(0.5))
    _turning_chunk(est, 0.02)
    f = CalibrationFile(tmp_path / "cal.json", "car")
    assert f.save(cal, cov, t_s=60.0, yaw_gain=est.state())
    g = CalibrationFile(tmp_path / "cal.json", "car")
    assert g.load() is not None and g.yaw_gain == pytest.approx((est.info, est.info_c))
    assert json.loads((tmp_path / "cal.json").read_text())["readable"]["yaw_rate_gain_pct"] == pytest.approx(2.0,
                                                                                                           abs=0.2)
    assert f.save(cal, cov)  # a file without the section (an older runtime's): the rest restores, no gain
    h = CalibrationFile(tmp_path / "cal.json", "car")
    assert h.load() is not None and h.yaw_gain is None and h.last_error is None
    doc = json.loads((tmp_path / "cal.json").read_text())
    doc["yaw_gain"] = {"info": "many"}
    (tmp_path / "cal.json").write_text(json.dumps(doc))
    bad = CalibrationFile(tmp_path / "cal.json", "car")
    assert bad.load() is not None and bad.yaw_gain is None
    assert "yaw_gain section refused" in bad.last_error and "gyro gain starts from its prior" in caplog.text


def test_the_filter_divides_the_yaw_cue_by_the_restored_gain(tmp_path):
    """A drive whose gyro reads 5 % high: with the gain its calibration file learned, the calibrating filter's pose
    is the one on the true gyro; without it (or with the option off) the heading turns 5 % too far."""
    from prml2_edge.data.datasets import generate_dataset, load_dataset
    from prml2_edge.evaluation.protocol import ModelSpec, run_window, split_tasks
    from tests.runtime_models import make_kinematic_model

    recipe = {"name": "gain", "drives": [{"name": "dry_a", "family": "lateral", "mu": 1.0, "seed": 6,
                                          "minutes": 1.5, "role": "dry"}]}
    data = load_dataset(generate_dataset(tmp_path / "data", recipe, workers=1, progress=False))
    task = max(split_tasks(data, "test", 8.0), key=lambda t: np.abs(np.diff(t.pose_gt[:, 2])).sum())
    # the drive's gyro is the reference car's 1.28 deg/s one, which by default counts as coarse from its first step:
    # then the model, which reads the same high gyro, carries the yaw rate and no gain is learned for it
    # (yaw_gain_max_resolution_radps). Counted fine, the gyro's cue carries it: what this test is about.
    spec = ModelSpec("kin", "onnx", str(make_kinematic_model(tmp_path / "kin.onnx")), calibration=True,
                     filter=(("coarse_until_fine_step", False),))
    onboard = task.onboard.copy()
    onboard[:, YAW] *= 1.05
    high = replace(task, onboard=onboard)
    truth = run_window(spec, task).pose
    learned = run_window(spec, replace(high, yaw_gain=(1e6, 1e6 / 1.05))).pose
    unknown = run_window(spec, high).pose
    off = run_window(replace(spec, filter=(*spec.filter, ("yaw_gain_calibration", False))),
                     replace(high, yaw_gain=(1e6, 1e6 / 1.05))).pose
    err = {name: float(np.abs(p[-1, 2] - truth[-1, 2])) for name, p in
           (("learned", learned), ("unknown", unknown), ("off", off))}
    assert err["unknown"] > math.radians(0.2) and err["off"] == pytest.approx(err["unknown"])
    assert err["learned"] < 0.2 * err["unknown"]


def test_the_drive_is_one_draw_about_its_car_not_its_cars_mean(monkeypatch):
    """``unit_history.DRIVE_DRAW``: the history drives vary about the car's gain and cue offsets, and the car's are
    the drive's plus one per-drive variation, the same shift for every history drive; without it the history
    varies about the drive's own values (the drive at its car's mean, as before)."""
    from prml2_edge.evaluation import unit_history

    drive = simulate_drive(0.3, 1.0, 4, "mixed", "draw_car", vehicle="compact_fwd",
                           sensor_errors={"yaw_scale_error": 0.01, "lat_offset_mps2": 0.1,
                                          "steer_offset_rad": math.radians(1.0)})
    real = simulate_drive
    seen: dict[bool, list[dict]] = {}

    def spy(*args, sensor_errors, **kwargs):
        seen[unit_history.DRIVE_DRAW].append(dict(sensor_errors))
        return real(*args, sensor_errors=sensor_errors, **kwargs)

    monkeypatch.setattr("prml2_edge.data.simulate.simulate_drive", spy)
    for draw in (False, True):
        monkeypatch.setattr(unit_history, "DRIVE_DRAW", draw)
        seen[draw] = []
        assert unit_history.gain_evidence(drive, minutes=0.8, drives=4) is not None
    for name in ("yaw_scale_error", "lat_offset_mps2", "steer_offset_rad"):
        shift = [a[name] - b[name] for a, b in zip(seen[True], seen[False], strict=True)]
        assert len(shift) == 4 and np.ptp(shift) < 1e-12 and abs(shift[0]) > 0.0, name
