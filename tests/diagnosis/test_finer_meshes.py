"""The meshes finer than the fine reference on a phantom given by ``phantom.stl`` (issues 16
and 18): a claim that moves the contact must hold on them (``beyond_finer_mesh``), and a
contact kind's ``min_size`` must too (``world_min_size``). On the box they are the grids
31x11x11 and 37x13x13 (``tests/diagnosis/test_contact_discrepancy.py``); on any other
shape they are the phantom's own mesh at the fine element size over 1.25 and 1.5.

The run's shared dome session (``small_dome_force_session``: 6 s sequences, seed 3, force
columns), replayed at a coarse 8 mm element size so that the finer meshes stay small (the
fine reference 4 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

ELEMENT = 0.008
"""m: the replay's element size here (the fine reference's is half of it)."""


@pytest.fixture(scope="module")
def dome_evidence(small_dome_force_session):
    """(prepared dome session, Evidence at ELEMENT with its fine reference)."""
    from core.diagnosis.config import DiagnosisConfig
    from core.diagnosis.evidence import Evidence
    from core.diagnosis.patches import field_layout
    from core.identification.execution import SerialExecutor
    from core.preparation import prepare_session

    prepared = prepare_session(small_dome_force_session)
    cfg = DiagnosisConfig(element_size=ELEMENT)
    return prepared, Evidence(prepared, cfg, SerialExecutor(), field_layout(prepared, cfg))


def test_a_dome_s_finer_meshes_are_its_own_at_smaller_elements_and_converge(dome_evidence):
    """``finer_meshes`` of a dome: its own mesh at 4 mm / 1.25 and 4 mm / 1.5 (3.2 and
    2.67 mm), each with more nodes than the one before; the base model replayed on them
    (through ``Request.element_size``, as ``beyond_finer_mesh`` asks) differs from the
    fine reference's replay, and by less than the coarse replay does: the residual field
    converges under refinement, so the runs are really on the finer meshes. Measured: 727,
    1852, 2622 and 3638 nodes at 8, 4, 3.2 and 2.67 mm; the train field's distance to the
    fine reference's 13.6 mm (coarse), 2.1 and 2.9 mm (the finer meshes; not monotone, as
    on the box), 1.1 mm between the two finer ones (norms over every frame and patch)."""
    from core.diagnosis.evidence import Request, Spec
    from core.diagnosis.model_form import finer_meshes
    from core.simulation.replay import replay_mesh

    prepared, ev = dome_evidence
    assert ev.fine_element_size == pytest.approx(ELEMENT / 2)
    meshes = finer_meshes(ev)
    assert [m.element_size for m in meshes] == pytest.approx([ELEMENT / 2 / 1.25, ELEMENT / 2 / 1.5])
    assert all("mm mesh" in m.label for m in meshes)
    nodes = [replay_mesh(prepared, ev.cfg.grid, h).nodes.shape[0] for h in (ELEMENT, ELEMENT / 2)
             + tuple(m.element_size for m in meshes)]
    assert nodes == sorted(nodes) and len(set(nodes)) == 4, nodes

    base = [Spec((), ev.cfg.youngs_modulus)]
    coarse, fine, *finer = ev.runs_together([Request(base, "train"), Request(base, "train", fine=True)]
                                            + [m.request(base, "train") for m in meshes])
    assert all(r.ok for runs in [coarse, fine, *finer] for r in runs[0])

    def field(runs):
        return np.concatenate([np.nan_to_num(r.field).ravel() for r in runs[0]])

    f_coarse, f_fine, f_125, f_15 = field(coarse), field(fine), *(field(r) for r in finer)
    to_fine = np.linalg.norm(f_coarse - f_fine)
    assert to_fine > 0
    for f in (f_125, f_15):
        d = np.linalg.norm(f - f_fine)
        assert 0 < d < to_fine, (d, to_fine)
    assert np.linalg.norm(f_15 - f_125) < to_fine
