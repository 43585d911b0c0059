"""Sign conventions of a ReV-StED-schema file, checked from physics (NumPy only).

The loader flips the documented conventions into the schema's frame (docs/deviations.md:
ADMA ground truth is y right, z down, so ``rate_hor_z`` is clockwise positive and
``INS_velCOG_hor_y``/``acc_hor_y`` right positive; ``LatAcc_obd`` is right positive;
``ins_yaw`` clockwise from north). A file from another source with other conventions would
load without a word and train or evaluate on mirrored physics, so after loading:

* ``rate_hor_z`` against the heading change of ``ins_yaw`` and against ``Yawrate_obd``
  (two of the three agreeing names the odd one out);
* ``acc_hor_y`` against v_x x yaw rate; ``INS_velCOG_hor_y`` against the lateral velocity the
  positions give (``ins_pos_rel_x/y`` differentiated, rotated into the vehicle frame by ``ins_yaw``);
* the onboard columns with :func:`prml2_edge.data.signal_checks.check_onboard`: ``Yawrate_obd`` against
  the rear wheel-speed difference, ``LatAcc_obd`` against speed x yaw rate, ``SW_pos_obd``
  against the yaw rate at low speed, the wheels against each other and the speedometer.

A check that cannot decide (a straight drive, a parked car) is skipped, never failed.

The checks work on a loaded drive and read no files: :mod:`prml2_edge.data.revsted`, the loader, calls them
(:func:`~prml2_edge.data.revsted.load_drive` refuses a mirrored file; :func:`~prml2_edge.data.revsted.check_folder`
checks the CSVs of a folder), never the other way round.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from prml2_edge import schema
from prml2_edge.data.signal_checks import FAIL, PASS, SKIP, WARN, _corr, _smooth, check_onboard

MIN_ROWS = 100
MIN_R = 0.5

CONVENTION = {
    "rate_hor_z": "clockwise positive (ADMA: z down)",
    "ins_yaw": "clockwise from north",
    "INS_velCOG_hor_y": "right positive (ADMA: y right)",
    "acc_hor_y": "right positive (ADMA: y right)",
    "Yawrate_obd": "counter-clockwise positive",
    "LatAcc_obd": "right positive",
    "SW_pos_obd": "left positive",
}


@dataclass(frozen=True)
class ConventionFinding:
    file: str
    column: str
    result: str  # PASS | FAIL (a sign convention other than the documented one) | WARN (a scale) | SKIP
    detail: str
    fix: str = ""

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """One line naming the file, the column, what disagrees and the fix."""
        return f"{self.file}: column {self.column!r}: {self.detail}" + (f"; {self.fix}" if self.fix else "")


def _flip_fix(column: str) -> str:
    return (f"the documented convention is {CONVENTION.get(column, 'the one in revsted_columns.csv')}: this file's "
            f"looks opposite, negate the column")


def _column(name: str, header: set[str] | None) -> str:
    col = schema.SIGNAL_BY_NAME[name].revsted_column
    if header is not None and col not in header:
        for alias in schema.REVSTED_ALIASES.get(col, ()):
            if alias in header:
                return alias
    return col


def check_drive(drive, header: set[str] | None = None) -> list[ConventionFinding]:
    """Every convention check on a loaded :class:`~prml2_edge.data.revsted.Drive` (schema frame)."""
    file = str(drive.path or drive.name)
    out: list[ConventionFinding] = []
    for f in check_onboard(drive.onboard):
        col = _column(f.signal, header)
        if f.result == FAIL and f.scale_factor == -1.0:
            out.append(ConventionFinding(file, col, FAIL, f.detail.replace(f.signal, col), _flip_fix(col)))
        elif f.result == FAIL:  # a scale, not a convention: reported, never refused (short drives are noisy)
            out.append(ConventionFinding(file, col, WARN, f.detail.replace(f.signal, col),
                                         f"{f.fix} (check the column's unit against revsted_columns.csv)"))
        else:
            out.append(ConventionFinding(file, col, f.result, f.detail))
    if drive.z_gt is not None and drive.pose_gt is not None:
        out += _ground_truth(file, drive, _column("yaw_rate_radps", header))
    return out


def _ground_truth(file: str, drive, yaw_col: str) -> list[ConventionFinding]:
    dt = schema.DT_S
    z, pose = drive.z_gt, drive.pose_gt
    v_x = z[:, schema.Z.V_X]
    w_gt = _smooth(z[:, schema.Z.OMEGA_Z])
    psi = pose[:, 2]
    w_psi = _smooth(np.gradient(psi, dt))
    w_obd = _smooth(drive.onboard[:, schema.SIGNAL_BY_NAME["yaw_rate_radps"].index])
    moving = v_x > 3.0
    turning = moving & (np.abs(w_psi) > 0.05)
    out = []
    if turning.sum() < MIN_ROWS:
        for col in ("rate_hor_z", "acc_hor_y", "INS_velCOG_hor_y"):
            out.append(ConventionFinding(file, col, SKIP, "too little turning to check"))
        return out
    r_gt_psi = _corr(w_gt[moving], w_psi[moving])
    r_obd_psi = _corr(w_obd[moving], w_psi[moving])
    r_obd_gt = _corr(w_obd[moving], w_gt[moving])
    w_ref = w_psi
    heading_ok = True
    if r_gt_psi >= MIN_R:
        out.append(ConventionFinding(file, "rate_hor_z", PASS, f"follows the heading change of ins_yaw "
                                     f"(r = {r_gt_psi:+.2f})"))
    elif r_gt_psi <= -MIN_R and r_obd_psi >= MIN_R:
        out.append(ConventionFinding(file, "rate_hor_z", FAIL, "has the opposite sign of the heading change of "
                                     f"ins_yaw (r = {r_gt_psi:+.2f}) and of {yaw_col} (r = {r_obd_gt:+.2f})",
                                     _flip_fix("rate_hor_z")))
    elif r_gt_psi <= -MIN_R and r_obd_gt >= MIN_R:
        heading_ok = False
        w_ref = w_gt
        out.append(ConventionFinding(file, "ins_yaw", FAIL, f"its heading change has the opposite sign of rate_hor_z "
                                     f"(r = {r_gt_psi:+.2f}) and of {yaw_col} (r = {r_obd_psi:+.2f})",
                                     _flip_fix("ins_yaw")))
    else:
        out.append(ConventionFinding(file, "rate_hor_z", FAIL, f"rate_hor_z, the heading change of ins_yaw and "
                                     f"{yaw_col} disagree (r = {r_gt_psi:+.2f}, {r_obd_psi:+.2f}, {r_obd_gt:+.2f})",
                                     "check the yaw columns' units and signs against revsted_columns.csv"))
    a_y = _smooth(z[:, schema.Z.A_Y])
    ref = v_x * w_ref
    rows = moving & (np.abs(ref) > 1.0)
    if rows.sum() >= MIN_ROWS:
        r = _corr(a_y[moving], ref[moving])
        if r <= -MIN_R:
            out.append(ConventionFinding(file, "acc_hor_y", FAIL, f"has the opposite sign of v_x x yaw rate "
                                         f"(r = {r:+.2f})", _flip_fix("acc_hor_y")))
        else:
            out.append(ConventionFinding(file, "acc_hor_y", PASS if r >= MIN_R else SKIP, f"r = {r:+.2f} with v_x x "
                                         "yaw rate"))
    else:
        out.append(ConventionFinding(file, "acc_hor_y", SKIP, "too little cornering to check"))
    if heading_ok:
        dx, dy = (_smooth(np.gradient(pose[:, k], dt)) for k in (0, 1))
        v_y_pos = -np.sin(psi) * dx + np.cos(psi) * dy  # lateral velocity of the position point, left positive
        v_y = _smooth(z[:, schema.Z.V_Y])
        rows = moving & (np.abs(v_y_pos) > 0.05)
        if rows.sum() >= MIN_ROWS:
            r = _corr(v_y[moving], v_y_pos[moving])
            if r <= -MIN_R:
                out.append(ConventionFinding(file, "INS_velCOG_hor_y", FAIL, "has the opposite sign of the lateral "
                                             f"velocity the positions give (r = {r:+.2f})",
                                             _flip_fix("INS_velCOG_hor_y")))
            else:
                out.append(ConventionFinding(file, "INS_velCOG_hor_y", PASS if r >= MIN_R else SKIP,
                                             f"r = {r:+.2f} with the positions' lateral velocity"))
        else:
            out.append(ConventionFinding(file, "INS_velCOG_hor_y", SKIP, "too little side slip to check"))
    return out


def first_failure(drive, header: set[str] | None = None) -> ConventionFinding | None:
    """The first failed convention check of ``drive``, or None."""
    return next((f for f in check_drive(drive, header) if f.result == FAIL), None)


def format_findings(findings: list[ConventionFinding]) -> str:
    lines = []
    for f in findings:
        lines.append(f"{f.result:<5} {f.file}: {f.column}: {f.detail}")
        if f.result in (FAIL, WARN) and f.fix:
            lines.append(f"      fix: {f.fix}")
    n_fail = sum(f.result == FAIL for f in findings)
    lines.append("")
    lines.append("OK: every checked convention matches the documented one" if not n_fail else
                 f"{n_fail} column(s) with a convention other than the documented one")
    return "\n".join(lines)
