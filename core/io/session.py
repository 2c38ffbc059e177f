"""Recorded sessions (``tissue-session/1``): typed metadata, a validating reader and a
streaming writer.

The on-disk layout is defined in ``SESSION_FORMAT.md``::

    <session>/session.json
    <session>/phantom.stl                     optional
    <session>/calibration/corners.csv
    <session>/calibration/reference.ply       optional
    <session>/sequences/<name>/kinematics.csv
    <session>/sequences/<name>/frames.csv
    <session>/sequences/<name>/clouds/<frame>.ply
    <session>/truth.json                      optional, synthetic only; never read here
                                              except by :func:`read_truth` (tests, scorers)

Frames used below: *robot* (robot base frame: kinematics, corners, forces), *camera*
(depth-camera frame: every cloud) and *phantom* (box spans ``[0, size]``, z up, bottom
face at z = 0). All quantities SI (m, s, kg, N); quaternions ``x, y, z, w``.

:func:`read_session` validates ``session.json`` and every CSV eagerly and checks that
every cloud file exists; clouds are parsed lazily by :meth:`Sequence.cloud` (or all at
once with ``check_clouds=True``). :class:`SessionWriter` streams a session to disk one
cloud at a time (paper scale: 12 sequences x 1800 frames x 45k points) into a
temporary sibling folder and moves it into place only in :meth:`SessionWriter.finish`.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import operator
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path, PurePosixPath
from typing import Any, TextIO

import numpy as np

from core.errors import (
    ColumnError,
    MissingFileError,
    SessionFormatError,
    TimestampError,
    TissueTwinError,
    UnitsError,
)
from core.io.ply import check_ply, read_ply, write_ply

__all__ = [
    "FORMAT",
    "read_cloud",
    "ROLES",
    "CORNER_LABELS",
    "PhantomSpec",
    "ProbeSpec",
    "CameraSpec",
    "SequenceSpec",
    "SessionMeta",
    "Kinematics",
    "Frames",
    "Corners",
    "Sequence",
    "Session",
    "SessionExistsError",
    "read_session",
    "read_truth",
    "SessionWriter",
    "write_session",
]

FORMAT = "tissue-session/1"
"""Value of ``session.json["format"]`` this module reads and writes."""

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
_MAX_SIZE_M = 1.0  # phantom edge length / probe radius, m
_MAX_POSITION_NORM_M = 5.0  # corner and kinematic positions, robot frame, m
_MAX_CLOUD_MEDIAN_NORM_M = 5.0  # median distance of cloud points from the camera, m
_MIN_QUATERNION_NORM = 1e-9

_KIN_REQUIRED = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
_KIN_FORCE = ("fx", "fy", "fz")
_FRAMES_REQUIRED = ("frame", "t", "file")
_CORNERS_REQUIRED = ("corner", "x", "y", "z")


class SessionExistsError(TissueTwinError, FileExistsError):
    """:class:`SessionWriter` refuses to replace an existing path.

    Raised when the target exists and ``overwrite`` is false, or when ``overwrite``
    is true but the target is not a folder that looks like a session (holds a
    ``session.json``) or an empty folder: the writer never deletes anything else.
    """


# --------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------


def _frozen(a: Any, dtype: Any) -> np.ndarray:
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


class _ArrayEq:
    """Mixin: ``==`` for dataclasses holding arrays (field by field, exact)."""

    __hash__ = None  # holds arrays / dicts: not hashable

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))


def _row_msg(row: int) -> str:
    """Human row reference: 1-based data row and the file line (header is line 1)."""
    return f"row {row} (line {row + 1})"


# --------------------------------------------------------------------------------------
# Typed metadata
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PhantomSpec(_ArrayEq):
    """The phantom at rest, from ``session.json["phantom"]``.

    The phantom frame has the box spanning ``[0, size[0]] x [0, size[1]] x [0, size[2]]``,
    z up, bottom face at z = 0.
    """

    size: np.ndarray
    """(3,) float64, m: x length, y width, z height (read-only array)."""
    mass: float
    """kg."""
    fixed: str = "bottom"
    """Boundary condition; ``"bottom"``: every node on the z = 0 face is held."""
    shape: str = "box"
    """Rest shape kind; ``phantom.stl`` overrides ``size`` when present."""

    def __post_init__(self) -> None:
        size = _frozen(self.size, np.float64)
        if size.shape != (3,):
            raise ValueError(f"phantom size must be (3,), got {size.shape}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "mass", float(self.mass))


@dataclass(frozen=True)
class ProbeSpec:
    """The instrument tip, from ``session.json["probe"]``."""

    radius: float
    """Sphere radius, m. Kinematics give the sphere's centre."""
    shape: str = "sphere"
    """Tip shape; the format defines ``"sphere"``."""


@dataclass(frozen=True)
class CameraSpec:
    """The depth camera, from ``session.json["camera"]``."""

    rate_hz: float
    """Frame rate, Hz."""
    depth_accuracy: float
    """Depth noise scale, m (standard deviation as stated by the recorder)."""
    intrinsics: dict | None = None
    """Optional pinhole intrinsics as written (e.g. width, height, fx, fy, cx, cy), or None."""


@dataclass(frozen=True)
class SequenceSpec:
    """One entry of ``session.json["sequences"]``."""

    name: str
    """Folder name under ``sequences/``."""
    role: str
    """One of ``"train"``, ``"validation"``, ``"test"``."""

    def __post_init__(self) -> None:
        n = self.name
        if not isinstance(n, str) or not n or n in (".", "..") or "/" in n or "\\" in n:
            raise ValueError(f"sequence name must be a plain folder name, got {n!r}")
        if self.role not in ROLES:
            raise ValueError(f"sequence role must be one of {ROLES}, got {self.role!r}")


