"""Typed data of a session besides ``session.json``: probe kinematics, depth-frame
tables and calibration touches, with the checks that need the file they belong to.

Frames: *robot* (robot base frame: kinematics, touches, forces), *phantom* (box spans
``[0, size]``, z up, bottom face at z = 0). All quantities SI (m, s, N).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import SessionFormatError
from core.io.checks import (
    CORNER_LABELS,
    KIN_FORCE,
    MIN_QUATERNION_NORM,
    ArrayEq,
    check_finite,
    check_positions_metres,
    check_times,
    collinear,
    frozen_array,
    row_msg,
)

__all__ = [
    "Kinematics",
    "Frames",
    "Corners",
    "LandmarkTouches",
    "validate_kinematics",
    "validate_corners",
    "validate_landmark_touches",
    "check_landmark_label",
]

# --------------------------------------------------------------------------------------
# Typed data
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Kinematics(ArrayEq):
    """Probe track of one sequence (``kinematics.csv``), robot base frame.

    All arrays are read-only float64 copies. Construction checks shapes (ValueError) and
    normalises the quaternions; timestamps and units are checked by the reader and by
    :meth:`SessionWriter.write_kinematics`.
    """

    t: np.ndarray
    """(K,) float64, s; strictly increasing and finite (same clock as ``frames.csv``)."""
    position: np.ndarray
    """(K, 3) float64, m: probe sphere centre, robot frame."""
    quaternion: np.ndarray
    """(K, 4) float64, ``x, y, z, w`` (scalar last), unit norm: probe orientation in the
    robot frame."""
    force: np.ndarray | None = None
    """(K, 3) float64, N: force the probe applies to the phantom, robot frame; None when
    the file has no ``fx, fy, fz`` columns."""
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    """Unknown columns by name, each (K,) float64, written back in order."""

    def __post_init__(self) -> None:
        t = frozen_array(self.t, np.float64)
        if t.ndim != 1:
            raise ValueError(f"t must be (K,), got {t.shape}")
        k = t.shape[0]
        pos = frozen_array(self.position, np.float64)
        if pos.shape != (k, 3):
            raise ValueError(f"position must be ({k}, 3), got {pos.shape}")
        q = np.array(self.quaternion, dtype=np.float64, copy=True)
        if q.shape != (k, 4):
            raise ValueError(f"quaternion must be ({k}, 4), got {q.shape}")
        norm = np.linalg.norm(q, axis=1)
        bad = ~(norm >= MIN_QUATERNION_NORM)  # also catches NaN
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"quaternion row {i} cannot be normalised: {q[i].tolist()}")
        q /= norm[:, None]
        q.flags.writeable = False
        force = None
        if self.force is not None:
            force = frozen_array(self.force, np.float64)
            if force.shape != (k, 3):
                raise ValueError(f"force must be ({k}, 3), got {force.shape}")
        extra = {}
        for name, col in dict(self.extra).items():
            c = frozen_array(col, np.float64)
            if c.shape != (k,):
                raise ValueError(f"extra column {name!r} must be ({k},), got {c.shape}")
            extra[str(name)] = c
        for name, value in (("t", t), ("position", pos), ("quaternion", q),
                            ("force", force), ("extra", extra)):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def has_force(self) -> bool:
        """True when ``fx, fy, fz`` were recorded."""
        return self.force is not None


@dataclass(frozen=True, eq=False)
class Frames(ArrayEq):
    """Depth-frame table of one sequence (``frames.csv``)."""

    index: np.ndarray
    """(M,) int64 frame numbers (unique)."""
    t: np.ndarray
    """(M,) float64, s; strictly increasing, same clock as the kinematics."""
    files: tuple[str, ...]
    """M cloud paths relative to the sequence folder, e.g. ``"clouds/000000.ply"``."""

    def __post_init__(self) -> None:
        index = frozen_array(self.index, np.int64)
        t = frozen_array(self.t, np.float64)
        files = tuple(str(f) for f in self.files)
        if index.ndim != 1 or t.shape != index.shape or len(files) != index.shape[0]:
            raise ValueError(
                f"index, t and files must have one length, got {index.shape}, {t.shape}, "
                f"{len(files)}"
            )
        object.__setattr__(self, "index", index)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "files", files)

    def __len__(self) -> int:
        return len(self.files)


@dataclass(frozen=True, eq=False)
class Corners(ArrayEq):
    """Calibration touches (``calibration/corners.csv``): the probe sphere centre, robot
    frame, while the sphere's lowest point touches a top corner of the phantom."""

    labels: tuple[str, ...]
    """K labels among ``"x0y0", "x1y0", "x0y1", "x1y1"`` (repeats allowed)."""
    positions: np.ndarray
    """(K, 3) float64, m, robot frame (read-only)."""

    def __post_init__(self) -> None:
        labels = tuple(str(s) for s in self.labels)
        pos = frozen_array(self.positions, np.float64)
        if pos.shape != (len(labels), 3):
            raise ValueError(f"positions must be ({len(labels)}, 3), got {pos.shape}")
        unknown = sorted(set(labels) - set(CORNER_LABELS))
        if unknown:
            raise ValueError(f"corner labels must be in {list(CORNER_LABELS)}, got {unknown}")
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "positions", pos)

    def __len__(self) -> int:
        return len(self.labels)

    def phantom_points(self, size: np.ndarray, radius: float) -> np.ndarray:
        """Phantom-frame sphere centres matching :attr:`positions` row by row.

        Args:
            size: (3,) phantom size, m (``PhantomSpec.size``).
            radius: probe radius, m.

        Returns:
            (K, 3) float64, m, phantom frame: ``(i * size[0], j * size[1], size[2] + radius)``
            for the label ``x{i}y{j}``.
        """
        size = np.asarray(size, dtype=np.float64)
        if size.shape != (3,):
            raise ValueError(f"size must be (3,), got {size.shape}")
        ij = np.array([CORNER_LABELS[s] for s in self.labels], dtype=np.float64).reshape(-1, 2)
        out = np.empty((len(self.labels), 3), dtype=np.float64)
        out[:, 0] = ij[:, 0] * size[0]
        out[:, 1] = ij[:, 1] * size[1]
        out[:, 2] = size[2] + float(radius)
        return out


