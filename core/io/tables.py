"""CSV tables of a session: ``kinematics.csv``, ``frames.csv`` and the calibration
touches, parsed and validated (errors name the file, the column and the row).
"""

from __future__ import annotations

import csv
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path, PurePosixPath
from typing import TextIO

import numpy as np

from core.errors import ColumnError, MissingFileError, SessionFormatError
from core.io.checks import (
    CORNER_LABELS,
    KIN_FORCE,
    KIN_REQUIRED,
    MIN_QUATERNION_NORM,
    check_finite,
    check_positions_metres,
    check_times,
    row_msg,
)
from core.io.records import (
    Corners,
    Frames,
    Kinematics,
    LandmarkTouches,
    check_landmark_label,
    validate_corners,
    validate_landmark_touches,
)

__all__ = ["read_kinematics", "read_frames", "read_corners", "read_landmark_touches"]

_FRAMES_REQUIRED = ("frame", "t", "file")


# --------------------------------------------------------------------------------------
# CSV reading
# --------------------------------------------------------------------------------------


def _open_csv(path: Path, what: str) -> tuple[TextIO, list[str]]:
    """Open a CSV file, parse its header; return (file positioned after it, names)."""
    if not path.is_file():
        raise MissingFileError(path, f"{what} does not exist")
    f = open(path, encoding="utf-8-sig", newline=None)  # noqa: SIM115 (closed by caller)
    try:
        line = f.readline()
        if not line.strip():
            raise ColumnError(path, "empty file: expected a header line")
        names = [n.strip() for n in next(csv.reader([line]))]
        if any(not n for n in names):
            raise ColumnError(path, f"empty column name in header {names}")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ColumnError(path, f"duplicate column(s) {dup} in header {names}")
    except BaseException:
        f.close()
        raise
    return f, names


def _require_columns(path: Path, names: list[str], required: tuple[str, ...], expected: str) -> None:
    missing = [c for c in required if c not in names]
    if missing:
        raise ColumnError(path, f"missing column(s) {missing}: expected {expected}, got {names}")


