"""Reading a recorded session: :func:`read_session` validates ``session.json`` and every
CSV eagerly and checks that every cloud file exists; clouds are parsed lazily by
:meth:`Sequence.cloud`. Also :func:`read_truth` (tests and scorers only) and the
project-private :func:`read_picked`.
"""

from __future__ import annotations

import json
import operator
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.errors import MissingFileError, SessionFormatError, UnitsError
from core.io.checks import MAX_SIZE_M, ROLES, check_cloud_metres, row_msg
from core.io.meta import SessionMeta, read_meta
from core.io.ply import check_ply, read_ply
from core.io.records import Corners, Frames, Kinematics, LandmarkTouches
from core.io.tables import read_corners, read_frames, read_kinematics, read_landmark_touches

__all__ = [
    "read_cloud",
    "Sequence",
    "Session",
    "read_session",
    "read_truth",
    "PICKED_FILE",
    "read_picked",
]


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
    check_cloud_metres(path, points)
    return points



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
        corners: :class:`Corners` from ``calibration/corners.csv`` (robot frame), or
            None when that file is absent, which the format allows only when
            ``calibration/landmarks.csv`` is present.
        sequences: name -> :class:`Sequence`, in ``session.json`` order.
        phantom_stl: ``phantom.stl`` (phantom-frame rest surface, m) or None if absent.
        reference_path: ``calibration/reference.ply`` or None if absent.
        landmark_touches: :class:`LandmarkTouches` from ``calibration/landmarks.csv``
            (robot frame; labels are landmarks of ``meta.landmarks``), or None if absent.
    """

    def __init__(self, path: Path, meta: SessionMeta, corners: Corners | None,
                 sequences: dict[str, Sequence], phantom_stl: Path | None,
                 reference_path: Path | None, landmark_touches: LandmarkTouches | None = None):
        self.path = Path(path)
        self.meta = meta
        self.corners = corners
        self.sequences = sequences
        self.phantom_stl = phantom_stl
        self.reference_path = reference_path
        self.landmark_touches = landmark_touches

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
        check_cloud_metres(self.reference_path, points)
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
        if (ext > MAX_SIZE_M).any():
            raise UnitsError(self.phantom_stl, f"extents {ext.tolist()} look like millimetres: "
                                               f"the format uses metres")
        return mesh


def read_session(path: str | os.PathLike, *, check_clouds: bool = False) -> Session:
    """Read and validate a session folder (``tissue-session/1``).

    ``session.json``, ``calibration/corners.csv`` (optional when
    ``calibration/landmarks.csv`` is present), ``calibration/landmarks.csv`` (optional)
    and every ``kinematics.csv`` and ``frames.csv`` are parsed and validated now, and
    every cloud file listed in a
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
            ``corners.csv`` (without ``landmarks.csv``), sequence folder,
            ``kinematics.csv``, ``frames.csv`` or cloud.
        SessionFormatError: bad ``session.json`` (not JSON, wrong format, missing or
            invalid fields, bad role, duplicate names, bad ``landmarks``), a CSV without
            data rows, a cloud path leaving its sequence folder, fewer than 4 corner
            touches; in ``landmarks.csv`` a label that is not a landmark of
            ``session.json``, fewer than 3 distinct or collinear landmarks.
        ColumnError: missing, partial (force), duplicate or non-numeric CSV columns,
            non-finite positions, quaternions or forces, a zero quaternion, an unknown
            corner label, repeated frame numbers.
        TimestampError: NaN/inf or not strictly increasing ``t``.
        UnitsError: phantom size or probe radius > 1 m, a landmark coordinate beyond
            +-1 m, positions > 5 m from the robot origin (millimetres).
        PlyError: (``check_clouds``) a malformed, truncated or empty cloud.
    """
    root = Path(path)
    if not root.is_dir():
        raise MissingFileError(root, "session folder does not exist")
    meta = read_meta(root / "session.json")
    corners_csv = root / "calibration" / "corners.csv"
    landmarks_csv = root / "calibration" / "landmarks.csv"
    touches = None
    if landmarks_csv.is_file():
        touches = read_landmark_touches(landmarks_csv, meta.landmarks)
    # corners.csv is required unless the landmarks replace it (SESSION_FORMAT.md).
    corners = read_corners(corners_csv) if touches is None or corners_csv.is_file() else None
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
        kin = read_kinematics(seq_dir / "kinematics.csv")
        frames_path = seq_dir / "frames.csv"
        frames = read_frames(frames_path)
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
                    file, f"cloud listed in {frames_path} at {row_msg(r)} does not exist"
                )
        sequences[spec.name] = Sequence(spec.name, spec.role, seq_dir, kin, frames)
    session = Session(root, meta, corners, sequences,
                      phantom_stl=stl if stl.is_file() else None,
                      reference_path=reference if reference.is_file() else None,
                      landmark_touches=touches)
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

