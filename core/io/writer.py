"""Writing a session: :class:`SessionWriter` streams a session to disk one cloud at a
time (paper scale: 12 sequences x 1800 frames x 45k points) into a temporary sibling
folder and moves it into place only in :meth:`SessionWriter.finish`;
:func:`write_session` copies a read session through it.
"""

from __future__ import annotations

import json
import math
import operator
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import (
    ColumnError,
    MissingFileError,
    SessionFormatError,
    TimestampError,
    TissueTwinError,
    UnitsError,
)
from core.io.checks import KIN_FORCE, KIN_REQUIRED, MAX_SIZE_M, check_cloud_metres
from core.io.meta import SessionMeta, parse_meta
from core.io.ply import write_ply
from core.io.reader import Session
from core.io.records import (
    Corners,
    Kinematics,
    LandmarkTouches,
    validate_corners,
    validate_kinematics,
    validate_landmark_touches,
)

__all__ = ["SessionExistsError", "SessionWriter", "write_session"]


class SessionExistsError(TissueTwinError, FileExistsError):
    """:class:`SessionWriter` refuses to replace an existing path.

    Raised when the target exists and ``overwrite`` is false, or when ``overwrite``
    is true but the target is not a folder that looks like a session (holds a
    ``session.json``) or an empty folder: the writer never deletes anything else.
    """



def _check_points_arg(points: Any) -> np.ndarray:
    """Writer argument check: (N, 3) finite, N >= 1 (ValueError otherwise)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ValueError(f"points must be (N, 3) with N >= 1, got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("points must be finite")
    return pts



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


def _write_labelled_xyz(path: Path, label_column: str, labels: tuple[str, ...],
                        positions: np.ndarray) -> None:
    """Write a ``<label_column>,x,y,z`` table with round-trip-exact floats."""
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(f"{label_column},x,y,z\n")
        for label, p in zip(labels, positions.tolist()):
            f.write(f"{label},{_fmt(p[0])},{_fmt(p[1])},{_fmt(p[2])}\n")


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
    :meth:`write_corners` or :meth:`write_landmark_touches` (landmarks named in
    ``meta.landmarks``; corners are then optional), and for every sequence of ``meta``
    :meth:`write_kinematics` and at least one :meth:`write_frame`.

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
        parse_meta(self.path / "session.json", meta.to_json())
        self._check_target()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp: Path | None = Path(
            tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent)
        )
        self._state = "open"
        self._corners = False
        self._landmark_touches = False
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
        validate_corners(self.path / "calibration" / "corners.csv", corners)
        _write_labelled_xyz(tmp / "calibration" / "corners.csv", "corner", corners.labels,
                            corners.positions)
        self._corners = True

    def write_landmark_touches(self, touches: LandmarkTouches) -> None:
        """Write ``calibration/landmarks.csv`` (``landmark,x,y,z``): robot-frame sphere
        centres, m, touching the landmarks of ``meta.landmarks`` (written to
        ``session.json`` by :meth:`finish`). With it, :meth:`write_corners` is optional.

        Raises:
            TypeError: not a :class:`LandmarkTouches`.
            SessionFormatError: a label that is not in ``meta.landmarks``, fewer than 3
                distinct or collinear landmarks.
            ColumnError: non-finite positions.  UnitsError: a position > 5 m away.
        """
        tmp = self._need_open()
        if not isinstance(touches, LandmarkTouches):
            raise TypeError(f"touches must be LandmarkTouches, got {type(touches).__name__}")
        target = self.path / "calibration" / "landmarks.csv"
        validate_landmark_touches(target, touches, self.meta.landmarks)
        _write_labelled_xyz(tmp / "calibration" / "landmarks.csv", "landmark", touches.labels,
                            touches.positions)
        self._landmark_touches = True

    def write_reference(self, points_camera: np.ndarray) -> None:
        """Write ``calibration/reference.ply``: (N, 3) camera-frame points, m, of the
        phantom at rest (float32 on disk).

        Raises:
            ValueError: not a finite (N, 3) array with N >= 1.
            UnitsError: median distance from the camera > 5 m.
        """
        tmp = self._need_open()
        pts = _check_points_arg(points_camera)
        check_cloud_metres(self.path / "calibration" / "reference.ply", pts)
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
        if (ext > MAX_SIZE_M).any():
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
        validate_kinematics(target, kinematics)
        header = list(KIN_REQUIRED)
        cols = [kinematics.t[:, None], kinematics.position, kinematics.quaternion]
        if kinematics.force is not None:
            header += list(KIN_FORCE)
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
        check_cloud_metres(self.path / "sequences" / sequence / rel, pts)
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
            MissingFileError: neither corners nor landmark touches, or a sequence's
                kinematics were never written.
            SessionFormatError: a sequence has no frame.
            SessionExistsError: the target appeared meanwhile and ``overwrite`` is false.
            The writer stays open after these, so the caller may complete it or
            :meth:`abort`.
        """
        tmp = self._need_open()
        if not (self._corners or self._landmark_touches):
            raise MissingFileError(self.path / "calibration" / "corners.csv",
                                   "never written: call write_corners() (or "
                                   "write_landmark_touches()) before finish()")
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


def write_session(session: Session, path: str | os.PathLike, *, overwrite: bool = False,
                  landmark_touches: LandmarkTouches | None = None) -> Path:
    """Copy a session through :class:`SessionWriter` (re-validating everything).

    Clouds are re-encoded as binary float32 PLY named ``clouds/{frame:06d}.ply``
    (non-finite points dropped); ``phantom.stl`` and ``truth.json`` are copied byte for
    byte; unknown ``session.json`` keys (and its ``landmarks``), kinematics columns,
    corner touches and landmark touches are kept. ``path`` may be ``session.path``
    itself with ``overwrite=True``.

    Args:
        session: a read session.
        path: the session folder to write.
        overwrite: replace an existing session folder.
        landmark_touches: touches (robot frame, m) to write as
            ``calibration/landmarks.csv`` instead of ``session.landmark_touches``; their
            labels must be landmarks of ``session.meta.landmarks``.

    Returns:
        the written session folder.

    Raises:
        SessionExistsError: ``path`` exists and ``overwrite`` is false.
        SessionFormatError: ``landmark_touches`` that :meth:`SessionWriter.write_landmark_touches`
            refuses.
        The reader's errors for any invalid cloud.
    """
    if landmark_touches is None:
        landmark_touches = session.landmark_touches
    with SessionWriter(path, session.meta, overwrite=overwrite) as w:
        if session.corners is not None:
            w.write_corners(session.corners)
        if landmark_touches is not None:
            w.write_landmark_touches(landmark_touches)
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
