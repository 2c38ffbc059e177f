"""Preparing a session: calibration, cleaned clouds and calibrated probe paths, once.

Between registration and simulation in the data flow: a prepared session
(:class:`PreparedSession`) is what every replay, fit, diagnosis and training reads, and
:func:`prepare_session` computes it once per session content and settings (cached, see
:mod:`core.preparation.prepare`).

Public surface::

    prepared = prepare_session("data/s3")            # calibrate, clean (in parallel), cache
    prepared.sequences["seq00"].clouds[10]           # (M, 3) float32, m, phantom frame
"""

from core.preparation.calibration import Calibration, calibrate, calibrate_robot_on_landmarks
from core.preparation.prepare import cache_root, prepare_session
from core.preparation.prepared import Clouds, PrepareConfig, PreparedSequence, PreparedSession, release_pages
from core.preparation.probe import ProbePath

__all__ = [
    "calibrate_robot_on_landmarks",
    "Calibration",
    "Clouds",
    "PrepareConfig",
    "PreparedSequence",
    "PreparedSession",
    "ProbePath",
    "cache_root",
    "calibrate",
    "prepare_session",
    "release_pages",
]
