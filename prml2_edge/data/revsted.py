"""Load and write drives in the ReV-StED CSV column schema.

Columns, units and frames: ``../shared/data/revsted/revsted_columns.csv`` and
``../shared/docs/method.md``. A :class:`Drive` holds, in SI:

* ``onboard`` o_t (N, 9) in the canonical order of :data:`prml2_edge.schema.SIGNALS`;
* ``z_gt`` (N, 5) = [v_x, v_y, a_x, a_y, omega_z] at the COG, levelled vehicle frame
  (``INS_velCOG_hor_x/y`` m/s, ``acc_hor_x/y`` g, ``rate_hor_z`` deg/s);
* ``pose_gt`` (N, 3) = [x east m, y north m, psi rad counter-clockwise from east], psi
  unwrapped (``ins_pos_rel_x/y`` m, ``ins_yaw`` deg clockwise from north).

What the loader does with imperfect files (nothing is dropped silently):

* missing onboard column, or time column: :class:`DataError` naming file and column;
* a file with none of the ground-truth columns loads onboard-only; a file with some of
  a group (velocities/accelerations/yaw rate, or position/heading) but not all raises;
* non-numeric text in a used column: :class:`DataError` naming file, column and row;
* time not strictly increasing, or a sample rate other than 50 Hz: :class:`DataError`;
* one missing sample (a time step of ~2 periods): **repaired** by inserting the linearly
  interpolated row, counted in ``repairs["gap_rows_inserted"]``; a longer gap raises
  :class:`DataError` with the row (split the file there);
* non-finite values (empty, NaN, inf) in a used column for at most
  :data:`MAX_HELD_NONFINITE` consecutive rows: **repaired** by holding the previous value
  (the next one at the start), counted in ``repairs["nonfinite_held:<column>"]``; longer
  runs raise :class:`DataError` with the file, column and first row.

Row numbers in messages are 1-based data rows (row 1 is the line after the header).
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from prml2_edge import schema
from prml2_edge.data.conventions import ConventionFinding, check_drive, first_failure
from prml2_edge.errors import DataError

TIME_COLUMN = "INS_time_sec"
# Ground truth z (schema.STATES order): (column, scale to SI).
# The ADMA INS reports in its own frame: x forward, y RIGHT, z DOWN (so yaw rate is
# clockwise positive: in ADMA_data_sample.csv rate_hor_z > 0 while ins_yaw, clockwise
# from north, increases). The schema's vehicle frame is y left, z up, hence the signs.
Z_COLUMNS: tuple[tuple[str, float], ...] = (
    ("INS_velCOG_hor_x", 1.0),  # m/s
    ("INS_velCOG_hor_y", -1.0),  # m/s, right-positive -> left-positive
    ("acc_hor_x", schema.G_MPS2),  # g -> m/s^2
    ("acc_hor_y", -schema.G_MPS2),  # g, right-positive -> m/s^2 left-positive
    ("rate_hor_z", -schema.DEG_TO_RAD),  # deg/s clockwise-positive -> rad/s counter-clockwise
)
POSE_COLUMNS: tuple[str, ...] = ("ins_pos_rel_x", "ins_pos_rel_y", "ins_yaw")  # m east, m north, deg cw from north
MAX_HELD_NONFINITE = 5  # rows: longer runs of non-finite values are an error, not a repair
_DT_TOL = 0.25  # accepted jitter of one time step, fraction of schema.DT_S
META_SUFFIX = ".meta.json"


@dataclass
class Drive:
    """One drive at 50 Hz in SI units (see the module docstring for frames and shapes).

    Attributes
    ----------
    name : str
    path : Path or None
        The CSV it was loaded from (None when simulated in memory).
    t_s : ndarray (N,) float64
        Time [s], as in the file.
    onboard : ndarray (N, 9) float64
        o_t in canonical order and SI units of :data:`schema.SIGNALS`.
    z_gt : ndarray (N, 5) float64 or None
        [v_x m/s, v_y m/s, a_x m/s^2, a_y m/s^2, omega_z rad/s], COG, vehicle frame.
    pose_gt : ndarray (N, 3) float64 or None
        [x east m, y north m, psi rad ccw from east], psi unwrapped.
    meta : dict
        Provenance, e.g. ``{"family": "mixed", "mu": 1.0, "seed": 3, "snow": False}``.
    repairs : dict[str, int]
        What the loader repaired, counted (empty when nothing was).
    """

    name: str
    path: Path | None
    t_s: np.ndarray
    onboard: np.ndarray
    z_gt: np.ndarray | None
    pose_gt: np.ndarray | None
    meta: dict = field(default_factory=dict)
    repairs: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.t_s)
        if self.onboard.shape != (n, schema.NUM_SIGNALS):
            raise ValueError(f"onboard must be ({n}, {schema.NUM_SIGNALS}), got {self.onboard.shape}")
        if self.z_gt is not None and self.z_gt.shape != (n, schema.NUM_STATES):
            raise ValueError(f"z_gt must be ({n}, {schema.NUM_STATES}), got {self.z_gt.shape}")
        if self.pose_gt is not None and self.pose_gt.shape != (n, 3):
            raise ValueError(f"pose_gt must be ({n}, 3), got {self.pose_gt.shape}")

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def has_ground_truth(self) -> bool:
        """True when both z_gt and pose_gt are present."""
        return self.z_gt is not None and self.pose_gt is not None

    @property
    def duration_s(self) -> float:
        return len(self.t_s) * schema.DT_S

    def slice(self, start: int, stop: int) -> Drive:
        """Rows ``start:stop`` as a new Drive (copies; meta gains ``slice = [start, stop]``)."""
        sl = slice(start, stop)
        meta = dict(self.meta)
        meta["slice"] = [int(start), int(stop)]
        return replace(
            self,
            name=f"{self.name}[{start}:{stop}]",
            t_s=self.t_s[sl].copy(),
            onboard=self.onboard[sl].copy(),
            z_gt=None if self.z_gt is None else self.z_gt[sl].copy(),
            pose_gt=None if self.pose_gt is None else self.pose_gt[sl].copy(),
            meta=meta,
            repairs=dict(self.repairs),
        )


def _onboard_column_names(header: list[str]) -> list[str]:
    """The column used for each canonical signal (accepting aliases); raises if one is missing."""
    names = []
    for sig in schema.SIGNALS:
        candidates = (sig.revsted_column,) + schema.REVSTED_ALIASES.get(sig.revsted_column, ())
        found = next((c for c in candidates if c in header), None)
        if found is None:
            alias = f" (or {', '.join(candidates[1:])})" if len(candidates) > 1 else ""
            raise DataError(
                f"missing onboard column {sig.revsted_column!r}{alias} for {sig.name}; "
                "ReV-StED columns are listed in revsted_columns.csv"
            )
        names.append(found)
    return names


def _parse_column(path: Path, rows: list[list[str]], col_index: int, col_name: str) -> np.ndarray:
    """One column as float64; empty cells become NaN; text raises naming the row."""
    raw = [row[col_index].strip() if col_index < len(row) else "" for row in rows]
    raw = ["nan" if not s else s for s in raw]
    try:
        return np.asarray(raw, dtype=np.float64)
    except ValueError:
        for i, s in enumerate(raw):
            try:
                float(s)
            except ValueError:
                raise DataError(
                    f"{path}: column {col_name!r} row {i + 1}: {s!r} is not a number; fix or blank the cell"
                ) from None
        raise


def _hold_nonfinite(path: Path, values: np.ndarray, col_name: str, repairs: dict[str, int]) -> np.ndarray:
    """Hold the previous finite value over short runs of non-finite values (counted)."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return values
    if bad.all():
        raise DataError(f"{path}: column {col_name!r} has no finite value; it must hold numbers")
    edges = np.diff(np.concatenate(([0], bad.astype(np.int8), [0])))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    lengths = stops - starts
    if lengths.max() > MAX_HELD_NONFINITE:
        k = int(np.argmax(lengths > MAX_HELD_NONFINITE))
        raise DataError(
            f"{path}: column {col_name!r} rows {starts[k] + 1}-{stops[k]}: {lengths[k]} consecutive non-finite "
            f"values (at most {MAX_HELD_NONFINITE} are held over); fill them or cut the file there"
        )
    out = values.copy()
    idx = np.where(bad, 0, np.arange(len(values)))
    np.maximum.accumulate(idx, out=idx)
    first_good = int(np.argmax(~bad))
    idx[:first_good] = first_good
    out = out[idx]
    repairs[f"nonfinite_held:{col_name}"] = int(bad.sum())
    return out