def _parse_rows_slowly(path: Path, names: list[str]) -> np.ndarray:
    """Fallback parser (csv module + float): returns the data or raises ColumnError
    naming the first bad cell."""
    rows: list[list[float]] = []
    with open(path, encoding="utf-8-sig", newline="") as f:
        reader = csv.reader(f)
        next(reader, None)
        for r, row in enumerate(reader, start=1):
            if not row or all(not c.strip() for c in row):
                continue  # blank line
            if len(row) != len(names):
                raise ColumnError(
                    path, f"{row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            vals = []
            for c, cell in enumerate(row):
                try:
                    vals.append(float(cell))
                except ValueError:
                    raise ColumnError(
                        path, f"column '{names[c]}' is not numeric at {row_msg(r)}: {cell!r}"
                    ) from None
            rows.append(vals)
    return np.array(rows, dtype=np.float64).reshape(len(rows), len(names))


def _read_numeric_csv(path: Path, what: str, required: tuple[str, ...],
                      expected: str) -> tuple[list[str], np.ndarray]:
    """Read an all-numeric CSV: returns (column names, (K, C) float64)."""
    f, names = _open_csv(path, what)
    with f:
        _require_columns(path, names, required, expected)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "input contained no data"
                data = np.loadtxt(f, delimiter=",", dtype=np.float64, comments=None, ndmin=2)
        except ValueError:
            data = None
    if data is None:
        data = _parse_rows_slowly(path, names)  # precise message, or lenient (quoted) parse
    if data.size == 0:
        data = np.zeros((0, len(names)))
    if data.shape[1] != len(names):
        raise ColumnError(path, f"rows have {data.shape[1]} fields, the header has {len(names)}")
    return names, data


def read_kinematics(path: Path) -> Kinematics:
    expected = "t,x,y,z,qx,qy,qz,qw[,fx,fy,fz][,extra...]"
    names, data = _read_numeric_csv(path, "kinematics.csv", KIN_REQUIRED, expected)
    present = [c for c in KIN_FORCE if c in names]
    if present and len(present) != 3:
        raise ColumnError(
            path,
            f"partial force columns {present}: give all of fx,fy,fz or none (got {names})",
        )
    if len(data) == 0:
        raise SessionFormatError(path, "no data rows")
    col = {n: data[:, i] for i, n in enumerate(names)}
    t = col["t"]
    check_times(path, t)
    pos = np.stack([col[c] for c in "xyz"], axis=1)
    check_finite(path, pos, ("x", "y", "z"))
    q = np.stack([col[c] for c in ("qx", "qy", "qz", "qw")], axis=1)
    check_finite(path, q, ("qx", "qy", "qz", "qw"))
    qn = np.linalg.norm(q, axis=1)
    zero = qn < MIN_QUATERNION_NORM
    if zero.any():
        r = int(np.flatnonzero(zero)[0]) + 1
        raise ColumnError(path, f"zero quaternion at {row_msg(r)}: {q[r - 1].tolist()}")
    force = None
    if present:
        force = np.stack([col[c] for c in KIN_FORCE], axis=1)
        check_finite(path, force, KIN_FORCE)
    check_positions_metres(path, pos, "probe position")
    known = set(KIN_REQUIRED) | set(KIN_FORCE)
    extra = {n: col[n] for n in names if n not in known}
    return Kinematics(t=t, position=pos, quaternion=q, force=force, extra=extra)


def read_frames(path: Path) -> Frames:
    f, names = _open_csv(path, "frames.csv")
    with f:
        _require_columns(path, names, _FRAMES_REQUIRED, "frame,t,file", )
        ci = {n: names.index(n) for n in _FRAMES_REQUIRED}
        index: list[int] = []
        times: list[float] = []
        files: list[str] = []
        for r, row in enumerate(csv.reader(f), start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(names):
                raise ColumnError(
                    path, f"{row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            try:
                index.append(int(row[ci["frame"]]))
            except ValueError:
                raise ColumnError(
                    path, f"column 'frame' is not an integer at {row_msg(r)}: {row[ci['frame']]!r}"
                ) from None
            try:
                times.append(float(row[ci["t"]]))
            except ValueError:
                raise ColumnError(
                    path, f"column 't' is not numeric at {row_msg(r)}: {row[ci['t']]!r}"
                ) from None
            file = row[ci["file"]].strip()
            p = PurePosixPath(file.replace("\\", "/"))
            if not file or p.is_absolute() or ".." in p.parts or ":" in file:
                raise SessionFormatError(
                    path,
                    f"column 'file' at {row_msg(r)} must be a path inside the sequence "
                    f"folder, got {file!r}",
                )
            files.append(p.as_posix())
    if not files:
        raise SessionFormatError(path, "no frames (only a header)")
    t = np.array(times, dtype=np.float64)
    check_times(path, t)
    idx = np.array(index, dtype=np.int64)
    uniq, first, counts = np.unique(idx, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = int(uniq[counts > 1][0])
        rows = [int(i) + 1 for i in np.flatnonzero(idx == dup)]
        raise ColumnError(path, f"column 'frame' repeats frame number {dup} at rows {rows}")
    return Frames(index=idx, t=t, files=tuple(files))


def _read_labelled_xyz(path: Path, what: str, label_column: str,
                       check_label: Callable[[int, str], None]) -> tuple[list[str], np.ndarray]:
    """Read a ``<label_column>,x,y,z`` table: returns (labels, (K, 3) float64).

    ``check_label(row, label)`` raises for a label that is not allowed (``row`` 1-based).
    """
    f, names = _open_csv(path, what)
    required = (label_column, "x", "y", "z")
    labels: list[str] = []
    values: list[list[float]] = []
    with f:
        _require_columns(path, names, required, ",".join(required))
        ci = [names.index(c) for c in required]
        for r, row in enumerate(csv.reader(f), start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(names):
                raise ColumnError(
                    path, f"{row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            label = row[ci[0]].strip()
            check_label(r, label)
            xyz = []
            for c, name in zip(ci[1:], "xyz"):
                try:
                    xyz.append(float(row[c]))
                except ValueError:
                    raise ColumnError(
                        path, f"column '{name}' is not numeric at {row_msg(r)}: {row[c]!r}"
                    ) from None
            labels.append(label)
            values.append(xyz)
    return labels, np.array(values, dtype=np.float64).reshape(-1, 3)


def read_corners(path: Path) -> Corners:
    """``calibration/corners.csv``: corner touches, robot frame, m.

    Raises:
        MissingFileError: no such file.  ColumnError: missing or non-numeric columns,
            an unknown corner label, non-finite positions.
        SessionFormatError: fewer than 4 touches or 3 distinct corners.
        UnitsError: a position > 5 m from the robot origin.
    """

    def check_label(r: int, label: str) -> None:
        if label not in CORNER_LABELS:
            raise ColumnError(
                path,
                f"column 'corner' at {row_msg(r)} must be one of {list(CORNER_LABELS)}, "
                f"got {label!r}",
            )

    labels, positions = _read_labelled_xyz(path, "corners.csv", "corner", check_label)
    corners = Corners(labels=tuple(labels), positions=positions)
    validate_corners(path, corners)
    return corners


def read_landmark_touches(path: Path, landmarks: Mapping[str, np.ndarray]) -> LandmarkTouches:
    """``calibration/landmarks.csv`` (``landmark,x,y,z``): landmark touches, robot frame, m.

    Args:
        path: the file.
        landmarks: ``SessionMeta.landmarks`` (name -> (3,) point, m, phantom frame); every
            label must be one of them.

    Raises:
        MissingFileError: no such file.  ColumnError: missing or non-numeric columns, an
            empty label, non-finite positions.
        SessionFormatError: a label that is not a landmark of ``session.json``, no rows,
            fewer than 3 distinct or collinear landmarks touched.
        UnitsError: a position > 5 m from the robot origin.
    """

    def check_label(r: int, label: str) -> None:
        if not label:
            raise ColumnError(path, f"column 'landmark' is empty at {row_msg(r)}")
        check_landmark_label(path, r, label, landmarks)

    labels, positions = _read_labelled_xyz(path, "landmarks.csv", "landmark", check_label)
    touches = LandmarkTouches(labels=tuple(labels), positions=positions)
    validate_landmark_touches(path, touches, landmarks)
    return touches
