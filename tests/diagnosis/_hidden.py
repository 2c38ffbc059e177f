"""Shared by the diagnosis tests: generate a session, diagnose it, and check what the
diagnosis writes against SESSION_FORMAT.md's contract."""

from core.diagnosis import ANSWERS
from core.lab import generate_session
from core.simulation.effects import EFFECT_KINDS
from tests._presets import SHORT_SMALL

LAB = SHORT_SMALL
"""The sessions of the end-to-end tests: the `small` preset with 6 s sequences, without force."""


def lab_session(tmp_path_factory, name: str, seed: int, effects: list[dict], **kwargs):
    """Generate a :data:`LAB` session hiding ``effects`` and return its path (``kwargs``
    go to :func:`core.lab.generate_session`)."""
    kwargs.setdefault("preset", LAB)
    return generate_session(tmp_path_factory.mktemp("diag") / name, seed=seed, effects=effects, **kwargs)


def check_contract(data: dict, session) -> None:
    """Assert that ``data`` (a diagnosis.json) has the fields of SESSION_FORMAT.md's
    contract: E with its interval, baseline, causes, extended, unexplained, and a
    detectability statement and an answer for every effect kind."""
    assert data["format"] == "tissue-diagnosis/1" and data["session"] == str(session)
    assert set(data["youngs_modulus"]) >= {"value", "interval", "identifiable"}
    assert data["baseline"]["test_error"] > 0
    for c in data["causes"]:
        assert set(c) >= {"kind", "parameters", "test_error", "gain", "confidence"}
        assert 0.0 <= c["confidence"] <= 1.0
    assert set(data["extended"]) >= {"kinds", "test_error", "gain"}
    assert set(data["unexplained"]) >= {"test_error", "noise_floor"}
    assert set(data["detectability"]) == set(EFFECT_KINDS)
    for kind, d in data["detectability"].items():
        assert set(d) >= {"min_size", "parameters", "why"} and d["why"], kind
        assert d["min_size"] is None or d["min_size"] > 0, (kind, d)
    assert isinstance(data["confounded"], list)
    confounded = {k for g in data["confounded"] for k in (g["kinds"] if isinstance(g, dict) else g)}
    assert not confounded & {c["kind"] for c in data["causes"]}
    assert set(data["answers"]) == set(EFFECT_KINDS) and set(data["answers"].values()) <= set(ANSWERS)
    for c in data["causes"]:
        assert data["answers"][c["kind"]] == "found"
