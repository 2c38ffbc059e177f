"""Session I/O: read, validate and write recorded sessions (``tissue-session/1``).

The format is defined in ``SESSION_FORMAT.md``. Start with :func:`read_session`
(validating reader) and :class:`SessionWriter` (streaming writer).
"""

from core.io.ply import check_ply, read_ply, write_ply
from core.io.session import (
    CORNER_LABELS,
    FORMAT,
    ROLES,
    CameraSpec,
    Corners,
    Frames,
    Kinematics,
    Landmarks,
    LandmarkTouches,
    PhantomSpec,
    ProbeSpec,
    Sequence,
    SequenceSpec,
    Session,
    SessionExistsError,
    SessionMeta,
    SessionWriter,
    read_cloud,
    read_session,
    read_picked,
    read_truth,
    write_session,
)

__all__ = [
    "CORNER_LABELS",
    "FORMAT",
    "ROLES",
    "CameraSpec",
    "Corners",
    "Frames",
    "Kinematics",
    "Landmarks",
    "LandmarkTouches",
    "PhantomSpec",
    "ProbeSpec",
    "Sequence",
    "SequenceSpec",
    "Session",
    "SessionExistsError",
    "SessionMeta",
    "SessionWriter",
    "check_ply",
    "read_cloud",
    "read_picked",
    "read_ply",
    "read_session",
    "read_truth",
    "write_ply",
    "write_session",
]
