"""Hide a physical effect of the material or the load (gravity, an inclusion, viscoelasticity)
in a generated session with force data and require the diagnosis to name exactly it,
recover its parameters and gain on the test sequence.

Each kind meets the rival that came closest to it when all eight kinds were fitted
(see ``_hidden.diagnose_hidden``); the benchmark runs every kind against all eight. Tolerances are stated per kind with the
measured value and why it is as loose as it is.
"""

import numpy as np
import pytest

from tests.diagnosis._hidden import diagnose_hidden, named as _named

pytestmark = pytest.mark.slow  # whole diagnoses, 1-3 min each


def test_gravity_is_named_with_its_sag(tmp_path):
    """The sag pins g / E and the force pins E. g / E within 5 % of the truth's
    9.81 / 5000 (measured 0.2 % off). g itself comes out 29 % high (-12.6 m/s^2): the
    truth is stable neo-Hookean, and the paper's corotational law needs a 29 % higher E
    to match its probe force but only ~6 % higher to match its sag (the README's E fit
    note), so with E pinned by the force, g absorbs the difference of the laws. A
    model-form gap, reported, not hidden: g is required within 35 %."""
    d, truth = diagnose_hidden(tmp_path, "gravity", 0, ("base_compliance",))
    c = _named(d, "gravity")
    g = -c.parameters["g"][2]
    assert g / d.youngs["value"] == pytest.approx(9.81 / 5000.0, rel=0.05)
    assert g == pytest.approx(9.81, rel=0.35)
    assert d.extended_gain > 0.02 and d.gain_interval[0] > 0
    assert d.youngs["identifiable"]


def test_inclusion_is_named_where_it_is(tmp_path):
    """The centre within 4 mm laterally and 5 mm in depth: the data see the inclusion
    through 3-9 mm deep presses of a 5 mm sphere, on 1 mm camera noise and 8 mN force
    noise; a bigger, deeper sphere of similar stiffness explains them nearly as well,
    so radius and ratio are only required to make it stiffer than the bulk."""
    d, truth = diagnose_hidden(tmp_path, "inclusion", 0, ("base_compliance",))
    c = _named(d, "inclusion")
    centre = np.array(c.parameters["center"])
    assert np.linalg.norm(centre[:2] - truth["center"][:2]) < 0.004
    assert abs(centre[2] - truth["center"][2]) < 0.005
    assert c.parameters["stiffness_ratio"] > 1.5
    assert d.force["gain"] > 0.05


def test_viscoelasticity_is_named_with_its_relaxation_time(tmp_path):
    """Relaxation time within a factor 2 (a Maxwell arm of 0.5 s, ratio 2). Seed 2: measured
    0.53 s, ratio 2.31, gains 4.2 % (surface) and 10 % (force)."""
    d, truth = diagnose_hidden(tmp_path, "viscoelasticity", 2, ("gravity",))
    c = _named(d, "viscoelasticity")
    assert 0.25 < c.parameters["relaxation_time"] < 1.0
    assert d.extended_gain > 0 and d.force["gain"] > 0.05
