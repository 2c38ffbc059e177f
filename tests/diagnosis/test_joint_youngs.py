"""The diagnosis's verdict on E with force data follows the fit's rule (issue 19 item 2):
identifiable when its 95 % interval (here with the model form) spans at most the fit's
MAX_RATIO, the same threshold the sweep and the fit apply."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from core.diagnosis.youngs import joint_youngs
from core.identification.verdict import MAX_RATIO


def _fit(E: float, rel: float) -> SimpleNamespace:
    """A joint fit of log10 E with a 95 % interval of +-``rel`` (relative)."""
    return SimpleNamespace(x=[math.log10(E)], se=[math.log10(1.0 + rel) / 1.96], youngs_modulus=E)


@pytest.mark.parametrize("low,high,identifiable", [(4000.0, 6000.0, True), (2700.0, 8550.0, False),
                                                    (1000.0, 2900.0, True), (1000.0, 3100.0, False)])
def test_the_interval_rule_is_the_fits(low, high, identifiable):
    E = math.sqrt(low * high)
    v = joint_youngs(_fit(E, 0.001), {"low": low, "high": high, "variants": []})
    lo, hi = v["interval"]
    assert lo == pytest.approx(low / 1.001, rel=1e-6) and hi == pytest.approx(high * 1.001, rel=1e-6)
    assert v["identifiable"] is identifiable and v["statistic"]["max_ratio"] == MAX_RATIO
    assert v["statistic"]["ratio"] == pytest.approx(hi / lo)
    assert v["value"] == pytest.approx(E)  # the estimate is kept; the verdict says whether it holds
    if not identifiable:
        assert f"spans a factor {hi / lo:.2f} (> {MAX_RATIO:g})" in v["reason"]


def test_a_wide_statistical_interval_alone_is_not_identifiable():
    v = joint_youngs(_fit(5000.0, 2.5))  # 95 % from 5000 / 3.5 to 5000 x 3.5: a factor 12
    assert v["identifiable"] is False and "statistical" in v["reason"]
    assert joint_youngs(_fit(5000.0, 0.2))["identifiable"] is True


def test_gravity_read_at_the_reported_youngs_modulus():
    from core.diagnosis.youngs import gravity_at_reported_youngs

    youngs = {"value": 4803.0, "replay_grid_value_used": 8541.0}
    assert gravity_at_reported_youngs([-1.23, 1.46, -16.6], youngs) == pytest.approx(
        math.sqrt(1.23**2 + 1.46**2 + 16.6**2) * 4803.0 / 8541.0)
    assert gravity_at_reported_youngs([0, 0, -9.81], {"value": 5000.0, "replay_grid_value_used": 5020.0}) is None
    assert gravity_at_reported_youngs([0, 0, -9.81], {"value": None, "replay_grid_value_used": 5000.0}) is None
