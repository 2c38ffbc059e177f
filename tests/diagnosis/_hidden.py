"""Shared by the diagnosis tests: generate a session with hidden effects, diagnose it, and
check what the diagnosis names and writes."""

from core.diagnosis import DiagnosisConfig, diagnose
from core.lab import generate_session, scenario
from tests._presets import SHORT_DURATION as DURATION, SHORT_SMALL


def diagnose_hidden(tmp_path, kind: str, seed: int, rivals: tuple[str, ...], fine_refit_iterations: int = 1):
    """Generate ``kind``'s scenario (:func:`core.lab.scenario`, 4 x 6 s, force columns) at
    ``seed`` and diagnose it with ``kind`` and its ``rivals`` as the candidates.

    The full candidate set on every kind runs in benchmarks/bench_diagnosis.py (the
    confusion matrix); here each kind meets the rival that mimicked it most when all
    eight were fitted, to keep the suite's time (one 25 x 9 x 9 refit iteration, two
    selection rounds). Returns (diagnosis, hidden effect dict)."""
    lab, effects = scenario(kind, seed, DURATION)
    session = generate_session(tmp_path / f"{kind}-{seed}", preset=lab, seed=seed, effects=effects, with_force=True)
    d = diagnose(session, DiagnosisConfig(fit_youngs=False, n_boot=100, kinds=(kind, *rivals), max_causes=2,
                                          fine_refit_iterations=fine_refit_iterations))
    print({c.kind: (c.parameters, c.score, c.delta_chi2_field, c.delta_chi2_force) for c in d.candidates})
    print([(c.kind, c.parameters, c.gain, c.force_gain) for c in d.causes], d.force, d.timings)
    return d, effects[0]


def named(d, kind: str):
    """Assert that ``kind`` is the one cause claimed (nothing confounded) and return it."""
    assert [c.kind for c in d.causes] == [kind], [(c.kind, c.score) for c in d.candidates]
    assert d.confounded == []
    return d.causes[0]


LAB = SHORT_SMALL
"""The sessions of the end-to-end tests: the `small` preset with 6 s sequences, without force."""


def lab_session(tmp_path_factory, name: str, seed: int, effects: list[dict]):
    """Generate a :data:`LAB` session hiding ``effects`` (no force columns) and return its path."""
    return generate_session(tmp_path_factory.mktemp("diag") / name, preset=LAB, seed=seed, effects=effects)


def check_contract(data: dict, session) -> None:
    """Assert that ``data`` (a diagnosis.json) has the fields of SESSION_FORMAT.md's contract."""
    assert data["format"] == "tissue-diagnosis/1" and data["session"] == str(session)
    assert set(data["youngs_modulus"]) >= {"value", "interval", "identifiable"}
    assert data["baseline"]["test_error"] > 0
    for c in data["causes"]:
        assert set(c) >= {"kind", "parameters", "test_error", "gain", "confidence"}
        assert 0.0 <= c["confidence"] <= 1.0
    assert set(data["extended"]) >= {"kinds", "test_error", "gain"}
    assert set(data["unexplained"]) >= {"test_error", "noise_floor"}
