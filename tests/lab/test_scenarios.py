"""Hidden-effect scenarios (core.lab.scenarios): what each kind's session design holds."""

import numpy as np
import pytest

from core.lab import SCENARIO_KINDS, complete_effects, hidden_effects, scenario
from core.lab.generate import PHANTOM_SIZE


def test_every_kind_hides_exactly_itself_with_valid_parameters():
    for kind in SCENARIO_KINDS:
        lab, effects = scenario(kind, seed=1, duration=6.0)
        assert [e["kind"] for e in effects] == ([] if kind == "none" else [kind])
        complete_effects(effects)  # valid for the simulator
        assert lab.sequence_durations == (6.0,) * len(lab.sequence_roles)
    with pytest.raises(ValueError, match="unknown scenario kind"):
        hidden_effects("wobble", 0)


def test_the_inclusion_moves_with_the_seed_and_the_palpation_covers_it():
    centres = []
    for seed in range(4):
        lab, (inc,) = scenario("inclusion", seed)
        c = np.array(inc["center"])
        centres.append(c)
        x0, y0, x1, y1 = lab.probing.top_region
        assert x0 < c[0] < x1 and y0 < c[1] < y1 and lab.probing.side_probability == 0.0
        assert c[2] + inc["radius"] == pytest.approx(PHANTOM_SIZE[2] - 0.002)  # 2 mm under the top
    assert len({tuple(np.round(c, 6)) for c in centres}) == 4


def test_friction_is_probed_by_sliding_and_other_kinds_keep_the_preset_protocol():
    lab, _ = scenario("friction", 0)
    assert lab.probing.slide_probability == 1.0
    base, _ = scenario("gravity", 0)
    assert base.probing.slide_probability < 1.0 and base.probing.top_region is None and base.probing.face_cycle is None


def test_a_probe_radius_is_probed_on_a_side_and_the_top():
    """Side pokes show the radius (the calibration keeps the depth of top pokes right);
    top pokes tell it from a lateral robot offset, which would shift their dents."""
    lab, (eff,) = scenario("probe_radius", 0, 6.0)
    assert lab.probing.face_cycle == ("side", "top") and eff["radius"] > lab.probe_radius
