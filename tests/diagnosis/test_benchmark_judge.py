"""The diagnosis benchmark's judge of a hidden inclusion (``benchmarks.bench_diagnosis.
applicable_min_size``): a statement covers a hidden sphere only at its own placement (or 10 mm
beside the best one) and only when the hidden sphere is no smaller than the stated one."""

from __future__ import annotations

import pytest

from benchmarks.bench_diagnosis import applicable_min_size
from core.diagnosis.results import Detectability

PLACES = [{"center": [0.030, 0.020, 0.024], "radius": 0.010, "min_size": 3.0},
          {"center": [0.050, 0.020, 0.024], "radius": 0.010, "min_size": 5.0}]
DET = Detectability("inclusion", 3.0, {"center": PLACES[0]["center"], "radius": 0.010, "placements": PLACES,
                                       "beside": {"distance": 0.010, "min_size": 9.0}}, "not found", "not_found")


@pytest.mark.parametrize("hidden, expected", [
    ({"center": [0.031, 0.021, 0.024], "radius": 0.010}, (3.0, True, "its placement")),    # at the best placement
    ({"center": [0.050, 0.022, 0.025], "radius": 0.012}, (5.0, True, "its placement")),    # at the other, larger sphere
    ({"center": [0.030, 0.030, 0.024], "radius": 0.010}, (9.0, True, "10 mm beside the best placement")),    # 10 mm beside the best
    ({"center": [0.040, 0.035, 0.024], "radius": 0.010}, (None, False, "")),  # between, no statement
    ({"center": [0.030, 0.020, 0.024], "radius": 0.009}, (None, False, "")),  # a smaller sphere shows less
])
def test_a_hidden_inclusion_is_judged_by_the_statement_that_covers_it(hidden, expected):
    assert applicable_min_size(DET, hidden) == expected


def test_other_kinds_are_judged_by_their_min_size():
    det = Detectability("gravity", 2.5, {"direction": [0.0, 0.0, -1.0]}, "not found", "not_found")
    assert applicable_min_size(det, {"kind": "gravity", "vector": [0.0, 0.0, -9.81]}) == (2.5, True, "")
