"""The planner: its moves stay on the phantom's faces and within the depth and speed
limits, an unreachable phantom is an error that says why, and for friction that the
session could not tell it proposes a slide and asks for the force."""

import json

import numpy as np
import pytest

from app.cli import main
from core.diagnosis.moves import within_duration
from core.diagnosis.planner import PlanError, PlanLimits, candidate_moves
from core.lab.probing import ProbeTrajectory, penetration_depth
from core.simulation.effects import EFFECT_KINDS

SIZE = np.array([0.068, 0.040, 0.036])
RADIUS = 0.005


@pytest.mark.parametrize("depth,speed", [(0.008, 0.010), (0.003, 0.004)])
def test_moves_keep_to_the_faces_depth_and_speed(depth, speed):
    lim = PlanLimits(max_depth=depth, speed=speed)
    moves = candidate_moves(SIZE, RADIUS, lim)
    faces = {m.face for m in moves}
    assert faces == {"+z", "+x", "-x", "+y", "-y"}
    assert any(m.name.startswith("slide") for m in moves)
    for m in moves:
        t = np.arange(0.0, m.duration, 0.002)
        c = ProbeTrajectory(m.knots_t, m.knots_p)(t)
        d = penetration_depth(c, SIZE, RADIUS)
        assert d.max() == pytest.approx(depth, abs=2e-4), m.name  # presses to the limit, not beyond
        assert d.max() <= depth + 1e-6
        # in contact: never faster than the limit, and the sphere's centre over the face it presses
        v = np.linalg.norm(np.diff(c, axis=0), axis=1) / 0.002
        contact = (d[1:] > 0) & (d[:-1] > 0)
        assert v[contact].max() <= 1.01 * speed, m.name
        inside = d > 0
        assert np.all(c[inside] >= -RADIUS) and np.all(c[inside] <= SIZE + RADIUS), m.name


def test_an_unreachable_phantom_is_an_error_that_says_why():
    with pytest.raises(PlanError, match="no point"):
        candidate_moves([0.012, 0.040, 0.036], RADIUS, PlanLimits(edge_margin=0.008))
    with pytest.raises(PlanError, match="depth limit"):
        candidate_moves(SIZE, RADIUS, PlanLimits(max_depth=0.0002))


