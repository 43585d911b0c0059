"""The Toyota RAV4 2017-18 map on opendbc's toyota_new_mc_pt_generated.dbc: a drive encoded with it replays
with every frame accounted, and matches the project-DBC replay of the same drive within what the Toyota
DBC does to the signals (its resolution and its bus rates), brake pressure fed as the map's substitute."""

from __future__ import annotations

import numpy as np
import pytest

from prml2_edge import schema
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.can.signal_map import load_map_and_dbc, shipped_map_path
from prml2_edge.data.simulate import simulate_drive
from prml2_edge.runtime.initial_pose import InitialPose
from prml2_edge.runtime.pipeline import MemorySink, Pipeline, run_source
from prml2_edge.runtime.source import LogReplay
from prml2_edge.schema import psi_rad_to_heading_deg

BRAKE = schema.SIGNAL_BY_NAME["brake_pressure_bar"].index


def resolution_si(smap, db) -> np.ndarray:
    res = np.zeros(schema.NUM_SIGNALS)
    for spec in smap.present:
        msg = db.get_message_by_name(spec.message)
        res[schema.SIGNAL_BY_NAME[spec.name].index] = max(abs(msg.get_signal_by_name(p).scale * w * spec.scale)
                                                          for p, w in spec.summed_parts)
    return res


def replay(log, map_path, dbc, pose):
    sink = MemorySink()
    pipeline = Pipeline.build(map=map_path, dbc=dbc, initial_pose=pose, sinks=[sink])
    rows = []
    step = pipeline.localizer.step

    def spy(values, valid, *a, **k):
        rows.append(np.array(values))
        return step(values, valid, *a, **k)

    pipeline.localizer.step = spy
    with LogReplay(log) as source:
        run_source(pipeline, source)
    return pipeline.summary(), sink.arrays(), np.array(rows)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, shared_dir):
    root = tmp_path_factory.mktemp("toyota")
    dbc = shared_dir / "dbc" / "opendbc" / "toyota_new_mc_pt_generated.dbc"
    drive = simulate_drive(0.5, 1.0, 11, family="mixed")  # 30 s
    toyota_info = encode_drive_to_log(drive, root / "toyota.log", signal_map_path=shipped_map_path("toyota_rav4_2018"),
                                      dbc_path=dbc)
    encode_drive_to_log(drive, root / "project.log")
    # the project map with brake pressure fed as the Toyota map feeds it (the car has none)
    src = shipped_map_path("prml2_onboard").read_text()
    brake = src[src.index("[signals.brake_pressure_bar]"):src.index("[signals.wheel_speed_fl_mps]")]
    no_brake = root / "prml2_no_brake.toml"
    no_brake.write_text(src.replace(brake, "[signals.brake_pressure_bar]\nabsent = true\n"
                                                 'substitute = "wheel_deceleration"\n\n')
                        .replace('dbc = "prml2_onboard.dbc"',
                                 f'dbc = "{shipped_map_path("prml2_onboard").parent.parent / "prml2_onboard.dbc"}"'))
    pose = InitialPose(float(drive.pose_gt[0, 0]), float(drive.pose_gt[0, 1]),
                       psi_rad_to_heading_deg(float(drive.pose_gt[0, 2])), source="test")
    toyota = replay(root / "toyota.log", "toyota_rav4_2018", dbc, pose)
    project = replay(root / "project.log", str(no_brake), None, pose)
    smap, db, _ = load_map_and_dbc(shipped_map_path("toyota_rav4_2018"), dbc)
    return drive, toyota_info, toyota, project, resolution_si(smap, db)


def test_every_toyota_frame_is_accounted_and_used(runs):
    drive, info, (summary, _, _), _, _ = runs
    fr = summary["frames"]
    assert fr["received"] == info["frames"] == fr["used"] and fr["balanced"] and not fr["rejected_by_reason"]
    assert set(fr["used_by_message"]) == {"SPEED", "STEER_ANGLE_SENSOR", "KINEMATICS", "WHEEL_SPEEDS"}
    assert summary["signals_missing"] == [] and summary["model_used_steps"] > 0
    assert fr["used_by_message"]["KINEMATICS"] == pytest.approx(83.0 * drive.duration_s, abs=2)
    assert fr["used_by_message"]["SPEED"] == pytest.approx(41.5 * drive.duration_s, abs=2)


def test_toyota_replay_matches_the_project_dbc_replay_within_the_toyota_quantisation(runs):
    drive, _, (_, tx, trows), (_, px, prows), res = runs
    n = min(len(trows), len(prows))
    assert n >= len(drive) - 1
    # per signal: half the Toyota step (the project DBC's is 10-100x finer) plus one sample of change, since an
    # 83 or 41.5 Hz message holds a sample a different 50 Hz row long than the project's 100 / 50 / 25 Hz ones
    change = np.max(np.abs(np.diff(drive.onboard, axis=0)), axis=0)
    tol = 0.5 * res + 2 * change + 1e-9
    diff = np.abs(trows[:n] - prows[:n])
    diff[:, BRAKE] = 0.0  # fed as the substitute in both
    assert np.all(diff <= tol), (diff.max(axis=0), tol)
    # the trajectories: what those input differences cost with the shipped model, within 2 % of the distance
    distance = float(np.sum(np.hypot(*np.diff(drive.pose_gt[:, :2], axis=0).T)))
    pos = np.hypot(*(tx["x"][:n, :2] - px["x"][:n, :2]).T)
    print(f"Toyota vs project-DBC replay: max {pos.max():.2f} m over {distance:.0f} m")
    assert distance > 200 and float(pos.max()) <= 0.02 * distance, (pos.max(), distance)
