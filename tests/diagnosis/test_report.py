"""The diagnosis report's evidence plot with candidates whose score is undefined."""

import math
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from core.diagnosis.report import evidence_scores  # noqa: E402


def test_undefined_scores_leave_gaps_instead_of_failing_the_report():
    """A score is None when its null's critical value is zero or not finite; a 2-minute
    session's diagnosis failed in write_diagnosis on one (matplotlib cannot add None)."""
    cands = [SimpleNamespace(kind="gravity", round=0, score=3.5), SimpleNamespace(kind="friction", round=0, score=None),
             SimpleNamespace(kind="gravity", round=1, score=0.2)]
    r0 = evidence_scores(cands, ["gravity", "friction", "inclusion"], 0)
    assert r0[0] == 3.5 and math.isnan(r0[1]) and math.isnan(r0[2])
    r1 = evidence_scores(cands, ["gravity", "friction"], 1)
    assert r1[0] == 0.2 and math.isnan(r1[1])
    fig, ax = plt.subplots()
    bars = ax.bar(range(3), r0, 0.4)  # what report._maps draws
    assert len(bars) == 3 and bars[0].get_height() == 3.5
    plt.close(fig)