@dataclass(frozen=True, eq=False)
class LandmarkTouches(ArrayEq):
    """Calibration touches of named landmarks (``calibration/landmarks.csv``): the probe
    sphere centre, robot frame, while the sphere touches the landmark from outside the
    phantom along the surface normal there (``SESSION_FORMAT.md``).

    Construction checks shapes and labels (ValueError); that the labels are landmarks of
    ``session.json``, and units, are checked by the reader and the writer
    (:func:`validate_landmark_touches`).
    """

    labels: tuple[str, ...]
    """K landmark names of ``SessionMeta.landmarks`` (repeats: repeated touches)."""
    positions: np.ndarray
    """(K, 3) float64, m, robot frame (read-only)."""

    def __post_init__(self) -> None:
        labels = tuple(self.labels)
        bad = [s for s in labels if not isinstance(s, str) or not s]
        if bad:
            raise ValueError(f"landmark labels must be non-empty strings, got {bad}")
        pos = frozen_array(self.positions, np.float64)
        if pos.shape != (len(labels), 3):
            raise ValueError(f"positions must be ({len(labels)}, 3), got {pos.shape}")
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "positions", pos)

    def __len__(self) -> int:
        return len(self.labels)


# --------------------------------------------------------------------------------------
# Validation shared by reader and writer (messages name the file)
# --------------------------------------------------------------------------------------


def validate_kinematics(path: Path, kin: Kinematics) -> None:
    """Checks that need the file context (shapes and quaternions are checked on
    construction)."""
    if len(kin) == 0:
        raise SessionFormatError(path, "no data rows")
    check_times(path, kin.t)
    check_finite(path, kin.position, ("x", "y", "z"))
    check_finite(path, kin.quaternion, ("qx", "qy", "qz", "qw"))
    if kin.force is not None:
        check_finite(path, kin.force, KIN_FORCE)
    check_positions_metres(path, kin.position, "probe position")


def validate_corners(path: Path, corners: Corners) -> None:
    if len(corners) < 4:
        raise SessionFormatError(path, f"needs at least 4 corner touches, got {len(corners)}")
    distinct = sorted(set(corners.labels))
    if len(distinct) < 3:
        raise SessionFormatError(
            path, f"needs touches of at least 3 distinct corners to register, got {distinct}"
        )
    check_finite(path, corners.positions, ("x", "y", "z"))
    check_positions_metres(path, corners.positions, "corner position")



def check_landmark_label(path: Path, row: int, label: str,
                         landmarks: Mapping[str, np.ndarray]) -> None:
    """Raise SessionFormatError (naming ``path`` and 1-based data ``row``) unless
    ``label`` is a landmark of ``session.json``."""
    if label in landmarks:
        return
    known = list(landmarks)
    have = (f"its landmarks are {known}" if known else
            "it names none (expected a top-level 'landmarks' object "
            "{\"<name>\": [x, y, z], ...} there)")
    raise SessionFormatError(
        path, f"column 'landmark' at {row_msg(row)}: {label!r} is not a landmark of session.json; "
              f"{have}",
    )


def validate_landmark_touches(path: Path, touches: LandmarkTouches,
                              landmarks: Mapping[str, np.ndarray]) -> None:
    """Check landmark touches against the landmarks of ``session.json``.

    Args:
        path: the ``landmarks.csv`` file (named in the errors).
        touches: the touches (robot frame, m).
        landmarks: ``SessionMeta.landmarks``: name -> (3,) point, m, phantom frame.

    Raises:
        SessionFormatError: no rows; a label that is not a landmark of ``session.json``;
            fewer than 3 distinct landmarks touched, or touched landmarks that are
            collinear (the rotation about their line is then not determined).
        ColumnError: non-finite positions.  UnitsError: a position > 5 m away.
    """
    if len(touches) == 0:
        raise SessionFormatError(path, "no data rows")
    for r, label in enumerate(touches.labels, start=1):
        check_landmark_label(path, r, label, landmarks)
    check_finite(path, touches.positions, ("x", "y", "z"))
    check_positions_metres(path, touches.positions, "landmark touch position")
    distinct = sorted(set(touches.labels))
    if len(distinct) < 3:
        raise SessionFormatError(
            path, f"needs touches of at least 3 distinct landmarks to register, got {distinct}"
        )
    if collinear(np.stack([landmarks[n] for n in distinct])):
        raise SessionFormatError(
            path,
            f"the touched landmarks {distinct} are collinear in session.json: they cannot fix "
            f"the rotation about their line; touch at least 3 non-collinear landmarks",
        )
