"""Point-cloud PLY files: read (ASCII or binary) and write (float32 x, y, z).

The session format (``SESSION_FORMAT.md``) stores every depth frame as a PLY file
with float ``x``, ``y``, ``z`` vertex properties; extra properties (colour,
normals, confidence) are allowed and ignored here. Parsing is done by the
``plyfile`` library; this module adds the checks and messages the format asks for.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from core.errors import MissingFileError, PlyError

__all__ = ["read_ply", "write_ply", "check_ply"]

_FLOAT_KINDS = ("f",)  # numpy dtype kinds accepted for x, y, z (float32 / float64)


def _load(path: Path, *, mmap: bool):
    """Parse ``path`` with plyfile; translate every failure into :class:`PlyError`.

    Returns the ``vertex`` :class:`plyfile.PlyElement`, checked to hold at least one
    row and float ``x``, ``y``, ``z`` properties.
    """
    import plyfile  # noqa: PLC0415 (kept local: only needed when clouds are read)

    if not path.is_file():
        raise MissingFileError(path, "point-cloud file does not exist")
    try:
        data = plyfile.PlyData.read(str(path), mmap="c" if mmap else False)
    except plyfile.PlyHeaderParseError as exc:
        raise PlyError(path, f"malformed PLY header ({exc})") from exc
    except plyfile.PlyElementParseError as exc:
        raise PlyError(path, f"malformed or truncated PLY data ({exc})") from exc
    except (ValueError, TypeError, KeyError, IndexError, UnicodeDecodeError, EOFError,
            OSError) as exc:
        raise PlyError(path, f"cannot parse PLY file ({type(exc).__name__}: {exc})") from exc
    if "vertex" not in data:
        names = [e.name for e in data.elements]
        raise PlyError(path, f"no 'vertex' element (elements: {names})")
    vertex = data["vertex"]
    dtype = vertex.data.dtype
    missing = [c for c in "xyz" if dtype.names is None or c not in dtype.names]
    if missing:
        have = list(dtype.names or ())
        raise PlyError(path, f"vertex element lacks float x, y, z (missing {missing}, has {have})")
    for c in "xyz":
        if dtype[c].kind not in _FLOAT_KINDS or dtype[c].shape != ():
            raise PlyError(
                path, f"vertex property '{c}' must be float or double, got {dtype[c]}"
            )
    if vertex.count == 0:
        raise PlyError(path, "empty point cloud (0 vertices)")
    return vertex


def read_ply(path: str | os.PathLike) -> np.ndarray:
    """Read the vertex positions of a PLY point cloud.

    Args:
        path: PLY file, ASCII or binary (little- or big-endian), with float or double
            ``x``, ``y``, ``z`` vertex properties. Other properties and elements
            (faces, colours, normals) are ignored.

    Returns:
        ``points``: (N, 3) float64, in whatever frame and unit the file holds (session
        clouds are camera frame, metres). Points with a NaN or infinite coordinate
        (invalid depth pixels) are dropped; N >= 1.

    Raises:
        MissingFileError: the file does not exist.
        PlyError: malformed or truncated file, no float x, y, z, 0 vertices, or no
            finite point at all.
    """
    path = Path(path)
    vertex = _load(path, mmap=True)
    data = vertex.data
    points = np.empty((vertex.count, 3), dtype=np.float64)
    for j, c in enumerate("xyz"):
        points[:, j] = data[c]
    del data, vertex  # release the memory map before returning
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        if not finite.any():
            raise PlyError(path, f"no finite point among {len(points)} vertices")
        points = points[finite]
    return points


def check_ply(path: str | os.PathLike) -> int:
    """Check a PLY cloud's header and size without converting its points.

    Binary files are memory-mapped, so only the header is parsed and the file size
    compared with what the header promises; ASCII files are parsed in full.

    Returns:
        the number of vertices (>= 1).

    Raises:
        MissingFileError: the file does not exist.
        PlyError: as :func:`read_ply` (except the all-non-finite check).
    """
    return int(_load(Path(path), mmap=True).count)


def write_ply(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True) -> None:
    """Write a point cloud as a PLY file with float32 ``x``, ``y``, ``z`` vertices.

    Args:
        path: destination file (overwritten if present; parent folder must exist).
        points: (N, 3) array, any float dtype, N >= 1, all finite; stored as float32
            (about 7 significant digits: 0.1 um at 1 m).
        binary: binary little-endian (default, compact and fast) or ASCII (``%.9g``,
            which round-trips float32 exactly).

    Raises:
        ValueError: ``points`` is not a non-empty, finite (N, 3) array.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    if pts.shape[0] == 0:
        raise ValueError("points must hold at least one point, got (0, 3)")
    pts = pts.astype("<f4", copy=False)
    if not np.isfinite(pts).all():
        bad = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
        raise ValueError(f"points must be finite (in float32), row {bad} is {pts[bad]}")
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment written by tissuetwin core.io\n"
        f"element vertex {pts.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    ).encode("ascii")
    with open(path, "wb") as f:
        f.write(header)
        if binary:
            f.write(np.ascontiguousarray(pts).tobytes())
        else:
            np.savetxt(f, pts, fmt="%.9g", delimiter=" ")
