"""The paper's evaluation protocol on top of :meth:`StreamingLocalizer.run_arrays` (one code path).

Segments: the time-ordered 70:10:20 ``val``/``test`` parts of every dry drive, and whole snow
drives (``snow``). Dead reckoning (method.md "Evaluation protocol"): non-overlapping 60 s windows
inside a segment, each starting from the true pose and dynamic state; the L - 1 rows before the
start only fill the model's window (onboard signals a live system would already have), so the
model is warm at the first step. Every window is one ``run_arrays`` call with GNSS fusion off.

Table 1 (z RMSE) uses the model outputs the localiser consumed: the newest decoder output of
each window, after the physics guard (the guard off only in the ablation).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.dead_reckoning import DeadReckoningErrors, path_length_m
from prml2_edge.ekf.numpy_ekf import default_process_noise, mahalanobis2, wrap_angle
from prml2_edge.evaluation.consumer_gnss import (
    GNSS_HEADING_MIN_SPEED_MPS,
    GNSS_HEADING_STD_DEG,
    GNSS_POS_STD_M,
    GNSS_RATE_HZ,
)
from prml2_edge.evaluation.osd import StandstillBias, drive_bias
from prml2_edge.evaluation.standstill_restore import STANDSTILL_RESTORES, restore_standstill_calibration
from prml2_edge.guard import physics_guard
from prml2_edge.runtime.yaw_resolution import YawResolution
from prml2_edge.schema import EkfState, Z

DR_WINDOW_S = 60.0  # dead-reckoning window [s]
NO_GUARD_A_MAX_MPS2 = 1e9  # "guard off": an acceleration bound never reached (finite: inf / inf is NaN)


@dataclass(frozen=True)
class ModelSpec:
    """A method to evaluate.

    ``kind`` is ``"onnx"`` (``path`` an exported model) or ``"osd"`` (the OSD baseline);
    ``guard`` False switches the acceleration bound of the physics guard off (ablation);
    ``const_var`` (5,) replaces the model's variances (ablation "uncertainty off", and the OSD
    baseline's measurement noise); ``q_scale`` scales the EKF process noise ``Q``.
    """

    name: str
    kind: str
    path: str | None = None
    guard: bool = True
    const_var: tuple[float, ...] | None = None
    q_scale: float = 1.0
    calibration: bool = False  # the filter's calibration states and raw cues (runtime/filter.py)
    # with calibration: start from the standstill offset the OSD baseline uses (restore_standstill_calibration), known
    # as the runtime's own standstill update leaves it ("runtime") or as a calibration file restores it ("file")
    standstill_calibration: bool = True
    standstill_restore: str = "file"
    # with calibration: start from the wheel scale the car's earlier drives taught (the task's wheel_scale)
    wheel_scale_history: bool = True
    # with calibration: the cue estimator has run over the drive so far (the task's ``before`` rows and its history
    # rows), as the runtime's has by the time the window starts; False (before 2026-12-07): it starts at the window
    cue_drive_so_far: bool = True
    filter: tuple[tuple[str, object], ...] = ()  # LocalizerConfig fields to override, (name, value) pairs

    def __post_init__(self) -> None:
        if self.kind not in ("onnx", "osd"):
            raise ValueError(f"model kind must be 'onnx' or 'osd', got {self.kind!r}")
        if self.kind == "onnx" and not self.path:
            raise ValueError(f"model {self.name!r}: an ONNX model needs a path")
        if self.standstill_restore not in STANDSTILL_RESTORES:
            raise ValueError(f"model {self.name!r}: standstill_restore must be one of {STANDSTILL_RESTORES}, "
                             f"got {self.standstill_restore!r}")


@dataclass(frozen=True)
class WindowTask:
    """One dead-reckoning window of a drive.

    ``onboard`` (h + n, 9) [SI] with ``h`` history rows before the start; ``t_s`` (n,) [s];
    ``z_gt`` (n, 5), ``pose_gt`` (n, 3) [x east m, y north m, psi rad] from the start on;
    ``start`` the start row in the drive; ``mu`` road friction for the guard; ``bias`` the
    OSD baseline's standstill biases for this drive.
    """

    split: str
    drive: str
    start: int
    history: int
    onboard: np.ndarray
    t_s: np.ndarray
    z_gt: np.ndarray
    pose_gt: np.ndarray
    mu: float
    bias: StandstillBias
    # deployment protocol: GNSS-aided rows before the outage (onboard has them after the history rows;
    # their true pose (preroll, 3) and z (preroll, 5) make the fixes and the start state)
    preroll: int = 0
    pre_pose_gt: np.ndarray | None = None
    pre_z_gt: np.ndarray | None = None
    # the evidence on the CAN yaw rate's gain the car's calibration file holds from its earlier drives:
    # (information, information-weighted sum), evaluation.unit_history; None: no history
    yaw_gain: tuple[float, float] | None = None
    # the drive's car when it is one of the simulated fleet ("": not known); its driven axle and steering ratio go to
    # the runtime's filter, as a user's config would give them (Car.filter_settings)
    vehicle: str = ""
    # the cue axle's wheel scale the same history's GNSS baselines taught the file: (scale, variance); None: none
    wheel_scale: tuple[float, float] | None = None
    # the cues' own offsets the same history taught the cue estimator: (values (3,), cov (3, 3)); None: none
    cue_offsets: tuple[np.ndarray, np.ndarray] | None = None
    # the drive's CAN signals before ``onboard`` (its rows from the drive's start; with ``onboard``'s history rows,
    # the drive so far); None: not kept
    before: np.ndarray | None = None

    @property
    def key(self) -> str:
        return f"{self.split}/{self.drive}@{self.start}" + (f"+{self.preroll}" if self.preroll else "")

    @property
    def distance_m(self) -> float:
        """Distance travelled over the window [m] (ground truth)."""
        return path_length_m(self.pose_gt)


@dataclass
class WindowResult(DeadReckoningErrors):
    """One model on one window: estimated pose (n, 3), errors (n,), consumed model z (n, 5) (NaN where none)."""

    model: str
    task_key: str
    split: str
    pose: np.ndarray
    pos_error_m: np.ndarray
    yaw_error_rad: np.ndarray
    distance_m: float
    z: np.ndarray
    guard_fired: int = 0
    model_steps: int = 0
    mahal2: np.ndarray | None = None  # (n,) squared Mahalanobis distance of the 2D position error
    cal: np.ndarray | None = None  # (3,) calibration states at the outage start (NaN when off)
    z_var: np.ndarray | None = None  # (n, 5) the model's variance for the consumed z (NaN where none)


class InMemorySplits:
    """The one method of a dataset :func:`split_tasks` needs, for drives simulated on the fly: whole drives per
    split name (a benchmark's re-simulated or extra drives, never written to disk)."""

    def __init__(self, by_split: dict[str, list]) -> None:
        self.by_split = by_split

    def segments(self, split: str) -> list[tuple]:
        return [(d, 0, len(d)) for d in self.by_split.get(split, [])]


def filter_override(text: str) -> tuple[str, float]:
    """``FIELD=NUMBER`` as a :attr:`ModelSpec.filter` pair: a numeric :class:`LocalizerConfig` field. A benchmark's
    command-line parser; ``ValueError`` says in one line what is wrong."""
    from dataclasses import fields

    from prml2_edge.runtime.localizer import LocalizerConfig

    name, sep, value = text.partition("=")
    if not sep or name not in {f.name for f in fields(LocalizerConfig)}:
        raise ValueError(f"{text!r}: want FIELD=NUMBER with FIELD a LocalizerConfig field "
                         "(prml2_edge/runtime/localizer_config.py)")
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"{text!r}: the value must be a number") from None
    LocalizerConfig(**{name: number})  # a value the config refuses (its one line) is refused here, not in a worker
    return name, number


