"""The strain-stiffening law among the model-form worlds a claim must beat: it reaches the
replay (a deep press meets a stiffer phantom, a shallow one the same), and the worlds hold it."""

import numpy as np
import pytest

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence, Spec
from core.diagnosis.model_form import model_form_ends
from core.diagnosis.nuisance import STIFFENED_LAW
from core.diagnosis.patches import field_layout
from core.identification.execution import SerialExecutor
from core.preparation import prepare_session
from tests._presets import SHORT_SMALL


@pytest.fixture(scope="module")
def evidence(tmp_path_factory):
    from core.lab import generate_session

    path = generate_session(tmp_path_factory.mktemp("lab") / "none-s5", preset=SHORT_SMALL, seed=5, effects=[])
    prepared = prepare_session(path)
    cfg = DiagnosisConfig()
    return Evidence(prepared, cfg, SerialExecutor(), field_layout(prepared, cfg))


def test_the_stiffened_world_is_a_stiffer_phantom_under_deep_presses_only(evidence):
    """Replayed at the same E, the Yeoh k = 1 world's probe force is the corotational
    replay's at shallow indentation (the stiffening term is quartic in the strain: no
    change at small strain) and larger at the deepest (strain stiffening); it is one of
    the worlds alone, not at the corners."""
    ev = evidence
    E = ev.cfg.youngs_modulus
    ends = dict(model_form_ends(ev))
    label = f"law stable_yeoh k={STIFFENED_LAW['stiffening']:g}"
    assert ends[label] == STIFFENED_LAW
    assert not any("stable_yeoh" in k for k in ends if ", " in k)  # not at the corners
    base, stiff = ev.runs([Spec((), E), Spec((), E, **STIFFENED_LAW)], "train")
    for b, s in zip(base, stiff):
        fb, fs = np.linalg.norm(b.force, axis=1), np.linalg.norm(s.force, axis=1)
        deep = int(np.argmax(fb))
        assert fb[deep] > 0.1  # a press, N
        # measured on this session: 1.35 and 1.55 at the two train sequences' deepest frames
        assert fs[deep] > 1.2 * fb[deep], (fs[deep], fb[deep])
        touching = np.flatnonzero((fb > 0.02) & (np.arange(fb.size) < deep))  # loading (unloading lags)
        first = touching[np.argmin(fb[touching])]  # the shallowest loading frame in contact
        assert fb[first] < 0.5 * fb[deep]
        assert fs[first] == pytest.approx(fb[first], rel=0.05)  # measured 1.019 (0.25 N) and 1.000 (0.06 N)
