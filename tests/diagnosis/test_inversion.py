"""A replay that turns tetrahedra inside out under the probe bounds no kind's size."""

from core.diagnosis.detectability import held_by_inversion
from core.diagnosis.results import ANSWERS, Detectability


def _det():
    return {
        "inclusion": Detectability("inclusion", 2.16, {"radius": 0.01}, "not found: ...", "not_found", "stiffness ratio"),
        "gravity": Detectability("gravity", 4.2, {}, "found; ...", "found", "m/s^2"),
        "friction": Detectability("friction", None, {}, "cannot tell from this data: ...", "cannot_tell", "-"),
        "time_offset": Detectability("time_offset", 0.05, {}, "confounded ...", "confounded", "s"),
    }


def test_not_found_becomes_cannot_tell_with_the_replay_s_size_kept():
    det = _det()
    held = held_by_inversion(det, ["seq02", "seq03"])
    inc = held["inclusion"]
    assert inc.answer == "cannot_tell" and inc.answer in ANSWERS and inc.min_size is None
    assert inc.parameters == {"radius": 0.01, "inverted_replay_min_size": 2.16}
    assert "seq02, seq03" in inc.why and inc.why.startswith("cannot tell") and "2.16 stiffness ratio" in inc.why
    assert inc.to_json()["min_size"] is None
    for kind in ("gravity", "friction", "time_offset"):  # found, cannot tell and confounded stay as they were
        assert held[kind] == det[kind]
    assert det["inclusion"].answer == "not_found"  # the caller's statements are not changed in place


def test_without_inversion_nothing_changes():
    det = _det()
    assert held_by_inversion(det, []) is det