def split_tasks(dataset, split: str, window_s: float = DR_WINDOW_S, window_len: int = schema.WINDOW_LEN,
                max_windows: int | None = None, preroll_s: float = 0.0,
                history_min: float = 0.0) -> list[WindowTask]:
    """Non-overlapping dead-reckoning windows of ``split`` (``val``, ``test``, ``snow`` or ``heldout``).

    A window needs ``window_len - 1`` rows of history before its start; the first window of a
    segment starts at ``max(segment start, window_len - 1)``. ``max_windows`` caps the count
    per segment (None: all). ``preroll_s`` > 0 (the deployment protocol): each window is preceded
    by that much GNSS-aided driving, whose rows (and history before them) may reach back before
    the segment (onboard signals a car would have had; their ground truth only makes the fixes).
    ``history_min`` > 0: each simulated drive's car also has that many minutes of earlier drives, whose GNSS
    heading taught its calibration file the gyro's gain (:func:`~prml2_edge.evaluation.unit_history.gain_evidence`)
    and the wheel scale (:func:`~prml2_edge.evaluation.unit_history.wheel_scale_evidence`), and the cues' own
    offsets (:func:`~prml2_edge.evaluation.unit_history.cue_evidence`).
    """
    from prml2_edge.evaluation.unit_history import cue_evidence, gain_evidence, wheel_scale_evidence

    steps = int(round(window_s / schema.DT_S))
    pre = int(round(preroll_s / schema.DT_S))
    hist = window_len - 1
    tasks: list[WindowTask] = []
    for drive, a, b in dataset.segments(split):
        if not drive.has_ground_truth:
            continue
        mu = float(drive.meta.get("mu", 1.0))
        evidence = gain_evidence(drive, history_min) if history_min > 0.0 else None
        scale = wheel_scale_evidence(drive, history_min) if history_min > 0.0 else None
        cues = cue_evidence(drive, history_min) if history_min > 0.0 else None
        starts = list(range(max(a, hist + pre), b - steps + 1, steps))
        if max_windows is not None:
            starts = starts[:max_windows]
        for start in starts:
            # OSD biases from standstill before the window (causal), else from the whole drive
            bias = drive_bias(drive.onboard[:start], drive.onboard)
            sl = slice(start, start + steps)
            ps = slice(start - pre, start)
            tasks.append(WindowTask(split, drive.name, start, hist,
                                    drive.onboard[start - pre - hist : start + steps],
                                    drive.t_s[sl], drive.z_gt[sl], drive.pose_gt[sl], mu, bias, pre,
                                    drive.pose_gt[ps] if pre else None, drive.z_gt[ps] if pre else None,
                                    evidence, str(drive.meta.get("vehicle", "")), scale, cues,
                                    drive.onboard[: start - pre - hist]))
    return tasks


