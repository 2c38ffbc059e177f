"""What the viewer shows of a diagnosis (app.viewer.diagnosis_data, issue 19 item 3): the
signed residual against an analytic offset, the layers a diagnose job writes checked
against core's replay, each cause's geometry, and the colour modes the viewer offers."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from app.viewer.diagnosis_data import cause_geometry, signed_residuals, vertex_normals, write_diagnosis_run
from core.simulation.mesh import box_mesh

SIZE = np.array([0.06, 0.03, 0.03])


def _top_points(offset: float, n: int = 40) -> np.ndarray:
    x, y = np.meshgrid(np.linspace(0.001, SIZE[0] - 0.001, n), np.linspace(0.001, SIZE[1] - 0.001, n // 2))
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, SIZE[2] + offset)], axis=1)


@pytest.mark.parametrize("offset", [5e-4, -3e-4])
def test_signed_residual_of_a_surface_offset_along_its_normal(offset):
    mesh = box_mesh(SIZE, (7, 4, 4))
    positions = mesh.nodes[None].astype(np.float64)
    r = signed_residuals(positions, mesh.surface_triangles, [_top_points(offset)])[0]
    top = np.flatnonzero(np.isclose(mesh.nodes[:, 2], SIZE[2]))
    inner = top[(mesh.nodes[top, 0] > 1e-6) & (mesh.nodes[top, 0] < SIZE[0] - 1e-6)
                & (mesh.nodes[top, 1] > 1e-6) & (mesh.nodes[top, 1] < SIZE[1] - 1e-6)]
    np.testing.assert_allclose(r[inner], offset, atol=1e-9)  # flat face: the normal is +z exactly
    bottom = np.flatnonzero(np.isclose(mesh.nodes[:, 2], 0.0))
    assert np.all(np.isnan(r[bottom]))  # no measured point falls to the hidden bottom face
    n = vertex_normals(mesh.nodes, mesh.surface_triangles)
    np.testing.assert_allclose(n[inner], [[0.0, 0.0, 1.0]] * len(inner), atol=1e-12)


def test_cause_geometry_of_every_kind():
    from core.simulation.effects import EFFECT_KINDS

    shapes = {}
    for kind in EFFECT_KINDS:
        effect = {"kind": kind, **EFFECT_KINDS[kind]().to_dict()}
        effect.pop("kind", None)
        g = cause_geometry({"kind": kind, **effect}, SIZE)
        shapes[kind] = g and g["shape"]
    assert shapes == {"gravity": "vector", "inclusion": "sphere", "viscoelasticity": None, "friction": None,
                      "base_compliance": None, "probe_radius": "probe_sphere", "time_offset": None,
                      "kinematic_offset": "probe_vector"}
    g = cause_geometry({"kind": "gravity", "g": [0.0, 0.0, -9.80665]}, SIZE)
    np.testing.assert_allclose(g["vector"], [0.0, 0.0, -0.015])
    assert g["origin"][2] > SIZE[2] and g["label"] == "gravity |g| 9.81 m/s^2 (arrow 15 mm per 9.81)"
    g = cause_geometry({"kind": "gravity", "g": [0.0, 0.0, -16.0]}, SIZE, {"value": 5000.0, "replay_grid_value_used": 8000.0})
    assert g["label"].endswith("16.00 m/s^2 (arrow 15 mm per 9.81) at the replay grid's E 8000 Pa; "
                               "10.00 m/s^2 at the mesh-corrected E 5000 Pa")
    k = cause_geometry({"kind": "kinematic_offset", "offset": [0.001, 0.0, -0.002]}, SIZE)
    np.testing.assert_allclose(k["vector"], [0.005, 0.0, -0.01])


@pytest.mark.filterwarnings("ignore:Mean of empty slice")
def test_diagnosis_run_layers_are_the_replays_with_and_without_the_claimed_causes(small_session, tmp_path):
    """A diagnose job's viewer run (the job itself takes minutes): the test sequence replayed
    plainly, with the claimed gravity (the corrected mesh), the gravity's change of the
    surface, the signed residuals and the answers, checked against core's replay here."""
    from app.viewer.buffers import SequenceView
    from app.viewer.data import load_run
    from core.preparation import prepare_session
    from core.simulation import effect_from_dict
    from core.simulation.replay import ReplayConfig, replay

    gravity = {"kind": "gravity", "g": [0.0, 0.0, -9.81]}
    summary = {"extended": {"kinds": ["gravity"], "effects": [gravity], "test_error": 0.0011},
               "baseline": {"test_error": 0.0013},
               "answers": {"gravity": "found", "inclusion": "not_found", "friction": "cannot_tell"},
               "detectability": {"gravity": {"min_size": 2.0, "why": "found"},
                                 "inclusion": {"min_size": 1.7, "why": "not found"},
                                 "friction": {"min_size": None, "why": "no slide"}}}
    prepared = prepare_session(small_session, ReplayConfig())
    shown = write_diagnosis_run(prepared, summary, (13, 5, 5), 5000.0, tmp_path / "run")
    assert shown["corrected_shown"] == {"seq01": "extended"}  # the small preset's test sequence
    assert shown["layers"] == ["base_residual", "extended_residual", "change_gravity"]
    run = load_run(tmp_path / "run")
    seq = run.sequences["seq01"]
    base = ReplayConfig(youngs_modulus=5000.0, sequences=("seq01",))
    plain = replay(small_session, base, prepared=prepared).sequences["seq01"].simulation.positions
    expected = replay(small_session, replace(base, effects=(effect_from_dict(gravity),)), prepared=prepared)
    ext = expected.sequences["seq01"].simulation.positions
    np.testing.assert_allclose(seq.positions, plain, atol=1e-6)  # float32 on disk
    np.testing.assert_allclose(seq.corrected_positions, ext, atol=1e-6)

    # gravity's change of the surface: the node displacement along the base outward normal
    faces = box_mesh(np.ptp(plain[0], axis=0), (13, 5, 5)).surface_triangles
    change = seq.diagnosis.changes["gravity"]
    f = seq.n_frames // 2
    n = vertex_normals(plain[f], faces)
    np.testing.assert_allclose(change[f], np.einsum("ij,ij->i", ext[f] - plain[f], n), atol=1e-7)
    top = np.flatnonzero(np.isclose(plain[0][:, 2], plain[0][:, 2].max()))
    assert np.nanmean(change[:, top]) < -1e-5  # the top sags: it moves against its outward normal

    # the residuals are the time means of the signed residual of each model
    clouds = prepared.sequences["seq01"].clouds
    np.testing.assert_allclose(seq.diagnosis.base_residual,
                               np.nanmean(signed_residuals(plain, faces, clouds), axis=0), atol=1e-7, equal_nan=True)
    np.testing.assert_allclose(seq.diagnosis.extended_residual,
                               np.nanmean(signed_residuals(ext, faces, clouds), axis=0), atol=1e-7, equal_nan=True)

    view = run.diagnosis
    assert view["answers"]["gravity"] == {"answer": "found", "min_size": 2.0, "unit": "m/s^2", "why": "found"}
    assert view["answers"]["friction"]["min_size"] is None
    assert [g["shape"] for g in view["geometry"]] == ["vector"]
    assert json.loads((tmp_path / "run" / "diagnosis" / "view.json").read_text()) == view

    sv = SequenceView(seq)
    assert sv.colour_modes() == ["error", "base_residual", "extended_residual", "change_gravity"]
    values, vmax = sv.signed_layer("change_gravity")
    assert values.shape == (seq.n_frames, seq.positions.shape[1]) and vmax > 0
    assert sv.glb("fem", f, "change_gravity") != sv.glb("fem", f, "error")
    with pytest.raises(KeyError):
        sv.signed_layer("change_friction")


def test_a_diagnosis_without_claims_still_shows_the_base_residual(small_session, tmp_path):
    from app.viewer.data import load_run
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig

    prepared = prepare_session(small_session, ReplayConfig())
    summary = {"extended": {"kinds": [], "effects": []}, "baseline": {"test_error": 0.0012},
               "answers": {"gravity": "not_found"}, "detectability": {"gravity": {"min_size": 3.0, "why": "x"}}}
    shown = write_diagnosis_run(prepared, summary, (13, 5, 5), 5000.0, tmp_path / "run")
    assert shown == {"corrected_shown": {}, "layers": ["base_residual"]}
    run = load_run(tmp_path / "run")
    seq = run.sequences["seq01"]
    assert seq.corrected_positions is None and seq.diagnosis.extended_residual is None and not seq.diagnosis.changes
    assert np.isfinite(seq.diagnosis.base_residual).sum() > 20  # the observed top and sides
    assert run.diagnosis["geometry"] == [] and run.diagnosis["claimed"] == []
