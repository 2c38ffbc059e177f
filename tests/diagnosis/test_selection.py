"""The round's choice (core.diagnosis.selection.choose): the largest passing drop is
claimed unless a larger unconfirmed explanation or an equal rival takes the residual."""

import numpy as np
import pytest

from core.diagnosis.selection import choose

CHANGES = {"gravity": np.array([1.0, 2.0, 0.0]), "base_compliance": np.array([0.5, 1.0, 0.6]),
           "probe_radius": np.array([1.0, 2.1, 0.05]), "friction": np.array([0.0, 0.0, 1.0])}


def _adds(table):
    """``adds`` from a table {(kind, given): bool}; records what was asked."""
    asked = []

    def adds(kind, given):
        asked.append((kind, given))
        return table[(kind, given)]

    return adds, asked


def test_the_largest_passing_drop_is_claimed_when_nothing_shadows_or_rivals_it():
    adds, asked = _adds({})
    T = {"gravity": 900.0, "friction": 800.0, "base_compliance": 100.0}
    assert choose(["base_compliance", "friction", "gravity"], [], T, CHANGES.__getitem__, adds) == ("gravity", [])
    assert asked == []  # friction explains 0.89 of it but changes other data: no nested test


@pytest.mark.parametrize("adds_on_top, expected", [(False, (None, ["base_compliance", "gravity"])),
                                                   (True, ("base_compliance", []))])
def test_a_larger_unconfirmed_explanation_shadows_the_best(adds_on_top, expected):
    """The measured case: gravity explained 7560 but could not be claimed (its fitted
    change below the critical value), a compliant base passed at 3004."""
    adds, asked = _adds({("base_compliance", "gravity"): adds_on_top})
    T = {"gravity": 7560.0, "base_compliance": 3004.0, "probe_radius": 284.0}
    got = choose(["base_compliance"], ["gravity", "probe_radius"], T, CHANGES.__getitem__, adds)
    assert got == expected
    assert asked == [("base_compliance", "gravity")]  # the smaller unconfirmed kind is not asked


def test_a_rival_with_the_same_change_is_confounded_or_replaces_the_best():
    T = {"gravity": 1000.0, "probe_radius": 950.0}
    for table, expected in (({("gravity", "probe_radius"): False, ("probe_radius", "gravity"): False},
                             (None, ["gravity", "probe_radius"])),
                            ({("gravity", "probe_radius"): False, ("probe_radius", "gravity"): True},
                             ("probe_radius", [])),
                            ({("gravity", "probe_radius"): True, ("probe_radius", "gravity"): False},
                             ("gravity", []))):
        adds, _ = _adds(table)
        assert choose(["gravity", "probe_radius"], [], T, CHANGES.__getitem__, adds) == expected


def test_no_passing_kind_is_an_error():
    with pytest.raises(ValueError, match="no kind passed"):
        choose([], ["gravity"], {"gravity": 1.0}, CHANGES.__getitem__, lambda k, g: False)


def test_a_fit_at_its_bound_is_not_claimed_and_claims_on_top_of_a_withdrawn_one_go_with_it():
    """A fit at the edge of its kind's plausible range is refused before any claim check
    (answer "cannot tell", no simulation asked); a claim made in a round after one that is
    withdrawn was judged against a model holding a cause that does not stand, and is
    withdrawn with it (an earlier one stays)."""
    from types import SimpleNamespace

    from core.diagnosis.candidates import candidates
    from core.diagnosis.detectability import with_dependents
    from core.diagnosis.rounds import beyond_verdict

    cands = candidates((0.0687, 0.0393, 0.0358), 0.005)
    e = SimpleNamespace(fit=SimpleNamespace(x=np.array([0.015, 1e-4])), statistic=900.0)
    verdict, nested = beyond_verdict(None, None, e, cands["probe_radius"])  # rnd and ev are not asked
    assert verdict[0] == "at_bound" and "radius at its upper bound 0.015" in verdict[1] and nested is None

    def claim(kind, rnd):
        return (SimpleNamespace(kind=kind), None, SimpleNamespace(round=rnd))

    claimed = [claim("gravity", 0), claim("base_compliance", 1), claim("probe_radius", 2)]
    out = with_dependents(claimed, {"base_compliance": "below its own detectability"})
    assert set(out) == {"base_compliance", "probe_radius"}
    assert "on top of base compliance" in out["probe_radius"]
    assert with_dependents(claimed, {}) == {}
    assert set(with_dependents(claimed, {"probe_radius": "x"})) == {"probe_radius"}
