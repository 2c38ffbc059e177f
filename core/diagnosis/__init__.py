"""Discovery: what the replay gets wrong, which effect explains it, and what the fix is worth.

``diagnose(session)`` prepares a session (calibration, cleaning), runs the method of
:mod:`core.diagnosis.engine` and returns a :class:`Diagnosis`; ``write_diagnosis``
writes ``diagnosis.json`` (the SESSION_FORMAT.md contract) and ``report.md`` with figures.
"""

from __future__ import annotations

from pathlib import Path

from core.diagnosis.candidates import KINDS, Candidate, candidates
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.engine import diagnose_prepared
from core.diagnosis.results import ANSWERS, CauseReport, Detectability, Diagnosis
from core.diagnosis.fields import PHASES, FieldLayout, phase_labels
from core.diagnosis.report import write_diagnosis

__all__ = [
    "ANSWERS",
    "Detectability",
    "KINDS",
    "PHASES",
    "Candidate",
    "CauseReport",
    "Diagnosis",
    "DiagnosisConfig",
    "FieldLayout",
    "candidates",
    "diagnose",
    "diagnose_prepared",
    "phase_labels",
    "write_diagnosis",
]


def diagnose(session: str | Path, config: DiagnosisConfig | None = None, *, executor=None, callback=None) -> Diagnosis:
    """Calibrate, clean and diagnose the session folder ``session``.

    Args:
        session: a session folder (SESSION_FORMAT.md).
        config: settings (see :class:`DiagnosisConfig`).
        executor: where the replays run (``core.identification.executor()`` for Dask).
        callback: ``callback(fraction, message)``; preparation takes the first 10 %.

    Raises:
        SessionFormatError, RegistrationError, CleaningError: bad input.
        TissueTwinError: a session without train, validation or test sequences.
    """
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    config = config or DiagnosisConfig()
    say = callback or (lambda f, m: None)
    prepared = prepare_session(session, ReplayConfig(grid=config.grid), callback=lambda f, m: say(0.1 * f, m))
    return diagnose_prepared(prepared, config, executor=executor, callback=lambda f, m: say(0.1 + 0.9 * f, m))