@dataclass(frozen=True, eq=False)
class SessionMeta(_ArrayEq):
    """The content of ``session.json``: typed fields plus everything else, kept verbatim."""

    phantom: PhantomSpec
    probe: ProbeSpec
    camera: CameraSpec
    sequences: tuple[SequenceSpec, ...]
    """In file order; names are unique."""
    raw: dict = field(default_factory=dict)
    """The whole ``session.json`` as read (unknown keys at any level are kept and written
    back by :meth:`to_json`); empty for metadata built in code."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "sequences", tuple(self.sequences))
        names = [s.name for s in self.sequences]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"sequence names must be unique, got duplicates {dup}")

    def sequence(self, name: str) -> SequenceSpec:
        """The :class:`SequenceSpec` called ``name`` (KeyError if absent)."""
        for s in self.sequences:
            if s.name == name:
                return s
        raise KeyError(f"no sequence {name!r}; have {[s.name for s in self.sequences]}")

    def to_json(self) -> dict:
        """The ``session.json`` object: :attr:`raw` with the typed fields written over it.

        Unknown keys of :attr:`raw` (top level, inside ``phantom``/``probe``/``camera``
        and inside each sequence entry, matched by name) are preserved; ``"format"`` is
        set to ``"tissue-session/1"``. Returns a new dict (JSON-serialisable).
        """
        raw = copy.deepcopy(self.raw)
        out: dict[str, Any] = {"format": FORMAT}
        out.update((k, v) for k, v in raw.items() if k != "format")

        def _sub(key: str) -> dict:
            v = raw.get(key)
            return dict(v) if isinstance(v, dict) else {}

        phantom = _sub("phantom")
        phantom.update(
            shape=self.phantom.shape,
            size=[float(v) for v in self.phantom.size],
            mass=float(self.phantom.mass),
            fixed=self.phantom.fixed,
        )
        probe = _sub("probe")
        probe.update(shape=self.probe.shape, radius=float(self.probe.radius))
        camera = _sub("camera")
        camera.update(rate_hz=float(self.camera.rate_hz),
                      depth_accuracy=float(self.camera.depth_accuracy))
        if self.camera.intrinsics is None:
            camera.pop("intrinsics", None)
        else:
            camera["intrinsics"] = copy.deepcopy(self.camera.intrinsics)
        raw_seqs = {
            s["name"]: s
            for s in (raw.get("sequences") if isinstance(raw.get("sequences"), list) else [])
            if isinstance(s, dict) and isinstance(s.get("name"), str)
        }
        sequences = []
        for s in self.sequences:
            entry = dict(raw_seqs.get(s.name, {}))
            entry.update(name=s.name, role=s.role)
            sequences.append(entry)
        out.update(phantom=phantom, probe=probe, camera=camera, sequences=sequences)
        return out

    @classmethod
    def from_json(cls, obj: Any, path: str | os.PathLike = "session.json") -> SessionMeta:
        """Validate a parsed ``session.json`` object and build the metadata.

        Args:
            obj: the parsed JSON value.
            path: the file it came from (named in error messages).

        Raises:
            SessionFormatError: wrong ``format``, missing ``phantom``/``probe``/``camera``/
                ``sequences``, wrong types, non-positive size/mass/radius/rate, bad role,
                bad or duplicate sequence names.
            UnitsError: a phantom dimension or the probe radius > 1 m (millimetres).
        """
        return _parse_meta(Path(path), obj)


# --------------------------------------------------------------------------------------
# Typed data
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Kinematics(_ArrayEq):
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
        t = _frozen(self.t, np.float64)
        if t.ndim != 1:
            raise ValueError(f"t must be (K,), got {t.shape}")
        k = t.shape[0]
        pos = _frozen(self.position, np.float64)
        if pos.shape != (k, 3):
            raise ValueError(f"position must be ({k}, 3), got {pos.shape}")
        q = np.array(self.quaternion, dtype=np.float64, copy=True)
        if q.shape != (k, 4):
            raise ValueError(f"quaternion must be ({k}, 4), got {q.shape}")
        norm = np.linalg.norm(q, axis=1)
        bad = ~(norm >= _MIN_QUATERNION_NORM)  # also catches NaN
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"quaternion row {i} cannot be normalised: {q[i].tolist()}")
        q /= norm[:, None]
        q.flags.writeable = False
        force = None
        if self.force is not None:
            force = _frozen(self.force, np.float64)
            if force.shape != (k, 3):
                raise ValueError(f"force must be ({k}, 3), got {force.shape}")
        extra = {}
        for name, col in dict(self.extra).items():
            c = _frozen(col, np.float64)
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
class Frames(_ArrayEq):
    """Depth-frame table of one sequence (``frames.csv``)."""

    index: np.ndarray
    """(M,) int64 frame numbers (unique)."""
    t: np.ndarray
    """(M,) float64, s; strictly increasing, same clock as the kinematics."""
    files: tuple[str, ...]
    """M cloud paths relative to the sequence folder, e.g. ``"clouds/000000.ply"``."""

    def __post_init__(self) -> None:
        index = _frozen(self.index, np.int64)
        t = _frozen(self.t, np.float64)
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
class Corners(_ArrayEq):
    """Calibration touches (``calibration/corners.csv``): the probe sphere centre, robot
    frame, while the sphere's lowest point touches a top corner of the phantom."""

    labels: tuple[str, ...]
    """K labels among ``"x0y0", "x1y0", "x0y1", "x1y1"`` (repeats allowed)."""
    positions: np.ndarray
    """(K, 3) float64, m, robot frame (read-only)."""

    def __post_init__(self) -> None:
        labels = tuple(str(s) for s in self.labels)
        pos = _frozen(self.positions, np.float64)
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


# --------------------------------------------------------------------------------------
# Validation shared by reader and writer (messages name the file)
# --------------------------------------------------------------------------------------


def _check_times(path: Path, t: np.ndarray, column: str = "t") -> None:
    """Raise TimestampError unless ``t`` is finite and strictly increasing."""
    finite = np.isfinite(t)
    if not finite.all():
        r = int(np.flatnonzero(~finite)[0])
        raise TimestampError(
            path, f"column '{column}' is not finite at {_row_msg(r + 1)}: {float(t[r])}"
        )
    d = np.diff(t)
    bad = ~(d > 0)
    if bad.any():
        r = int(np.flatnonzero(bad)[0]) + 1
        dup = ", a duplicate" if d[r - 1] == 0 else ""
        raise TimestampError(
            path,
            f"column '{column}' is not strictly increasing at {_row_msg(r + 1)} "
            f"({float(t[r])!r} after {float(t[r - 1])!r}{dup})",
        )


def _check_finite(path: Path, values: np.ndarray, columns: tuple[str, ...]) -> None:
    """Raise ColumnError at the first non-finite cell of (K, C) ``values``."""
    finite = np.isfinite(values)
    if not finite.all():
        r, c = (int(v) for v in np.argwhere(~finite)[0])
        raise ColumnError(
            path, f"column '{columns[c]}' is not finite at {_row_msg(r + 1)}: {float(values[r, c])}"
        )


