"""Constants of the session format and the checks shared by its reader and writer.

Every check raises a :class:`core.errors.SessionFormatError` subclass naming the file
it is about (``path``); messages give 1-based data rows and file lines. Arrays are
(K, 3) float64 in metres unless stated otherwise.
"""

from __future__ import annotations

from dataclasses import fields
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import ColumnError, TimestampError, UnitsError

__all__ = [
    "FORMAT",
    "ROLES",
    "CORNER_LABELS",
    "MAX_SIZE_M",
    "MAX_POSITION_NORM_M",
    "MAX_CLOUD_MEDIAN_NORM_M",
    "MIN_QUATERNION_NORM",
    "KIN_REQUIRED",
    "KIN_FORCE",
    "frozen_array",
    "ArrayEq",
    "row_msg",
    "check_times",
    "check_finite",
    "check_positions_metres",
    "check_cloud_metres",
    "collinear",
]

FORMAT = "tissue-session/1"
"""Value of ``session.json["format"]`` this package reads and writes."""

ROLES = ("train", "validation", "test")
"""Allowed ``role`` of a sequence."""

CORNER_LABELS: dict[str, tuple[int, int]] = {
    "x0y0": (0, 0),
    "x1y0": (1, 0),
    "x0y1": (0, 1),
    "x1y1": (1, 1),
}
"""Corner label -> (i, j): the corner is at ``(i * size[0], j * size[1], size[2])``
in the phantom frame."""

# Unit sanity limits (anything beyond is taken for millimetres).
MAX_SIZE_M = 1.0  # phantom edge length / probe radius, m
MAX_POSITION_NORM_M = 5.0  # corner and kinematic positions, robot frame, m
MAX_CLOUD_MEDIAN_NORM_M = 5.0  # median distance of cloud points from the camera, m
MIN_QUATERNION_NORM = 1e-9
COLLINEAR_RTOL = 1e-6
"""Points whose spread across their best-fit line is at most this fraction of their
spread along it count as collinear (:func:`collinear`)."""

KIN_REQUIRED = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
KIN_FORCE = ("fx", "fy", "fz")


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------


def frozen_array(a: Any, dtype: Any) -> np.ndarray:
    """Return a read-only copy of ``a`` as ``dtype``."""
    out = np.array(a, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def _equal(a: Any, b: Any) -> bool:
    """Structural equality that understands numpy arrays inside dicts and tuples."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(map(_equal, a, b))
    return bool(a == b)


class ArrayEq:
    """Mixin: ``==`` for dataclasses holding arrays (field by field, exact)."""

    __hash__ = None  # holds arrays / dicts: not hashable

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))


def row_msg(row: int) -> str:
    """Human row reference: 1-based data row and the file line (header is line 1)."""
    return f"row {row} (line {row + 1})"


# --------------------------------------------------------------------------------------
# Validation shared by reader and writer (messages name the file)
# --------------------------------------------------------------------------------------


def check_times(path: Path, t: np.ndarray, column: str = "t") -> None:
    """Raise TimestampError unless ``t`` is finite and strictly increasing."""
    finite = np.isfinite(t)
    if not finite.all():
        r = int(np.flatnonzero(~finite)[0])
        raise TimestampError(
            path, f"column '{column}' is not finite at {row_msg(r + 1)}: {float(t[r])}"
        )
    d = np.diff(t)
    bad = ~(d > 0)
    if bad.any():
        r = int(np.flatnonzero(bad)[0]) + 1
        dup = ", a duplicate" if d[r - 1] == 0 else ""
        raise TimestampError(
            path,
            f"column '{column}' is not strictly increasing at {row_msg(r + 1)} "
            f"({float(t[r])!r} after {float(t[r - 1])!r}{dup})",
        )


def check_finite(path: Path, values: np.ndarray, columns: tuple[str, ...]) -> None:
    """Raise ColumnError at the first non-finite cell of (K, C) ``values``."""
    finite = np.isfinite(values)
    if not finite.all():
        r, c = (int(v) for v in np.argwhere(~finite)[0])
        raise ColumnError(
            path, f"column '{columns[c]}' is not finite at {row_msg(r + 1)}: {float(values[r, c])}"
        )


def check_positions_metres(path: Path, positions: np.ndarray, what: str) -> None:
    """Raise UnitsError if any (K, 3) position is farther than 5 m from the origin."""
    if len(positions) == 0:
        return
    norms = np.linalg.norm(positions, axis=1)
    r = int(np.argmax(norms))
    if norms[r] > MAX_POSITION_NORM_M:
        raise UnitsError(
            path,
            f"{what} at {row_msg(r + 1)} is {norms[r]:.6g} m from the robot origin "
            f"({positions[r].tolist()}): looks like millimetres, the format uses metres "
            f"(limit {MAX_POSITION_NORM_M} m)",
        )


def check_cloud_metres(path: Path, points: np.ndarray) -> None:
    """Raise UnitsError if the median distance of (N, 3) points from the camera > 5 m."""
    med = float(np.median(np.linalg.norm(points, axis=1)))
    if med > MAX_CLOUD_MEDIAN_NORM_M:
        raise UnitsError(
            path,
            f"median point distance from the camera is {med:.6g} m: looks like millimetres, "
            f"the format uses metres (limit {MAX_CLOUD_MEDIAN_NORM_M} m)",
        )



def collinear(points: np.ndarray, rtol: float = COLLINEAR_RTOL) -> bool:
    """True when (N, 3) points (m, any frame) do not span a plane.

    That is: fewer than 3 points, all points coincident, or the second singular value of
    the centred points at most ``rtol`` times the first (their spread across the best-fit
    line relative to the spread along it). A rigid registration on such points cannot fix
    the rotation about that line.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] < 3:
        return True
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return not sv[0] > 0 or bool(sv[1] <= rtol * sv[0])