def _check_time(path: Path, t_s: np.ndarray, repairs: dict[str, int]) -> np.ndarray:
    """Check the time axis; returns the rows after which one missing sample is inserted (0-based)."""
    if not np.all(np.isfinite(t_s)):
        row = int(np.argmax(~np.isfinite(t_s))) + 1
        raise DataError(f"{path}: column {TIME_COLUMN!r} row {row}: time is not a finite number")
    if len(t_s) < 2:
        raise DataError(f"{path}: needs at least 2 rows, has {len(t_s)}")
    dt = np.diff(t_s)
    if np.any(dt <= 0):
        row = int(np.argmax(dt <= 0)) + 2
        raise DataError(
            f"{path}: column {TIME_COLUMN!r} row {row}: time {t_s[row - 1]!r} does not increase "
            f"(previous {t_s[row - 2]!r}); sort the file by time and remove duplicate rows"
        )
    med = float(np.median(dt))
    if abs(med - schema.DT_S) > _DT_TOL * schema.DT_S:
        raise DataError(
            f"{path}: sample period is {med * 1000:.1f} ms; onboard data must be at {schema.SAMPLE_RATE_HZ:g} Hz "
            f"({schema.DT_S * 1000:.0f} ms); resample the file first"
        )
    steps = dt / schema.DT_S
    ok = np.abs(steps - 1.0) <= _DT_TOL
    one_missing = np.abs(steps - 2.0) <= _DT_TOL
    bad = ~(ok | one_missing)
    if bad.any():
        row = int(np.argmax(bad)) + 2
        raise DataError(
            f"{path}: column {TIME_COLUMN!r} row {row}: time step of {dt[row - 2] * 1000:.1f} ms "
            f"(expected {schema.DT_S * 1000:.0f} ms; one missing sample is repaired, longer gaps are not); "
            "split the file at that row"
        )
    if one_missing.any():
        repairs["gap_rows_inserted"] = int(one_missing.sum())
    return np.flatnonzero(one_missing)


