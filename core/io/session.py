"""Recorded sessions (``tissue-session/1``): typed metadata, a validating reader and a
streaming writer.

The on-disk layout is defined in ``SESSION_FORMAT.md``::

    <session>/session.json
    <session>/phantom.stl                     optional
    <session>/calibration/corners.csv         required unless landmarks.csv is present
    <session>/calibration/landmarks.csv       optional (named landmarks of session.json)
    <session>/calibration/reference.ply       optional
    <session>/sequences/<name>/kinematics.csv
    <session>/sequences/<name>/frames.csv
    <session>/sequences/<name>/clouds/<frame>.ply
    <session>/truth.json                      optional, synthetic only; never read here
                                              except by :func:`read_truth` (tests, scorers)

Frames used below: *robot* (robot base frame: kinematics, touches, forces), *camera*
(depth-camera frame: every cloud) and *phantom* (box spans ``[0, size]``, z up, bottom
face at z = 0). All quantities SI (m, s, kg, N); quaternions ``x, y, z, w``.

:func:`read_session` validates ``session.json`` and every CSV eagerly and checks that
every cloud file exists; clouds are parsed lazily by :meth:`Sequence.cloud` (or all at
once with ``check_clouds=True``). :class:`SessionWriter` streams a session to disk one
cloud at a time (paper scale: 12 sequences x 1800 frames x 45k points) into a
temporary sibling folder and moves it into place only in :meth:`SessionWriter.finish`.

This module gathers the public names of the modules that implement it:

* :mod:`core.io.checks` -- constants of the format, unit and value checks;
* :mod:`core.io.meta` -- ``session.json`` (:class:`SessionMeta` and its specs);
* :mod:`core.io.records` -- kinematics, frame tables and calibration touches;
* :mod:`core.io.tables` -- parsing the CSV files;
* :mod:`core.io.reader` -- :func:`read_session`, :class:`Session`, :class:`Sequence`;
* :mod:`core.io.writer` -- :class:`SessionWriter`, :func:`write_session`.
"""

from __future__ import annotations

from core.io.checks import CORNER_LABELS, FORMAT, ROLES
from core.io.meta import CameraSpec, Landmarks, PhantomSpec, ProbeSpec, SequenceSpec, SessionMeta
from core.io.reader import (
    PICKED_FILE,
    Sequence,
    Session,
    read_cloud,
    read_picked,
    read_session,
    read_truth,
)
from core.io.records import Corners, Frames, Kinematics, LandmarkTouches
from core.io.writer import SessionExistsError, SessionWriter, write_session

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
    "Landmarks",
    "Kinematics",
    "Frames",
    "Corners",
    "LandmarkTouches",
    "Sequence",
    "Session",
    "SessionExistsError",
    "read_session",
    "read_truth",
    "SessionWriter",
    "write_session",
    "PICKED_FILE",
    "read_picked",
]
