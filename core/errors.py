"""Exception hierarchy of Tissue Twin.

Every error a user can cause derives from :class:`TissueTwinError`, so the CLI and
the job service can catch one type and show its message. Messages say what was
expected and what came, and name the file when there is one.
"""

from __future__ import annotations

from pathlib import Path


class TissueTwinError(Exception):
    """Base class of all domain errors (bad input, failed registration, ...)."""


class SessionFormatError(TissueTwinError):
    """A session folder does not follow ``SESSION_FORMAT.md``.

    Attributes:
        path: the offending file (or folder), as given.
        problem: one sentence saying what is wrong.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class MissingFileError(SessionFormatError):
    """A file the format requires is absent."""


class PlyError(SessionFormatError):
    """A PLY file is malformed, truncated, empty or lacks float x, y, z."""


class TimestampError(SessionFormatError):
    """Timestamps are NaN, infinite, or not strictly increasing."""


class ColumnError(SessionFormatError):
    """A CSV file has missing, unexpected or non-numeric columns."""


class UnitsError(SessionFormatError):
    """Coordinates look like millimetres where the format requires metres."""


class RegistrationError(TissueTwinError):
    """A registration (Kabsch, ICP) does not fit: too few inliers or too large a residual.

    Attributes:
        fitness: fraction of source points with a correspondence (ICP), or None.
        rms: root-mean-square residual in metres, or None.
    """

    def __init__(self, message: str, *, fitness: float | None = None, rms: float | None = None):
        self.fitness = fitness
        self.rms = rms
        super().__init__(message)


class CleaningError(TissueTwinError):
    """A point cloud cannot be cleaned (no table plane, nothing left of the phantom)."""


class SimulationError(TissueTwinError):
    """A simulation cannot be set up (bad mesh, bad parameters).

    A run that diverges is *not* an exception: it is reported in the result's status.
    """


class MeshingError(SessionFormatError):
    """A phantom surface (``phantom.stl``) cannot be filled with tetrahedra: not
    watertight, inconsistently oriented, self-intersecting, in millimetres, not resting
    on z = 0, or refused by the mesher. ``path`` names the STL."""