def _check_positions_metres(path: Path, positions: np.ndarray, what: str) -> None:
    """Raise UnitsError if any (K, 3) position is farther than 5 m from the origin."""
    if len(positions) == 0:
        return
    norms = np.linalg.norm(positions, axis=1)
    r = int(np.argmax(norms))
    if norms[r] > _MAX_POSITION_NORM_M:
        raise UnitsError(
            path,
            f"{what} at {_row_msg(r + 1)} is {norms[r]:.6g} m from the robot origin "
            f"({positions[r].tolist()}): looks like millimetres, the format uses metres "
            f"(limit {_MAX_POSITION_NORM_M} m)",
        )


def _check_cloud_metres(path: Path, points: np.ndarray) -> None:
    """Raise UnitsError if the median distance of (N, 3) points from the camera > 5 m."""
    med = float(np.median(np.linalg.norm(points, axis=1)))
    if med > _MAX_CLOUD_MEDIAN_NORM_M:
        raise UnitsError(
            path,
            f"median point distance from the camera is {med:.6g} m: looks like millimetres, "
            f"the format uses metres (limit {_MAX_CLOUD_MEDIAN_NORM_M} m)",
        )


def read_cloud(path: str | os.PathLike) -> np.ndarray:
    """One depth cloud file (a PLY of the session format), read and checked.

    Returns:
        ``points_camera``: (N, 3) float64, m, camera frame (non-finite points dropped), N >= 1.

    Raises:
        MissingFileError: the file is gone.
        PlyError: malformed, truncated or empty PLY, no float x, y, z.
        UnitsError: median point distance from the camera > 5 m (millimetres).
    """
    path = Path(path)
    points = read_ply(path)
    _check_cloud_metres(path, points)
    return points