# Deployment protocol (method.md deviation, docs/deviations.md): fixes as a consumer receiver gives them
# (evaluation.consumer_gnss).
DEPLOYMENT_PREROLL_S = 30.0  # GNSS-aided driving before each outage window [s]


def simulated_fixes(task: WindowTask) -> dict[int, object]:
    """GNSS fixes for the pre-roll of a deployment task, by row index of ``task.onboard``: 10 Hz, position
    noise 1.5 m per axis, and while moving the course over ground (the direction of travel, ``psi + atan2(v_y,
    v_x)``, as a single-antenna receiver gives it; 2 deg noise); deterministic per task."""
    import zlib

    from prml2_edge.runtime.rows import GnssFix
    from prml2_edge.schema import psi_rad_to_heading_deg

    if not task.preroll:
        return {}
    rng = np.random.default_rng(zlib.crc32(task.key.encode()))
    every = int(round(schema.SAMPLE_RATE_HZ / GNSS_RATE_HZ))
    fixes = {}
    for j in range(every, task.preroll, every):  # row 0 is the start pose itself
        x, y, psi = task.pre_pose_gt[j]
        noise = rng.normal(0.0, GNSS_POS_STD_M, 2)
        vx, vy = (float(v) for v in task.pre_z_gt[j, Z.VEL])
        moving = math.hypot(vx, vy) >= GNSS_HEADING_MIN_SPEED_MPS
        course = float(schema.course_over_ground(float(psi), vx, vy))
        heading = psi_rad_to_heading_deg(course + math.radians(rng.normal(0.0, GNSS_HEADING_STD_DEG)))
        fixes[task.history + j] = GnssFix(t_s=float((task.history + j) * schema.DT_S), x_m=float(x + noise[0]),
                                          y_m=float(y + noise[1]), heading_deg=heading if moving else None,
                                          valid=True)
    return fixes


# ---- running one window (worker side) ------------------------------------------------------------

_ONNX_CACHE: dict[str, object] = {}


def _onnx(path: str):
    from prml2_edge.runtime.inference import OnnxModel

    if path not in _ONNX_CACHE:
        _ONNX_CACHE[path] = OnnxModel(path, threads=1)
    return _ONNX_CACHE[path]


def forget_model(path: str) -> None:
    """Drop the cached session of ``path`` (its file was rewritten)."""
    _ONNX_CACHE.pop(str(path), None)


