"""E's model-form range on a phantom given by ``phantom.stl`` (issue 18): its variants are
replayed on the phantom's own mesh (at the replay's element size and at half its mean
edge), not on a box of the phantom's bounding size.

One dome session of the virtual lab (6 s sequences, seed 3, force columns; ~15 s; the run's
shared ``small_dome_force_session``) prepared with the module's own cache folder.
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def dome(small_dome_force_session, tmp_path_factory):
    """(prepared dome session, one train sequence's name)."""
    from core.preparation import prepare_session

    root = tmp_path_factory.mktemp("dome-mf")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TISSUETWIN_CACHE_DIR", str(root / "cache"))
        prepared = prepare_session(small_dome_force_session)
        name = next(n for n, s in prepared.sequences.items() if s.role == "train")
        yield prepared, name


def _force_fit(prepared, name, mesh, E, dt):
    """E of the least-squares fit along the force of ``mesh`` replayed at ``E`` (as the
    model form fits a variant: ``E f.m / f.f``, noise-weighted by the rest frames' force)."""
    from core.simulation import Material, SimulationConfig, build_model, simulate

    seq = prepared.sequences[name]
    model = build_model(mesh, prepared.mass, Material(E, 0.44, "corotational"), SimulationConfig(dt=dt), [])
    f = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times).contact_force
    m = seq.force_at(seq.frame_times)
    rest = m[prepared.rest_frames(name)]
    sigma = np.maximum(np.sqrt(np.mean(rest**2, axis=0)), 1e-3) if rest.shape[0] >= 10 else np.ones(3)
    return E * float(np.sum(f * m / sigma**2)) / float(np.sum(f * f / sigma**2))


def test_a_dome_s_model_form_runs_on_its_own_mesh_at_both_element_sizes(dome):
    from core.identification.model_form import COARSE, FINE, variant_element_sizes, youngs_model_form
    from core.simulation import box_mesh
    from core.simulation.meshing import mean_edge_length
    from core.simulation.replay import replay_mesh

    prepared, name = dome
    E, dt = 8000.0, 1.0 / 60.0
    sizes = variant_element_sizes(prepared, None)
    coarse = replay_mesh(prepared, COARSE, None)
    assert sizes[COARSE] is None and sizes[FINE] == pytest.approx(mean_edge_length(coarse) / 2.0)
    fine = replay_mesh(prepared, COARSE, sizes[FINE])
    assert fine.nodes.shape[0] > 3 * coarse.nodes.shape[0]

    mf = youngs_model_form(prepared, [], E, names=[name], variants=(), dt=dt)
    (ref, ref_fine) = mf["variants"]
    # the reference and the fine reference are the replay's own meshes, fitted as the model form fits
    assert ref["youngs_modulus"] == pytest.approx(_force_fit(prepared, name, coarse, E, dt), rel=1e-9)
    assert ref_fine["youngs_modulus"] == pytest.approx(_force_fit(prepared, name, fine, E, dt), rel=1e-9)
    assert ref["model"] == "corotational, nu 0.44, the replay's mesh"
    assert ref_fine["model"] == f"corotational, nu 0.44, elements {1e3 * sizes[FINE]:.1f} mm"
    # ... which a box of the dome's bounding size (what the variants ran on before) is not
    boxed = _force_fit(prepared, name, box_mesh(prepared.size, COARSE), E, dt)
    assert abs(boxed / ref["youngs_modulus"] - 1.0) > 0.05
    assert mf["fine_over_coarse"] == pytest.approx(ref_fine["youngs_modulus"] / ref["youngs_modulus"])


def test_the_box_keeps_its_grid_variants():
    from core.identification.model_form import FINE, COARSE, variant_element_sizes, _label, REFERENCE, VARIANTS

    class Box:
        stl_path = None

    assert variant_element_sizes(Box(), None) is None
    assert _label(REFERENCE, None) == "corotational, nu 0.44, 13x5x5"
    assert _label(VARIANTS[-1], None, FINE) == "yeoh k=2, nu 0.44, 25x9x9"
    assert COARSE == (13, 5, 5)


@pytest.fixture(scope="module")
def on_a_soft_base(tmp_path_factory):
    """A box session of the virtual lab whose phantom sits on a compliant base (50 kPa/m),
    with force columns (small preset, 6 s sequences, seed 5)."""
    from core.lab import generate_session
    from core.lab.generate import PRESETS
    from core.preparation import prepare_session

    root = tmp_path_factory.mktemp("soft-base")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TISSUETWIN_CACHE_DIR", str(root / "cache"))
        path = generate_session(root / "session", preset=PRESETS["small"].with_duration(6.0), seed=5,
                                effects=[{"kind": "base_compliance", "stiffness": 5e4}], with_force=True)
        yield prepare_session(path)


def test_the_force_fit_of_E_beside_a_compliant_base(on_a_soft_base):
    """force_youngs refits E along the force of several models in one map: without the base
    the replay reads the phantom soft (the base took part of every press); with it E rises,
    the more the softer the base, and equals youngs_model_form's reference fit."""
    from core.identification.model_form import force_youngs, youngs_model_form

    prepared = on_a_soft_base
    E = 5000.0
    models = [[], *([{"kind": "base_compliance", "stiffness": k}] for k in (2e5, 5e4, 2.5e4))]
    E0, E_stiff, E_lab, E_soft = force_youngs(prepared, models, E)
    # measured: 1958, 2585, 4146 and 6005 Pa for the lab's 5000 Pa on its finer mesh
    assert E0 < E_stiff < E_lab < E_soft
    assert E_lab / E0 > 1.8
    assert E_lab == pytest.approx(5000.0, rel=0.3)  # with the lab's base, near the lab's E
    assert E0 == pytest.approx(youngs_model_form(prepared, [], E, variants=())["variants"][0]["youngs_modulus"],
                               rel=1e-12)