def _insert_gaps(values: np.ndarray, gap_after: np.ndarray) -> np.ndarray:
    """Insert the mean of rows i and i+1 after each row i in ``gap_after`` (axis 0)."""
    mids = 0.5 * (values[gap_after] + values[gap_after + 1])
    return np.insert(values, gap_after + 1, mids, axis=0)


def _read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    """The stripped header and the non-empty data rows of the CSV at ``path``."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise DataError(f"{path}: file is empty; expected a CSV with a header row") from None
            rows = [row for row in reader if row]
    except FileNotFoundError:
        raise DataError(f"{path}: file not found") from None
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: not a text CSV file ({exc.reason})") from exc
    return header, rows


def _ground_truth(
    path: Path, col: dict[str, int], column: Callable[[str], np.ndarray], require_ground_truth: bool
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(z_gt, pose_gt)`` from the ground-truth columns (each None when its group is absent); ``column``
    reads one column as the loader does (parsed, non-finite runs held, gaps filled)."""
    z_names = [c for c, _ in Z_COLUMNS]
    z_gt = pose_gt = None
    for group in (z_names, list(POSE_COLUMNS)):
        present = [c for c in group if c in col]
        if present and len(present) < len(group):
            missing = [c for c in group if c not in col]
            raise DataError(
                f"{path}: has ground-truth column(s) {', '.join(present)} but lacks {', '.join(missing)}; "
                "add them, or remove the partial ground truth to load the file onboard-only"
            )
    if all(c in col for c in z_names):
        z_gt = np.stack([column(c) * scale for c, scale in Z_COLUMNS], axis=1)
    if all(c in col for c in POSE_COLUMNS):
        x_m, y_m, yaw_deg = (column(c) for c in POSE_COLUMNS)
        psi_rad = np.unwrap(schema.heading_deg_to_psi(yaw_deg))
        pose_gt = np.stack([x_m, y_m, psi_rad], axis=1)
    if require_ground_truth and (z_gt is None or pose_gt is None):
        need = ", ".join(z_names + list(POSE_COLUMNS))
        raise DataError(f"{path}: ground truth required but the file lacks it (columns {need})")
    return z_gt, pose_gt