def build_model(spec: ModelSpec, bias: StandstillBias | None = None):
    """The runtime model of ``spec`` (an :class:`OnnxModel`, :class:`OsdModel` or a wrapper)."""
    from prml2_edge.evaluation.models import ConstantVarianceModel, OsdModel

    if spec.kind == "osd":
        var = np.ones(schema.NUM_STATES) if spec.const_var is None else np.asarray(spec.const_var)
        return OsdModel(var, bias)
    model = _onnx(str(spec.path))
    if spec.const_var is not None:
        model = ConstantVarianceModel(model, np.asarray(spec.const_var))
    return model


def process_noise(model, q_scale: float = 1.0) -> np.ndarray:
    """EKF ``Q`` (8, 8): the model's metadata ``ekf_process_noise`` (trained with it), else the default; scaled."""
    meta_q = getattr(getattr(model, "metadata", None), "ekf_process_noise", None)
    q = np.asarray(meta_q, dtype=np.float64) if meta_q is not None else default_process_noise(schema.DT_S)
    return q * float(q_scale)


def car_settings(vehicle: str) -> dict:
    """The runtime settings a user gives for ``vehicle`` when it is a car of the simulated fleet ({} otherwise)."""
    from prml2_edge.data.simulate.fleet import CARS

    return CARS[vehicle].filter_settings() if vehicle in CARS else {}


def _localizer_config(spec: ModelSpec, task: WindowTask, stride: int):
    from prml2_edge.runtime.localizer import LocalizerConfig

    # the spec's overrides win over the protocol's receiver settings (an ablation may switch the heading fixes off)
    kwargs = dict(gnss_pos_std_m=GNSS_POS_STD_M, gnss_heading_std_deg=GNSS_HEADING_STD_DEG,
                  gnss_heading_min_speed_mps=GNSS_HEADING_MIN_SPEED_MPS)
    if spec.kind == "osd":  # the low-mu inflation is for a model trained on dry roads; OSD's noise was tuned as it is
        kwargs["low_mu_model_var_scale"] = 1.0
        kwargs["model_inputs_from_cues"] = False  # the baseline integrates the raw CAN values
    kwargs |= car_settings(task.vehicle)
    kwargs |= dict(spec.filter)
    return LocalizerConfig(stride=stride, mu=task.mu, fuse_gnss=bool(task.preroll), calibration=spec.calibration,
                           **kwargs)


def model_reads_cues(spec: ModelSpec) -> bool:
    """Whether ``spec``'s model reads its inputs less the cue estimator's offsets (``model_inputs_from_cues``, or a
    model trained so, ``cue_debiased_inputs``): two specs that differ here give the model different windows, so one's
    recorded outputs cannot replay the other's."""
    from prml2_edge.runtime.localizer import LocalizerConfig, reads_debiased_cues

    if spec.kind == "osd" or not spec.calibration:
        return False
    cfg = LocalizerConfig(calibration=True, **dict(spec.filter))
    return bool(cfg.cue_offset and reads_debiased_cues(build_model(spec), cfg))


def start_state(task: WindowTask) -> np.ndarray:
    """The filter's start state: the true pose and z at the first row it runs (the pre-roll's, when there is one)."""
    pose, z = (task.pre_pose_gt[0], task.pre_z_gt[0]) if task.preroll else (task.pose_gt[0], task.z_gt[0])
    x0 = np.zeros(EkfState.DIM)
    x0[EkfState.POS] = pose[:2]
    x0[EkfState.YAW] = pose[2]
    x0[list(schema.Z_TO_EKF_INDEX)] = z
    return x0