def _check_points_arg(points: Any) -> np.ndarray:
    """Writer argument check: (N, 3) finite, N >= 1 (ValueError otherwise)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"points must be (N, 3) with N >= 1, got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points must be finite")
    return pts


def _validate_kinematics(path: Path, kin: Kinematics) -> None:
    """Checks that need the file context (shapes and quaternions are checked on
    construction)."""
    if len(kin) == 0:
        raise SessionFormatError(path, "no data rows")
    _check_times(path, kin.t)
    _check_finite(path, kin.position, ("x", "y", "z"))
    _check_finite(path, kin.quaternion, ("qx", "qy", "qz", "qw"))
    if kin.force is not None:
        _check_finite(path, kin.force, _KIN_FORCE)
    _check_positions_metres(path, kin.position, "probe position")


def _validate_corners(path: Path, corners: Corners) -> None:
    if len(corners) < 4:
        raise SessionFormatError(path, f"needs at least 4 corner touches, got {len(corners)}")
    distinct = sorted(set(corners.labels))
    if len(distinct) < 3:
        raise SessionFormatError(
            path, f"needs touches of at least 3 distinct corners to register, got {distinct}"
        )
    _check_finite(path, corners.positions, ("x", "y", "z"))
    _check_positions_metres(path, corners.positions, "corner position")


# --------------------------------------------------------------------------------------
# session.json
# --------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _get_obj(path: Path, parent: dict, key: str, where: str = "") -> dict:
    if key not in parent:
        raise SessionFormatError(path, f"missing required key '{where}{key}'")
    v = parent[key]
    if not isinstance(v, dict):
        raise SessionFormatError(path, f"'{where}{key}' must be an object, got {v!r}")
    return v


def _get_str(path: Path, obj: dict, key: str, where: str, default: str | None) -> str:
    if key not in obj:
        if default is None:
            raise SessionFormatError(path, f"missing required key '{where}{key}'")
        return default
    v = obj[key]
    if not isinstance(v, str) or not v:
        raise SessionFormatError(path, f"'{where}{key}' must be a non-empty string, got {v!r}")
    return v


def _get_num(path: Path, obj: dict, key: str, where: str, *, positive: bool = True,
             default: float | None = None) -> float:
    name = f"{where}{key}"
    if key not in obj:
        if default is not None:
            return default
        raise SessionFormatError(path, f"missing required key '{name}'")
    v = obj[key]
    if not _is_number(v) or not math.isfinite(v):
        raise SessionFormatError(path, f"'{name}' must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise SessionFormatError(path, f"'{name}' must be positive, got {v!r}")
    if not positive and v < 0:
        raise SessionFormatError(path, f"'{name}' must be non-negative, got {v!r}")
    return float(v)


def _parse_meta(path: Path, obj: Any) -> SessionMeta:
    if not isinstance(obj, dict):
        raise SessionFormatError(path, f"top level must be a JSON object, got {type(obj).__name__}")
    fmt = obj.get("format")
    if fmt != FORMAT:
        raise SessionFormatError(path, f"'format' must be {FORMAT!r}, got {fmt!r}")

    ph = _get_obj(path, obj, "phantom")
    size = ph.get("size")
    if (not isinstance(size, list) or len(size) != 3
            or not all(_is_number(v) and math.isfinite(v) for v in size)):
        raise SessionFormatError(path, f"'phantom.size' must be 3 finite numbers, got {size!r}")
    if any(v <= 0 for v in size):
        raise SessionFormatError(path, f"'phantom.size' must be positive, got {size!r}")
    if any(v > _MAX_SIZE_M for v in size):
        raise UnitsError(
            path,
            f"'phantom.size' = {size!r} looks like millimetres: the format uses metres "
            f"(every dimension must be <= {_MAX_SIZE_M} m)",
        )
    phantom = PhantomSpec(
        size=np.array(size, dtype=np.float64),
        mass=_get_num(path, ph, "mass", "phantom."),
        fixed=_get_str(path, ph, "fixed", "phantom.", "bottom"),
        shape=_get_str(path, ph, "shape", "phantom.", "box"),
    )

    pr = _get_obj(path, obj, "probe")
    radius = _get_num(path, pr, "radius", "probe.")
    if radius > _MAX_SIZE_M:
        raise UnitsError(
            path,
            f"'probe.radius' = {radius!r} looks like millimetres: the format uses metres "
            f"(must be <= {_MAX_SIZE_M} m)",
        )
    probe = ProbeSpec(radius=radius, shape=_get_str(path, pr, "shape", "probe.", "sphere"))

    cam = _get_obj(path, obj, "camera")
    intrinsics = cam.get("intrinsics")
    if intrinsics is not None and not isinstance(intrinsics, dict):
        raise SessionFormatError(
            path, f"'camera.intrinsics' must be an object or absent, got {intrinsics!r}"
        )
    camera = CameraSpec(
        rate_hz=_get_num(path, cam, "rate_hz", "camera."),
        depth_accuracy=_get_num(path, cam, "depth_accuracy", "camera.", positive=False),
        intrinsics=copy.deepcopy(intrinsics),
    )

    if "sequences" not in obj:
        raise SessionFormatError(path, "missing required key 'sequences'")
    seqs = obj["sequences"]
    if not isinstance(seqs, list):
        raise SessionFormatError(path, f"'sequences' must be a list, got {seqs!r}")
    specs: list[SequenceSpec] = []
    seen: set[str] = set()
    for i, s in enumerate(seqs):
        where = f"sequences[{i}]."
        if not isinstance(s, dict):
            raise SessionFormatError(path, f"'sequences[{i}]' must be an object, got {s!r}")
        name = _get_str(path, s, "name", where, None)
        if name in (".", "..") or "/" in name or "\\" in name or name.strip() != name:
            raise SessionFormatError(path, f"'{where}name' = {name!r} is not a valid folder name")
        role = s.get("role")
        if role not in ROLES:
            raise SessionFormatError(
                path, f"'{where}role' of sequence {name!r} must be one of {list(ROLES)}, got {role!r}"
            )
        if name in seen:
            raise SessionFormatError(path, f"duplicate sequence name {name!r}")
        seen.add(name)
        specs.append(SequenceSpec(name=name, role=role))

    return SessionMeta(phantom=phantom, probe=probe, camera=camera, sequences=tuple(specs),
                       raw=copy.deepcopy(obj))


def _read_meta(path: Path) -> SessionMeta:
    if not path.is_file():
        raise MissingFileError(path, "session.json does not exist")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SessionFormatError(path, f"not UTF-8 text ({exc})") from exc
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionFormatError(
            path, f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from exc
    return _parse_meta(path, obj)


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
                    path, f"{_row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            vals = []
            for c, cell in enumerate(row):
                try:
                    vals.append(float(cell))
                except ValueError:
                    raise ColumnError(
                        path, f"column '{names[c]}' is not numeric at {_row_msg(r)}: {cell!r}"
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


def _read_kinematics(path: Path) -> Kinematics:
    expected = "t,x,y,z,qx,qy,qz,qw[,fx,fy,fz][,extra...]"
    names, data = _read_numeric_csv(path, "kinematics.csv", _KIN_REQUIRED, expected)
    present = [c for c in _KIN_FORCE if c in names]
    if present and len(present) != 3:
        raise ColumnError(
            path,
            f"partial force columns {present}: give all of fx,fy,fz or none (got {names})",
        )
    if len(data) == 0:
        raise SessionFormatError(path, "no data rows")
    col = {n: data[:, i] for i, n in enumerate(names)}
    t = col["t"]
    _check_times(path, t)
    pos = np.stack([col[c] for c in "xyz"], axis=1)
    _check_finite(path, pos, ("x", "y", "z"))
    q = np.stack([col[c] for c in ("qx", "qy", "qz", "qw")], axis=1)
    _check_finite(path, q, ("qx", "qy", "qz", "qw"))
    qn = np.linalg.norm(q, axis=1)
    zero = qn < _MIN_QUATERNION_NORM
    if zero.any():
        r = int(np.flatnonzero(zero)[0]) + 1
        raise ColumnError(path, f"zero quaternion at {_row_msg(r)}: {q[r - 1].tolist()}")
    force = None
    if present:
        force = np.stack([col[c] for c in _KIN_FORCE], axis=1)
        _check_finite(path, force, _KIN_FORCE)
    _check_positions_metres(path, pos, "probe position")
    known = set(_KIN_REQUIRED) | set(_KIN_FORCE)
    extra = {n: col[n] for n in names if n not in known}
    return Kinematics(t=t, position=pos, quaternion=q, force=force, extra=extra)


def _read_frames(path: Path) -> Frames:
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
                    path, f"{_row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            try:
                index.append(int(row[ci["frame"]]))
            except ValueError:
                raise ColumnError(
                    path, f"column 'frame' is not an integer at {_row_msg(r)}: {row[ci['frame']]!r}"
                ) from None
            try:
                times.append(float(row[ci["t"]]))
            except ValueError:
                raise ColumnError(
                    path, f"column 't' is not numeric at {_row_msg(r)}: {row[ci['t']]!r}"
                ) from None
            file = row[ci["file"]].strip()
            p = PurePosixPath(file.replace("\\", "/"))
            if not file or p.is_absolute() or ".." in p.parts or ":" in file:
                raise SessionFormatError(
                    path,
                    f"column 'file' at {_row_msg(r)} must be a path inside the sequence "
                    f"folder, got {file!r}",
                )
            files.append(p.as_posix())
    if not files:
        raise SessionFormatError(path, "no frames (only a header)")
    t = np.array(times, dtype=np.float64)
    _check_times(path, t)
    idx = np.array(index, dtype=np.int64)
    uniq, first, counts = np.unique(idx, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = int(uniq[counts > 1][0])
        rows = [int(i) + 1 for i in np.flatnonzero(idx == dup)]
        raise ColumnError(path, f"column 'frame' repeats frame number {dup} at rows {rows}")
    return Frames(index=idx, t=t, files=tuple(files))


def _read_corners(path: Path) -> Corners:
    f, names = _open_csv(path, "corners.csv")
    labels: list[str] = []
    values: list[list[float]] = []
    with f:
        _require_columns(path, names, _CORNERS_REQUIRED, "corner,x,y,z")
        ci = [names.index(c) for c in _CORNERS_REQUIRED]
        for r, row in enumerate(csv.reader(f), start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(names):
                raise ColumnError(
                    path, f"{_row_msg(r)} has {len(row)} fields, the header has {len(names)}"
                )
            label = row[ci[0]].strip()
            if label not in CORNER_LABELS:
                raise ColumnError(
                    path,
                    f"column 'corner' at {_row_msg(r)} must be one of {list(CORNER_LABELS)}, "
                    f"got {label!r}",
                )
            xyz = []
            for c, name in zip(ci[1:], "xyz"):
                try:
                    xyz.append(float(row[c]))
                except ValueError:
                    raise ColumnError(
                        path, f"column '{name}' is not numeric at {_row_msg(r)}: {row[c]!r}"
                    ) from None
            labels.append(label)
            values.append(xyz)
    corners = Corners(labels=tuple(labels),
                      positions=np.array(values, dtype=np.float64).reshape(-1, 3))
    _validate_corners(path, corners)
    return corners


# --------------------------------------------------------------------------------------
# Session and Sequence
# --------------------------------------------------------------------------------------


class Sequence:
    """One recorded sequence: probe kinematics and depth frames.

    Attributes:
        name: folder name under ``sequences/``.
        role: ``"train"``, ``"validation"`` or ``"test"``.
        path: the sequence folder.
        kinematics: :class:`Kinematics` (robot frame).
        frames: :class:`Frames` (one row per depth frame).
    """

    def __init__(self, name: str, role: str, path: Path, kinematics: Kinematics,
                 frames: Frames):
        self.name = name
        self.role = role
        self.path = Path(path)
        self.kinematics = kinematics
        self.frames = frames

    def __len__(self) -> int:
        """Number of depth frames."""
        return len(self.frames)

    def __repr__(self) -> str:
        return (f"Sequence(name={self.name!r}, role={self.role!r}, frames={len(self)}, "
                f"kinematics={len(self.kinematics)}, force={self.has_force})")

    @property
    def has_force(self) -> bool:
        """True when the kinematics hold ``fx, fy, fz``."""
        return self.kinematics.has_force

    def _row(self, i: int) -> int:
        i = operator.index(i)
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame row {i} out of range for sequence {self.name!r} with {n} frames")
        return i % n

    def cloud_path(self, i: int) -> Path:
        """Path of the cloud of frame row ``i`` (0-based row of ``frames.csv``)."""
        return self.path / self.frames.files[self._row(i)]

    def cloud(self, i: int) -> np.ndarray:
        """The depth cloud of frame row ``i`` (0-based row of ``frames.csv``, negative
        counts from the end).

        Returns:
            ``points_camera``: (N, 3) float64, m, camera frame, raw (may hold table,
            instrument and outliers; non-finite points dropped), N >= 1.

        Raises:
            IndexError: ``i`` out of range.
            MissingFileError: the file is gone.
            PlyError: malformed, truncated or empty PLY, no float x, y, z.
            UnitsError: median point distance from the camera > 5 m (millimetres).
        """
        return read_cloud(self.cloud_path(i))

    def clouds(self) -> Iterator[tuple[int, float, np.ndarray]]:
        """Iterate ``(frame number, t [s], points_camera (N, 3) float64 m)`` in file
        order, one cloud in memory at a time."""
        for i in range(len(self)):
            yield int(self.frames.index[i]), float(self.frames.t[i]), self.cloud(i)


class Session:
    """A recorded session read by :func:`read_session`.

    Attributes:
        path: the session folder.
        meta: :class:`SessionMeta` from ``session.json``.
        corners: :class:`Corners` from ``calibration/corners.csv`` (robot frame).
        sequences: name -> :class:`Sequence`, in ``session.json`` order.
        phantom_stl: ``phantom.stl`` (phantom-frame rest surface, m) or None if absent.
        reference_path: ``calibration/reference.ply`` or None if absent.
    """

    def __init__(self, path: Path, meta: SessionMeta, corners: Corners,
                 sequences: dict[str, Sequence], phantom_stl: Path | None,
                 reference_path: Path | None):
        self.path = Path(path)
        self.meta = meta
        self.corners = corners
        self.sequences = sequences
        self.phantom_stl = phantom_stl
        self.reference_path = reference_path

    def __repr__(self) -> str:
        seqs = ", ".join(f"{s.name}:{s.role}:{len(s)}" for s in self.sequences.values())
        return f"Session({str(self.path)!r}, sequences=[{seqs}], force={self.has_force})"

    @property
    def has_force(self) -> bool:
        """True when every sequence has ``fx, fy, fz`` (False for a session without
        sequences)."""
        return bool(self.sequences) and all(s.has_force for s in self.sequences.values())

    def sequences_with_role(self, role: str) -> list[Sequence]:
        """The sequences whose role is ``role`` (``"train"``, ``"validation"``, ``"test"``),
        in file order. Raises ValueError for another role."""
        if role not in ROLES:
            raise ValueError(f"role must be one of {ROLES}, got {role!r}")
        return [s for s in self.sequences.values() if s.role == role]

    def reference_cloud(self) -> np.ndarray | None:
        """``calibration/reference.ply``: the phantom at rest, no instrument.

        Returns:
            ``points_camera``: (N, 3) float64, m, camera frame, or None if absent.

        Raises:
            PlyError, UnitsError: as :meth:`Sequence.cloud`.
        """
        if self.reference_path is None:
            return None
        points = read_ply(self.reference_path)
        _check_cloud_metres(self.reference_path, points)
        return points

    def phantom_mesh(self):
        """``phantom.stl`` as a ``trimesh.Trimesh`` (phantom frame, m), or None if absent.

        Raises:
            SessionFormatError: the file cannot be parsed as a mesh.
            UnitsError: its bounding box is larger than 1 m (millimetres).
        """
        if self.phantom_stl is None:
            return None
        import trimesh  # noqa: PLC0415 (heavy, only needed here)

        try:
            mesh = trimesh.load_mesh(str(self.phantom_stl), file_type="stl")
        except Exception as exc:  # trimesh raises many types on bad input
            raise SessionFormatError(self.phantom_stl, f"cannot read STL ({exc})") from exc
        ext = np.asarray(mesh.extents, dtype=np.float64)
        if ext.size != 3 or not np.isfinite(ext).all() or len(mesh.faces) == 0:
            raise SessionFormatError(self.phantom_stl, "empty or degenerate mesh")
        if (ext > _MAX_SIZE_M).any():
            raise UnitsError(self.phantom_stl, f"extents {ext.tolist()} look like millimetres: "
                                               f"the format uses metres")
        return mesh


def read_session(path: str | os.PathLike, *, check_clouds: bool = False) -> Session:
    """Read and validate a session folder (``tissue-session/1``).

    ``session.json``, ``calibration/corners.csv`` and every ``kinematics.csv`` and
    ``frames.csv`` are parsed and validated now, and every cloud file listed in a
    ``frames.csv`` must exist. Clouds are parsed only when asked for
    (:meth:`Sequence.cloud`) unless ``check_clouds`` is true: then every PLY header and
    file size (and the reference cloud's) is checked now. ``truth.json`` is never read.

    Args:
        path: the session folder.
        check_clouds: check every cloud file's header and size up front.

    Returns:
        :class:`Session`.

    Raises:
        MissingFileError: no such folder, or a missing ``session.json``,
            ``corners.csv``, sequence folder, ``kinematics.csv``, ``frames.csv`` or cloud.
        SessionFormatError: bad ``session.json`` (not JSON, wrong format, missing or
            invalid fields, bad role, duplicate names), a CSV without data rows, a cloud
            path leaving its sequence folder, fewer than 4 corner touches.
        ColumnError: missing, partial (force), duplicate or non-numeric CSV columns,
            non-finite positions, quaternions or forces, a zero quaternion, an unknown
            corner label, repeated frame numbers.
        TimestampError: NaN/inf or not strictly increasing ``t``.
        UnitsError: phantom size or probe radius > 1 m, positions > 5 m from the robot
            origin (millimetres).
        PlyError: (``check_clouds``) a malformed, truncated or empty cloud.
    """
    root = Path(path)
    if not root.is_dir():
        raise MissingFileError(root, "session folder does not exist")
    meta = _read_meta(root / "session.json")
    corners = _read_corners(root / "calibration" / "corners.csv")
    reference = root / "calibration" / "reference.ply"
    stl = root / "phantom.stl"
    listings: dict[Path, set[str]] = {}
    sequences: dict[str, Sequence] = {}
    for spec in meta.sequences:
        seq_dir = root / "sequences" / spec.name
        if not seq_dir.is_dir():
            raise MissingFileError(
                seq_dir, f"folder of sequence {spec.name!r} (listed in session.json) does not exist"
            )
        kin = _read_kinematics(seq_dir / "kinematics.csv")
        frames_path = seq_dir / "frames.csv"
        frames = _read_frames(frames_path)
        for r, rel in enumerate(frames.files, start=1):
            file = seq_dir / rel
            parent = file.parent
            if parent not in listings:
                try:
                    listings[parent] = set(os.listdir(parent))
                except OSError:
                    listings[parent] = set()
            if file.name not in listings[parent]:
                raise MissingFileError(
                    file, f"cloud listed in {frames_path} at {_row_msg(r)} does not exist"
                )
        sequences[spec.name] = Sequence(spec.name, spec.role, seq_dir, kin, frames)
    session = Session(root, meta, corners, sequences,
                      phantom_stl=stl if stl.is_file() else None,
                      reference_path=reference if reference.is_file() else None)
    if check_clouds:
        if session.reference_path is not None:
            check_ply(session.reference_path)
        for seq in sequences.values():
            for rel in seq.frames.files:
                check_ply(seq.path / rel)
    return session


def read_truth(path: str | os.PathLike) -> dict | None:
    """``truth.json`` of a synthetic session, or None if absent.

    For tests and scorers only: the analysis pipeline must never call this
    (``SESSION_FORMAT.md``).

    Raises:
        SessionFormatError: the file is not a JSON object.
    """
    return _optional_json_object(Path(path) / "truth.json")


def _optional_json_object(p: Path) -> dict | None:
    """The JSON object in file ``p``, or None when it does not exist.

    Raises:
        SessionFormatError: not valid JSON, or not an object at the top level.
    """
    if not p.is_file():
        return None
    try:
        obj = json.loads(p.read_text(encoding="utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SessionFormatError(p, f"not valid JSON ({exc})") from exc
    if not isinstance(obj, dict):
        raise SessionFormatError(p, f"top level must be a JSON object, got {type(obj).__name__}")
    return obj


PICKED_FILE = Path("calibration") / "picked.json"
"""Project-private extra of a session folder: point pairs a user picked to initialise
the camera's ICP (written by the workbench; not part of SESSION_FORMAT.md)."""


def read_picked(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray] | None:
    """Accepted picked point pairs of a session (``calibration/picked.json``), or None.

    Returns:
        (points_camera (K, 3), points_phantom (K, 3)) float64, m, K >= 3, in the camera
        and phantom frames.

    Raises:
        SessionFormatError: the file exists but is not a valid ``tissuetwin-picked/1``.
    """
    p = Path(path) / PICKED_FILE
    obj = _optional_json_object(p)
    if obj is None:
        return None
    if obj.get("format") != "tissuetwin-picked/1":
        raise SessionFormatError(p, "expected \"format\": \"tissuetwin-picked/1\"")
    try:
        cam = np.asarray(obj["points_camera"], dtype=np.float64)
        pha = np.asarray(obj["points_phantom"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise SessionFormatError(p, f"points_camera and points_phantom must be lists of [x, y, z] ({exc})") from exc
    if cam.ndim != 2 or cam.shape[1:] != (3,) or cam.shape != pha.shape or cam.shape[0] < 3:
        raise SessionFormatError(p, f"need K >= 3 matching [x, y, z] pairs, got {cam.shape} and {pha.shape}")
    if not (np.all(np.isfinite(cam)) and np.all(np.isfinite(pha))):
        raise SessionFormatError(p, "picked points must be finite")
    return cam, pha


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _fmt(v: float) -> str:
    """Shortest decimal that reads back as the same float64 (``repr``)."""
    return repr(float(v))


def _write_table(path: Path, header: list[str], data: np.ndarray) -> None:
    """Write a numeric (K, C) table as CSV with round-trip-exact floats."""
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(header) + "\n")
        # tolist() gives Python floats; repr is exact and as short as possible.
        f.writelines(",".join(map(repr, row)) + "\n" for row in data.tolist())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _valid_column_name(name: str) -> bool:
    return bool(name) and name.strip() == name and not any(c in name for c in ',"\r\n')


class SessionWriter:
    """Stream a session to disk (``tissue-session/1``), one cloud at a time.

    Everything is written into a temporary hidden sibling folder
    (``.<name>.<random>.partial``); :meth:`finish` writes ``session.json`` and every
    ``frames.csv`` and then renames the folder into place, so a reader never sees a
    half-written session. Used as a context manager, an exception removes the temporary
    folder and leaves any existing session untouched; a clean exit calls :meth:`finish`
    if it was not called yet.

    Data are validated as the reader would (same error classes, naming the target
    file), so a session that was written can be read. Required before :meth:`finish`:
    :meth:`write_corners`, and for every sequence of ``meta`` :meth:`write_kinematics`
    and at least one :meth:`write_frame`.

    Example::

        with SessionWriter(out, meta) as w:
            w.write_corners(corners)
            for name in names:
                w.write_kinematics(name, kin[name])
                for k, (t, pts) in enumerate(frames[name]):
                    w.write_frame(name, k, t, pts)
    """

    def __init__(self, path: str | os.PathLike, meta: SessionMeta, *, overwrite: bool = False,
                 ply_binary: bool = True):
        """
        Args:
            path: the session folder to create.
            meta: the metadata; its sequences are the ones that may be written.
            overwrite: replace an existing session folder (or empty folder) at
                :meth:`finish`; without it an existing ``path`` is an error.
            ply_binary: write clouds as binary little-endian (default) or ASCII PLY.

        Raises:
            SessionExistsError: ``path`` exists and ``overwrite`` is false, or it exists
                but is not a session folder (no ``session.json``) nor an empty folder.
            SessionFormatError, UnitsError: ``meta`` would not pass :func:`read_session`.
            TypeError: ``meta`` is not a :class:`SessionMeta`.
        """
        if not isinstance(meta, SessionMeta):
            raise TypeError(f"meta must be a SessionMeta, got {type(meta).__name__}")
        self.path = Path(path)
        self.meta = meta
        self.overwrite = overwrite
        self.ply_binary = ply_binary
        # The metadata must pass the reader's checks (units, positivity, roles).
        _parse_meta(self.path / "session.json", meta.to_json())
        self._check_target()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp: Path | None = Path(
            tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent)
        )
        self._state = "open"
        self._corners = False
        self._kinematics: set[str] = set()
        self._rows: dict[str, list[tuple[int, float, str]]] = {}
        self._frame_numbers: dict[str, set[int]] = {}
        for s in meta.sequences:
            (self._tmp / "sequences" / s.name / "clouds").mkdir(parents=True)
            self._rows[s.name] = []
            self._frame_numbers[s.name] = set()
        (self._tmp / "calibration").mkdir()

    # -- helpers -------------------------------------------------------------------------

    def __repr__(self) -> str:
        return f"SessionWriter({str(self.path)!r}, state={self._state!r})"

    def _check_target(self) -> None:
        p = self.path
        if not (p.exists() or p.is_symlink()):
            return
        if not self.overwrite:
            raise SessionExistsError(
                f"{p}: already exists; pass overwrite=True to replace it"
            )
        if not p.is_dir() or p.is_symlink():
            raise SessionExistsError(f"{p}: exists and is not a folder; refusing to replace it")
        if not (p / "session.json").is_file() and any(p.iterdir()):
            raise SessionExistsError(
                f"{p}: exists, is not empty and holds no session.json; refusing to replace it"
            )

    def _need_open(self) -> Path:
        if self._state != "open" or self._tmp is None:
            raise RuntimeError(f"{self!r} is {self._state}; no more writes possible")
        return self._tmp

    def _need_sequence(self, sequence: str) -> None:
        if sequence not in self._rows:
            raise KeyError(
                f"sequence {sequence!r} is not in the metadata; have {list(self._rows)}"
            )

    # -- writes --------------------------------------------------------------------------

    def write_corners(self, corners: Corners) -> None:
        """Write ``calibration/corners.csv`` (robot-frame sphere centres, m).

        Raises:
            SessionFormatError: fewer than 4 touches or 3 distinct corners.
            ColumnError: non-finite positions.  UnitsError: a position > 5 m away.
        """
        tmp = self._need_open()
        if not isinstance(corners, Corners):
            raise TypeError(f"corners must be Corners, got {type(corners).__name__}")
        _validate_corners(self.path / "calibration" / "corners.csv", corners)
        with open(tmp / "calibration" / "corners.csv", "w", encoding="utf-8", newline="\n") as f:
            f.write("corner,x,y,z\n")
            for label, p in zip(corners.labels, corners.positions.tolist()):
                f.write(f"{label},{_fmt(p[0])},{_fmt(p[1])},{_fmt(p[2])}\n")
        self._corners = True

    def write_reference(self, points_camera: np.ndarray) -> None:
        """Write ``calibration/reference.ply``: (N, 3) camera-frame points, m, of the
        phantom at rest (float32 on disk).

        Raises:
            ValueError: not a finite (N, 3) array with N >= 1.
            UnitsError: median distance from the camera > 5 m.
        """
        tmp = self._need_open()
        pts = _check_points_arg(points_camera)
        _check_cloud_metres(self.path / "calibration" / "reference.ply", pts)
        write_ply(tmp / "calibration" / "reference.ply", pts, binary=self.ply_binary)

    def write_phantom_stl(self, mesh: Any) -> None:
        """Write ``phantom.stl``, the rest surface in the phantom frame, m.

        Args:
            mesh: a ``trimesh.Trimesh``, or the path of an existing STL file (copied
                byte for byte).

        Raises:
            UnitsError: the mesh's extents exceed 1 m (millimetres).
        """
        tmp = self._need_open()
        dst = tmp / "phantom.stl"
        if isinstance(mesh, (str, os.PathLike)):
            shutil.copyfile(mesh, dst)
            return
        ext = np.asarray(mesh.extents, dtype=np.float64)
        if (ext > _MAX_SIZE_M).any():
            raise UnitsError(self.path / "phantom.stl",
                             f"mesh extents {ext.tolist()} look like millimetres: "
                             f"the format uses metres")
        mesh.export(str(dst), file_type="stl")

    def write_kinematics(self, sequence: str, kinematics: Kinematics) -> None:
        """Write ``sequences/<sequence>/kinematics.csv``.

        Columns ``t,x,y,z,qx,qy,qz,qw``, then ``fx,fy,fz`` if ``kinematics.force`` is set,
        then the ``extra`` columns in order; floats written round-trip exact.

        Raises:
            KeyError: unknown sequence.  ValueError: written twice, or a bad extra name.
            TimestampError, ColumnError, UnitsError, SessionFormatError: as the reader.
        """
        tmp = self._need_open()
        self._need_sequence(sequence)
        if not isinstance(kinematics, Kinematics):
            raise TypeError(f"kinematics must be Kinematics, got {type(kinematics).__name__}")
        if sequence in self._kinematics:
            raise ValueError(f"kinematics of sequence {sequence!r} already written")
        target = self.path / "sequences" / sequence / "kinematics.csv"
        _validate_kinematics(target, kinematics)
        header = list(_KIN_REQUIRED)
        cols = [kinematics.t[:, None], kinematics.position, kinematics.quaternion]
        if kinematics.force is not None:
            header += list(_KIN_FORCE)
            cols.append(kinematics.force)
        for name, col in kinematics.extra.items():
            if name in header or not _valid_column_name(name):
                raise ValueError(f"extra kinematics column name {name!r} is reserved or invalid")
            header.append(name)
            cols.append(col[:, None])
        _write_table(tmp / "sequences" / sequence / "kinematics.csv", header,
                     np.concatenate(cols, axis=1))
        self._kinematics.add(sequence)

    def write_frame(self, sequence: str, frame: int, t: float,
                    points_camera: np.ndarray) -> None:
        """Write one depth frame as ``sequences/<sequence>/clouds/{frame:06d}.ply`` and
        remember its ``frames.csv`` row (written by :meth:`finish`).

        Args:
            sequence: a sequence of the metadata.
            frame: frame number, >= 0, unique in the sequence.
            t: time, s; greater than the previous frame's of this sequence.
            points_camera: (N, 3) camera-frame points, m (float32 on disk).

        Raises:
            KeyError: unknown sequence.  ValueError: bad ``frame`` or points.
            TimestampError: ``t`` not finite or not after the previous frame.
            ColumnError: repeated frame number.  UnitsError: cloud in millimetres.
        """
        tmp = self._need_open()
        self._need_sequence(sequence)
        frame = operator.index(frame)
        if frame < 0:
            raise ValueError(f"frame number must be >= 0, got {frame}")
        frames_csv = self.path / "sequences" / sequence / "frames.csv"
        t = float(t)
        rows = self._rows[sequence]
        if not math.isfinite(t):
            raise TimestampError(frames_csv, f"column 't' is not finite at frame {frame}: {t}")
        if rows and not t > rows[-1][1]:
            raise TimestampError(
                frames_csv,
                f"column 't' is not strictly increasing at frame {frame} "
                f"({t!r} after {rows[-1][1]!r})",
            )
        if frame in self._frame_numbers[sequence]:
            raise ColumnError(frames_csv, f"column 'frame' repeats frame number {frame}")
        pts = _check_points_arg(points_camera)
        rel = f"clouds/{frame:06d}.ply"
        _check_cloud_metres(self.path / "sequences" / sequence / rel, pts)
        write_ply(tmp / "sequences" / sequence / rel, pts, binary=self.ply_binary)
        rows.append((frame, t, rel))
        self._frame_numbers[sequence].add(frame)

    def write_truth(self, truth: dict) -> None:
        """Write ``truth.json`` (synthetic generators only; numpy arrays become lists)."""
        tmp = self._need_open()
        if not isinstance(truth, dict):
            raise TypeError(f"truth must be a dict, got {type(truth).__name__}")
        text = json.dumps(truth, indent=1, default=_json_default)
        (tmp / "truth.json").write_text(text + "\n", encoding="utf-8")

    # -- end -----------------------------------------------------------------------------

    def finish(self) -> Path:
        """Write ``session.json`` and every ``frames.csv`` and move the session into place.

        With ``overwrite``, an existing session is renamed aside, the new one renamed in,
        and the old one deleted (restored if the second rename fails).

        Returns:
            the session folder.

        Raises:
            MissingFileError: corners or a sequence's kinematics were never written.
            SessionFormatError: a sequence has no frame.
            SessionExistsError: the target appeared meanwhile and ``overwrite`` is false.
            The writer stays open after these, so the caller may complete it or
            :meth:`abort`.
        """
        tmp = self._need_open()
        if not self._corners:
            raise MissingFileError(self.path / "calibration" / "corners.csv",
                                   "never written: call write_corners() before finish()")
        for s in self.meta.sequences:
            seq = self.path / "sequences" / s.name
            if s.name not in self._kinematics:
                raise MissingFileError(seq / "kinematics.csv",
                                       "never written: call write_kinematics() before finish()")
            if not self._rows[s.name]:
                raise SessionFormatError(seq / "frames.csv",
                                         "no frames written: call write_frame() before finish()")
        for name, rows in self._rows.items():
            with open(tmp / "sequences" / name / "frames.csv", "w", encoding="utf-8",
                      newline="\n") as f:
                f.write("frame,t,file\n")
                f.writelines(f"{frame},{_fmt(t)},{rel}\n" for frame, t, rel in rows)
        text = json.dumps(self.meta.to_json(), indent=2, default=_json_default)
        (tmp / "session.json").write_text(text + "\n", encoding="utf-8")

        self._check_target()
        if self.path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".old",
                                        dir=self.path.parent))
            old.rmdir()
            os.replace(self.path, old)
            try:
                os.replace(tmp, self.path)
            except BaseException:
                os.replace(old, self.path)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, self.path)
        self._tmp = None
        self._state = "finished"
        return self.path

    def abort(self) -> None:
        """Remove the temporary folder; nothing at :attr:`path` is touched. Idempotent."""
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        if self._state == "open":
            self._state = "aborted"

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self.abort()
        elif self._state == "open":
            try:
                self.finish()
            except BaseException:
                self.abort()
                raise
        return False


def write_session(session: Session, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Copy a session through :class:`SessionWriter` (re-validating everything).

    Clouds are re-encoded as binary float32 PLY named ``clouds/{frame:06d}.ply``
    (non-finite points dropped); ``phantom.stl`` and ``truth.json`` are copied byte for
    byte; unknown ``session.json`` keys and kinematics columns are kept. ``path`` may be
    ``session.path`` itself with ``overwrite=True``.

    Returns:
        the written session folder.

    Raises:
        SessionExistsError: ``path`` exists and ``overwrite`` is false.
        The reader's errors for any invalid cloud.
    """
    with SessionWriter(path, session.meta, overwrite=overwrite) as w:
        w.write_corners(session.corners)
        ref = session.reference_cloud()
        if ref is not None:
            w.write_reference(ref)
        if session.phantom_stl is not None:
            w.write_phantom_stl(session.phantom_stl)
        for name, seq in session.sequences.items():
            w.write_kinematics(name, seq.kinematics)
            for frame, t, points in seq.clouds():
                w.write_frame(name, frame, t, points)
        truth = session.path / "truth.json"
        if truth.is_file():
            shutil.copyfile(truth, w._need_open() / "truth.json")
        return w.finish()