def _read_meta(path: Path) -> dict:
    """The sidecar ``<stem>.meta.json`` of the CSV at ``path``, or {} when there is none."""
    meta_path = path.with_name(path.stem + META_SUFFIX)
    if not meta_path.is_file():
        return {}
    try:
        return json.loads(meta_path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{meta_path}: not valid JSON ({exc.msg} at line {exc.lineno})") from exc


def load_drive(path: str | Path, *, require_ground_truth: bool = False, check_conventions: bool = True) -> Drive:
    """Load a ReV-StED-schema CSV into a :class:`Drive` (SI units; see the module docstring).

    Parameters
    ----------
    path : str or Path
        The CSV file. A sidecar ``<stem>.meta.json`` (written by :func:`write_drive_csv`)
        supplies ``meta`` when present.
    require_ground_truth : bool
        Raise :class:`DataError` when the ground-truth columns are absent.
    check_conventions : bool
        Refuse a file whose sign conventions differ from the documented ones, checked from physics
        (:mod:`prml2_edge.data.conventions`), naming the column and the fix.

    Returns
    -------
    Drive
        ``z_gt``/``pose_gt`` are None for an onboard-only file.
    """
    path = Path(path)
    header, rows = _read_csv(path)
    if TIME_COLUMN not in header:
        raise DataError(f"{path}: missing time column {TIME_COLUMN!r} (seconds); the first column of ReV-StED files")
    try:
        onboard_cols = _onboard_column_names(header)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None
    col = {name: i for i, name in enumerate(header)}

    repairs: dict[str, int] = {}
    t_s = _parse_column(path, rows, col[TIME_COLUMN], TIME_COLUMN)
    gap_after = _check_time(path, t_s, repairs)
    has_gaps = "gap_rows_inserted" in repairs

    def column(name: str) -> np.ndarray:
        values = _hold_nonfinite(path, _parse_column(path, rows, col[name], name), name, repairs)
        return _insert_gaps(values, gap_after) if has_gaps else values

    onboard = np.stack(
        [column(c) * sig.revsted_scale for c, sig in zip(onboard_cols, schema.SIGNALS, strict=True)], axis=1
    )
    if has_gaps:
        t_s = _insert_gaps(t_s, gap_after)

    z_gt, pose_gt = _ground_truth(path, col, column, require_ground_truth)
    meta = _read_meta(path)
    drive = Drive(name=path.stem, path=path, t_s=t_s, onboard=onboard, z_gt=z_gt, pose_gt=pose_gt,
                  meta=meta, repairs=repairs)
    if check_conventions:
        bad = first_failure(drive, set(header))
        if bad is not None:
            raise DataError(bad.line() + " (prml2 doctor --data FILE lists every check)")
    return drive


def check_folder(path: str | Path) -> list[ConventionFinding]:
    """Convention checks of one CSV or every ``*.csv`` under ``path`` (``drives/`` of a dataset included)."""
    path = Path(path)
    files = [path] if path.is_file() else sorted(path.rglob("*.csv"))
    if not files:
        raise DataError(f"{path}: no CSV files (a ReV-StED-schema CSV, or a folder of them)")
    out = []
    for f in files:
        drive = load_drive(f, check_conventions=False)
        out += check_drive(drive, _header(f))
    return out


def _header(path: Path) -> set[str]:
    with open(path, encoding="utf-8-sig") as f:
        return {h.strip() for h in f.readline().split(",")}


def _fmt_for_step(step: float) -> str:
    """A printf format that keeps values on a quantisation grid of ``step`` exact enough."""
    decimals = max(3, int(math.ceil(-math.log10(step))) + 3) if step > 0 else 6
    return f"%.{decimals}f"


def write_drive_csv(drive: Drive, path: str | Path) -> None:
    """Write ``drive`` as a ReV-StED-schema CSV (full-dataset column names, e.g. ``Yawrate_obd``).

    Columns: ``INS_time_sec``, the 9 onboard columns in their ReV-StED units, and, when
    the drive has ground truth, ``INS_velCOG_hor_x/y`` [m/s], ``acc_hor_x/y`` [g],
    ``rate_hor_z`` [deg/s], ``ins_pos_rel_x/y`` [m] and ``ins_yaw`` [deg, clockwise
    from north, in [0, 360)]. ``drive.meta`` goes to the sidecar ``<stem>.meta.json``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [TIME_COLUMN]
    cols = [np.asarray(drive.t_s, dtype=np.float64)]
    fmts = ["%.3f"]
    for i, sig in enumerate(schema.SIGNALS):
        names.append(sig.revsted_column)
        cols.append(drive.onboard[:, i] / sig.revsted_scale)
        fmts.append(_fmt_for_step(sig.revsted_step / abs(sig.revsted_scale)))
    if drive.z_gt is not None:
        for k, (c, scale) in enumerate(Z_COLUMNS):
            names.append(c)
            cols.append(drive.z_gt[:, k] / scale)
            fmts.append("%.6f")
    if drive.pose_gt is not None:
        yaw_deg = schema.psi_rad_to_heading_deg(drive.pose_gt[:, 2])
        names += list(POSE_COLUMNS)
        cols += [drive.pose_gt[:, 0], drive.pose_gt[:, 1], yaw_deg]
        fmts += ["%.4f", "%.4f", "%.5f"]
    table = np.stack(cols, axis=1)
    np.savetxt(path, table, fmt=fmts, delimiter=",", header=",".join(names), comments="")
    meta_path = path.with_name(path.stem + META_SUFFIX)
    meta_path.write_text(json.dumps(drive.meta, indent=1, sort_keys=True, default=_json_default) + "\n")


def _json_default(obj: object) -> object:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
