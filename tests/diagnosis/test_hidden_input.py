"""Hide an error of the probe input (clock, robot calibration, probe radius) in a
generated session with force data and require the diagnosis to name exactly it, recover
its parameters and gain on the test sequence (see test_hidden_physical.py)."""

import numpy as np
import pytest

from tests.diagnosis._hidden import diagnose_hidden, named as _named

pytestmark = pytest.mark.slow  # whole diagnoses, 1-3 min each


def test_time_offset_is_named_with_its_offset(tmp_path):
    """Within 0.05 s of 0.15 s: the camera sees the offset only while the probe moves
    (15 Hz frames, 67 ms apart). The force, on the robot's clock like the kinematics,
    carries no trace of it. Seed 1: measured 0.119 s, surface gain 0.2 %."""
    d, truth = diagnose_hidden(tmp_path, "time_offset", 1, ("viscoelasticity",))
    c = _named(d, "time_offset")
    assert c.parameters["offset"] == pytest.approx(0.15, abs=0.05)
    assert d.extended_gain > 0


def test_kinematic_offset_is_named_with_its_offset(tmp_path):
    """Each axis within 0.6 mm of (1.5, -1, -1.5) mm: the depth shows in the force and the
    dent, the lateral part only in where the dent is (bins of 4.3 x 4.9 mm)."""
    d, truth = diagnose_hidden(tmp_path, "kinematic_offset", 0, ("base_compliance",))
    c = _named(d, "kinematic_offset")
    assert np.abs(np.array(c.parameters["offset"]) - truth["offset"]).max() < 6e-4
    assert d.force["gain"] > 0


def test_probe_radius_is_named_from_side_and_top_pokes(tmp_path):
    """A 7.5 mm probe recorded as 5 mm, seed 2. The corner-touch calibration used the same
    sphere, so top pokes reach the right depth and only their force grows (what a stiffer
    gel gives); a side poke goes 2.5 mm deeper than the replay's, which E cannot mimic,
    and the top pokes in the same sequences rule out a lateral robot offset. Radius within
    0.5 mm, a fifth of the error (measured 7.72 mm: the side dent is resolved by 6 x 10 mm
    elements on the coarse grid and 3 x 5 mm on the fine one), and a third of the force
    error removed (measured 45 %)."""
    d, truth = diagnose_hidden(tmp_path, "probe_radius", 2, ("kinematic_offset",))
    c = _named(d, "probe_radius")
    assert c.parameters["radius"] == pytest.approx(truth["radius"], abs=5e-4)
    assert d.force["gain"] > 0.3