def test_moves_on_a_dome_press_along_its_normals_within_the_limits():
    from core.diagnosis.moves import surface_moves
    from core.lab.shapes import dome_surface
    from core.preparation.shape import SurfaceShape

    dome = SurfaceShape(*dome_surface(0.035, 0.025))
    rng = np.random.default_rng(0)
    # sites as the diagnosis's patches give them: points near the surface, with normals
    d = rng.normal(size=(40, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts, nrm = dome.project(np.array([0.035, 0.035, -0.012]) + 0.05 * d)
    lim = PlanLimits(max_depth=0.004, speed=0.008)
    moves = surface_moves(dome, RADIUS, (pts - 5e-4 * nrm, nrm), lim)
    presses = [m for m in moves if m.name.startswith("press-")]
    assert len(presses) == 6 and any(m.name.startswith("slide-") for m in moves)
    tops = np.array([m.knots_p[2] for m in presses])
    # spread over the dome: no two presses closer than 1 cm
    assert min(np.linalg.norm(a - b) for i, a in enumerate(tops) for b in tops[i + 1:]) > 0.01
    # each press goes in along the sphere's normal at its contact (approach -> pressed)
    from tests._shapes import DOME_CENTRE

    for m in presses:
        u = m.knots_p[1] - m.knots_p[2]
        n = m.knots_p[2] - DOME_CENTRE
        assert np.dot(u, n) / (np.linalg.norm(u) * np.linalg.norm(n)) > np.cos(np.radians(8)), m.name
    for m in moves:
        t = np.arange(0.0, m.duration, 0.002)
        c = ProbeTrajectory(m.knots_t, m.knots_p)(t)
        depth = dome.penetration_depth(c, RADIUS)
        assert depth.max() <= lim.max_depth + 1e-6, m.name
        if m.name.startswith("press-"):
            assert depth.max() == pytest.approx(lim.max_depth, abs=3e-4), m.name  # to the limit, along the normal
        v = np.linalg.norm(np.diff(c, axis=0), axis=1) / 0.002
        contact = (depth[1:] > 0) & (depth[:-1] > 0)
        assert v[contact].max() <= 1.01 * lim.speed, m.name
    # a surface seen only from below cannot be pressed from above
    with pytest.raises(PlanError, match="from above"):
        surface_moves(dome, RADIUS, (np.array([[0.035, 0.035, 0.0]]), np.array([[0.0, 0.0, -1.0]])), lim)


def test_a_move_longer_than_the_plan_is_not_offered():
    """``--duration`` bounds the plan: a move longer than it (a slide, a side press, each
    with its return to rest) is dropped, never cut short; none fitting is an error that
    names the shortest move. (Seen: a 6 s plan returned a 9.4 s slide.)"""
    moves = candidate_moves((0.0687, 0.0393, 0.0358), 0.004, PlanLimits())
    assert {m.name for m in moves} >= {"slide-top-x", "press-+x"}
    lim = PlanLimits(duration=8.0)
    kept = within_duration(moves, lim)
    assert kept and all(m.duration <= 8.0 for m in kept)
    assert {m.name for m in moves if m.duration <= 8.0} == {m.name for m in kept}
    assert not any(m.name.startswith("slide") for m in kept)
    shortest = min(moves, key=lambda m: m.duration)
    with pytest.raises(PlanError, match=f"no move fits in a 3.0 s plan: the shortest, {shortest.name}, takes"):
        within_duration(moves, PlanLimits(duration=3.0))


@pytest.mark.slow
def test_plan_for_friction_slides_and_records_force(small_session, tmp_path):
    """``tissuetwin plan --kinds friction`` on a session without force: the plan slides
    across the top, asks for the force, predicts a friction ``min_size`` it can show, and
    writes a path the virtual lab can record."""
    diag = tmp_path / "diag"
    diag.mkdir()
    detect = {k: {"min_size": None, "parameters": {}, "why": "test"} for k in EFFECT_KINDS}
    (diag / "diagnosis.json").write_text(json.dumps({"detectability": detect, "answers": {}, "extended": {"effects": []},
                                                     "youngs_modulus": {}}))
    out = tmp_path / "plan"
    assert main(["plan", str(small_session), "--diagnosis", str(diag), "--out", str(out), "--kinds", "friction",
                 "--serial", "--duration", "12"]) == 0
    plan = json.loads((out / "plan.json").read_text())
    assert plan["format"] == "tissue-plan/1" and plan["targets"] == {"friction": "asked for"}
    assert any(m["name"].startswith("slide") for m in plan["moves"]), plan["moves"]
    assert plan["record_force"] is True and any("force" in line for line in plan["description"])
    mu = plan["predicted_min_size"]["friction"]
    assert mu is not None and mu < EFFECT_KINDS["friction"].max_size
    # held to the model-form worlds: any world that set a size is named
    assert set(plan["predicted_model_form_world"]) <= set(plan["predicted_min_size"])
    assert plan["duration_s"] <= 12.0 + 1e-9
    assert "slide" in (out / "plan.md").read_text()
    assert (out / "kinematics.csv").read_text().splitlines()[0].startswith("t,")
    # the lab records it
    rec = tmp_path / "recorded"
    assert main(["generate", "--out", str(rec), "--plan", str(out), "--force",
                 "--effects", '[{"kind": "friction", "mu": 0.5}]']) == 0
    assert (rec / "sequences").is_dir() and "fx" in next((rec / "sequences").glob("*/kinematics.csv")).read_text().splitlines()[0]


def test_a_plan_s_prediction_holds_for_the_weakest_model_form_world():
    """The planner's q is the least of the replay's and every model-form world's: a world
    whose change of the data is half the replay's signature needs twice the strength (q/4),
    one whose change the fit along the signature cannot take up leaves nothing (q 0), the
    nuisance directions are projected out of the worlds' changes too, and the fine mesh
    (its runs on the fine grid, unshifted, its own base) is one of the worlds."""
    from core.diagnosis.config import DiagnosisConfig
    from core.diagnosis.model_form import mesh_world, model_form_worlds
    from core.diagnosis.planner import _world_q

    rng = np.random.default_rng(3)
    L = 40
    N = rng.normal(size=(L, 2))  # two nuisance directions

    def project(X):
        return X - N @ np.linalg.lstsq(N, X, rcond=None)[0]

    D_raw = rng.normal(size=L)
    D = project(D_raw)
    sigma2, strength = 0.5, 2.0
    q = float(D @ D) / sigma2
    effect = {"kind": "friction", "mu": 0.3}

    class FakeEvidence:
        cfg = DiagnosisConfig()

        def __init__(self, change):
            self.change = change  # {world label: its change of the data per unit strength}
            self.labels = {repr(f): name for name, f in model_form_worlds(self)}

        def runs(self, specs, role, fine=False):
            assert role == "validation"
            return [(spec, fine) for spec in specs]

        def vector(self, run, shifted=True):
            spec, fine = run
            fields = {k: getattr(spec, k) for k in ("law", "poisson_ratio", "stiffening", "simulation")
                      if getattr(spec, k) not in (None, (), 0.0)}
            name = mesh_world(self)[0] if fine else self.labels[repr(fields)]
            base = np.full(L, 0.3 if fine else 0.1)
            return base + (strength * self.change[name] if effect in spec.effects else 0.0)

    names = [name for name, _ in model_form_worlds(FakeEvidence({}))]
    assert len(names) == 8
    names.append(mesh_world(FakeEvidence({}))[0])  # the fine mesh, its base its own
    # every world makes the replay's own change: q unchanged, no world named
    same = FakeEvidence({n: D_raw for n in names})
    assert _world_q(same, (), 5000.0, effect, D, strength, project, sigma2, q) == (pytest.approx(q, rel=1e-9), "")
    # one world makes half of it, plus a nuisance-shaped part: q / 4, that world named
    half = dict(same.change)
    half[names[2]] = 0.5 * D_raw + N @ np.array([3.0, -1.0])
    got, world = _world_q(FakeEvidence(half), (), 5000.0, effect, D, strength, project, sigma2, q)
    assert got == pytest.approx(q / 4, rel=1e-9) and world == names[2]
    # a world whose change is orthogonal to the signature (after the nuisances): nothing shows
    ortho = dict(same.change)
    u = project(rng.normal(size=L))
    ortho[names[5]] = u - D * (u @ D) / (D @ D)
    got, world = _world_q(FakeEvidence(ortho), (), 5000.0, effect, D, strength, project, sigma2, q)
    assert got == pytest.approx(0.0, abs=1e-9 * q) and world == names[5]
    # the fine mesh making a third of it: q / 9, the fine mesh named
    third = dict(same.change)
    third[names[-1]] = D_raw / 3
    got, world = _world_q(FakeEvidence(third), (), 5000.0, effect, D, strength, project, sigma2, q)
    assert got == pytest.approx(q / 9, rel=1e-9) and world == "the 25x9x9 mesh"