def localizer_for(spec: ModelSpec, task: WindowTask, stride: int = 1, model=None):
    """``(localizer, recording model)``: the streaming localiser ``spec`` runs ``task`` with, as :func:`run_window`
    sets it up (the protocol's receiver settings, the car's settings, the spec's filter overrides, the calibration
    file's standstill offset, wheel scale and gyro gain); ``model`` as in :func:`run_window`. Run it with
    ``loc.run_arrays(task.onboard, start_state(task), start_index=task.history, ...)``."""
    from prml2_edge.evaluation.models import RecordingModel
    from prml2_edge.runtime.localizer import StreamingLocalizer

    model = RecordingModel(build_model(spec, task.bias) if model is None else model)
    loc = StreamingLocalizer(model, _localizer_config(spec, task, stride), process_noise=process_noise(model,
                                                                                                      spec.q_scale))
    if spec.calibration and spec.standstill_calibration:
        restore_standstill_calibration(loc, task.bias, task.wheel_scale if spec.wheel_scale_history else None,
                                       spec.standstill_restore)
        if task.yaw_gain is not None:
            loc.filter.yaw_gain.restore(*task.yaw_gain)
        if task.cue_offsets is not None:
            loc.restore_cue_offsets(*task.cue_offsets)
    cues = loc.filter.cue_offset
    if spec.cue_drive_so_far and cues is not None and task.before is not None:
        so_far = np.concatenate([task.before, task.onboard[:task.history]])
        step = YawResolution.of(so_far[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index], loc.filter.config)
        cues.rows(so_far, loc.filter.yaw_gain_factor, step)
    if not spec.guard:
        loc.a_max_mps2 = NO_GUARD_A_MAX_MPS2  # ablation: no friction-circle bound (speed/yaw-rate bounds stay)
    return loc, model


def run_window(spec: ModelSpec, task: WindowTask, stride: int = 1, model=None) -> WindowResult:
    """Dead-reckon ``task`` with ``spec`` through :meth:`StreamingLocalizer.run_arrays`.

    With a pre-roll (deployment protocol) the filter starts at the true pose ``preroll`` rows before the
    outage and fuses :func:`simulated_fixes` until it; everything reported is from the outage start on.
    ``model``: use this model (e.g. a :class:`~prml2_edge.evaluation.models.ReplayModel` of recorded outputs)
    instead of building ``spec``'s.
    """
    loc, model = localizer_for(spec, task, stride, model)
    traj = loc.run_arrays(task.onboard, start_state(task), start_index=task.history, gnss=simulated_fixes(task))
    h = task.history + task.preroll  # the outage starts here
    pose = traj.pose[h:]
    d = pose[:, :2] - task.pose_gt[:, :2]
    pos_err = np.hypot(d[:, 0], d[:, 1])
    yaw_err = np.asarray(wrap_angle(pose[:, 2] - task.pose_gt[:, 2]), dtype=np.float64)
    mahal2 = mahalanobis2(d, traj.pos_cov[h:])
    # model outputs the EKF consumed: call i is the window ending at row history + i * stride (rows all valid)
    z = np.full((len(pose), schema.NUM_STATES), np.nan)
    z_var = z.copy()
    if model.records:
        idx = np.array([r[0] for r in model.records]) * stride - task.preroll
        mean = np.array([r[1] for r in model.records])
        var = np.array([r[2] for r in model.records])
        if spec.guard:
            mean = physics_guard(mean, var, schema.accel_limit_mps2(task.mu))[0]
        ok = (idx >= 0) & (idx < len(pose))
        z[idx[ok]] = mean[ok]
        z_var[idx[ok]] = var[ok]
        if spec.kind == "osd":
            from prml2_edge.evaluation.models import OSD_MISSING

            z[:, list(OSD_MISSING)] = np.nan
    return WindowResult(spec.name, task.key, task.split, pose, pos_err, yaw_err, task.distance_m, z,
                        int(traj.guard_fired[h:].sum()), int(traj.model_used[h:].sum()), mahal2, traj.cal[h], z_var)


def _run_pair(args: tuple[ModelSpec, WindowTask, int]) -> WindowResult:
    return run_window(*args)


def run_all(specs: Sequence[ModelSpec], tasks: Sequence[WindowTask], stride: int = 1, jobs: int = 1,
            on_done: Callable[[WindowResult], None] | None = None) -> dict[str, list[WindowResult]]:
    """Every spec on every task; ``jobs`` worker processes (1: in this process). Results per model, task order."""
    pairs = [(spec, task, stride) for spec in specs for task in tasks]
    out: dict[str, list[WindowResult]] = {spec.name: [] for spec in specs}
    if jobs <= 1:
        results = map(_run_pair, pairs)
        for res in results:
            out[res.model].append(res)
            if on_done is not None:
                on_done(res)
        return out
    import multiprocessing as mp

    import prml2_edge.runtime.inference
    import prml2_edge.runtime.localizer  # noqa: F401 - imported before the fork: every worker runs the same code

    ctx = mp.get_context("fork" if os.name == "posix" else "spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        for res in pool.map(_run_pair, pairs, chunksize=1):
            out[res.model].append(res)
            if on_done is not None:
                on_done(res)
    return out
