"""Physics of each model option (effect kind of SESSION_FORMAT.md)."""

import numpy as np
import pytest

from core.simulation import (
    BaseCompliance,
    Friction,
    Gravity,
    Inclusion,
    KinematicOffset,
    Material,
    ProbePath,
    ProbeRadius,
    TimeOffset,
    Viscoelasticity,
    box_mesh,
    build_model,
    effect_from_dict,
    simulate,
    static_equilibrium,
)
from core.simulation.contact import find_contacts

SIZE = np.array([0.0687, 0.0393, 0.0358])
MASS = 0.10401
GRID = (9, 5, 5)


def _centre_top(mesh):
    top = mesh.top_nodes()
    d = np.linalg.norm(mesh.nodes[top, :2] - SIZE[:2] / 2, axis=1)
    return top[np.argmin(d)]


def test_gravity_sag_scales_as_rho_g_H2_over_E():
    mesh = box_mesh(SIZE, GRID)
    node = _centre_top(mesh)

    def sag(E, mass=MASS, g=9.81):
        x = static_equilibrium(build_model(mesh, mass, Material(E), effects=[Gravity((0, 0, -g))]))[0].x
        return mesh.nodes[node, 2] - x[node, 2]

    s = sag(5000.0)
    rho = MASS / np.prod(SIZE)
    scale = rho * 9.81 * SIZE[2] ** 2 / 5000.0
    assert 0.05 * scale < s < scale  # the right order: a fraction of rho g H^2 / E
    assert sag(10000.0) == pytest.approx(s / 2, rel=0.03)  # ~ 1/E (small strain)
    assert sag(5000.0, mass=2 * MASS) == pytest.approx(2 * s, rel=0.03)  # ~ rho
    assert sag(5000.0, g=4.905) == pytest.approx(s / 2, rel=0.03)  # ~ g


def _poke(xy, depth=0.005, T=3.0, hold=(0.8, 1.6)):
    t = np.linspace(0.0, T, 301)
    d = np.interp(t, [0, hold[0], hold[1], hold[1] + 0.3, T], [-0.002, depth, depth, -0.004, -0.004])
    c = np.zeros((t.size, 3))
    c[:, :2] = xy
    c[:, 2] = SIZE[2] + 0.005 - d
    return ProbePath(t, c)


def test_stiff_inclusion_stiffens_only_the_local_response():
    mesh = box_mesh(SIZE, GRID)
    under = np.array([SIZE[0] / 2, SIZE[1] / 2])
    far = np.array([0.012, 0.012])
    inc = Inclusion(center=(SIZE[0] / 2, SIZE[1] / 2, SIZE[2] - 0.008), radius=0.01, stiffness_ratio=8.0)

    def force(effects, xy):
        r = simulate(build_model(mesh, MASS, Material(5000.0), effects=effects), _poke(xy), 0.005, [1.2])
        return -r.contact_force[0, 2]

    assert force([inc], under) > 1.3 * force([], under)
    assert force([inc], far) == pytest.approx(force([], far), rel=0.1)


def test_inclusion_stiffness_volume_matches_the_sphere_and_moves_smoothly():
    """The volume-fraction inclusion: its excess stiffness volume, sum of V_e (scale - 1),
    is (ratio - 1) 4/3 pi r^3 within 15 % on a fine mesh, and on the coarse 13 x 5 x 5
    mesh it grows at every 0.1 mm step of the radius from 8 to 10 mm by about the
    sphere's own growth (a centroid-in-sphere test jumps by whole 84 mm^3 tetrahedra
    at a few steps and stays flat at the others)."""
    from core.simulation.model import ModelBuilder

    def excess(grid, radius, centre=(0.034, 0.02, 0.024)):
        b = ModelBuilder(box_mesh(SIZE, grid), MASS)
        Inclusion(center=centre, radius=radius, stiffness_ratio=6.0).configure(b)
        corners = b.mesh.nodes[b.mesh.tets]
        vol = np.abs(np.einsum("ij,ij->i", corners[:, 1] - corners[:, 0],
                               np.cross(corners[:, 2] - corners[:, 0], corners[:, 3] - corners[:, 0]))) / 6
        return float(vol @ (b.element_scale - 1.0))

    sphere = 5.0 * 4.0 / 3.0 * np.pi * 0.009**3
    assert excess((37, 13, 13), 0.009) == pytest.approx(sphere, rel=0.15)
    radii = np.arange(0.008, 0.0100001, 0.0001)
    steps = np.diff([excess((13, 5, 5), r) for r in radii])
    d_sphere = 5.0 * 4.0 * np.pi * radii[1:] ** 2 * 1e-4
    assert np.all(steps > 0.2 * d_sphere) and np.all(steps < 5.0 * d_sphere)


def test_viscoelastic_dent_recovers_with_the_retardation_time():
    """Standard linear solid: after release, creep back with tau_c = tau (1 + k)."""
    mesh = box_mesh(SIZE, GRID)
    node = _centre_top(mesh)
    tau, k = 0.5, 1.0
    times = np.linspace(2.0, 6.0, 81)  # release ends at 1.9 s
    path = _poke(SIZE[:2] / 2, depth=0.006, T=6.0, hold=(0.5, 1.6))
    ve = simulate(build_model(mesh, MASS, Material(5000.0), effects=[Viscoelasticity(tau, k)]), path, 0.005, times)
    el = simulate(build_model(mesh, MASS, Material(5000.0)), path, 0.005, times)
    dent_ve = mesh.nodes[node, 2] - ve.positions[:, node, 2]
    dent_el = mesh.nodes[node, 2] - el.positions[:, node, 2]
    assert dent_el[0] < 0.1 * dent_ve[0]  # the elastic solid has already recovered
    # exponential fit on the viscoelastic recovery
    good = dent_ve > 0.02 * dent_ve[0]
    slope = np.polyfit(times[good], np.log(dent_ve[good]), 1)[0]
    assert -1.0 / slope == pytest.approx(tau * (1 + k), rel=0.3)


def test_friction_drags_the_surface_along_a_slide():
    mesh = box_mesh(SIZE, GRID)
    t = np.linspace(0.0, 3.0, 301)
    c = np.zeros((t.size, 3))
    c[:, 0] = np.interp(t, [0, 1, 2.5, 3], [0.025, 0.025, 0.04, 0.04])
    c[:, 1] = SIZE[1] / 2
    c[:, 2] = SIZE[2] + 0.005 - np.interp(t, [0, 0.8, 3], [-0.002, 0.004, 0.004])
    path = ProbePath(t, c)
    top = mesh.top_nodes()

    def drag(effects):
        model = build_model(mesh, MASS, Material(5000.0), effects=effects)
        r = simulate(model, path, 0.005, [2.4])  # 2.4 s is a step's end (dt = 1/120 s)
        # the normal (penalty) part of the probe's force, from the contacts at that state
        cs = find_contacts(r.positions[0], mesh.surface_triangles, path.at(np.array([2.4]))[0], 0.005,
                           model.config.contact_subdivision)
        fn = model.contact_stiffness * cs.area * np.maximum(cs.depth, 0.0)
        normal = (fn[:, None] * cs.normals).sum(0)
        return (r.positions[0, top, 0] - mesh.nodes[top, 0]).mean(), r.contact_force[0], fn, normal

    dx0, f0, _, _ = drag([])
    dx1, f1, fn1, normal1 = drag([Friction(0.8)])
    assert dx1 > dx0 + 1e-5  # the surface follows the probe in +x
    assert f1[0] > f0[0]  # and the probe pushes it along +x harder (friction is in the force)
    # Coulomb: the friction part of the force stays within mu times the sum of the normal
    # forces (5 % slack for the lagged normal force of the regularised law). The resultant's
    # lateral part also holds the tilted normals' lateral components, so it is no bound.
    assert fn1.sum() > 0.1
    assert np.linalg.norm(f1 - normal1) <= 0.8 * fn1.sum() * 1.05


def test_base_compliance_lets_the_bottom_move_less_as_it_stiffens():
    mesh = box_mesh(SIZE, GRID)
    bottom = mesh.bottom_nodes()

    def bottom_motion(effects):
        r = simulate(build_model(mesh, MASS, Material(5000.0), effects=effects), _poke(SIZE[:2] / 2, depth=0.007), 0.005, [1.2])
        return np.abs(r.positions[0, bottom] - mesh.nodes[bottom]).max()

    assert bottom_motion([]) == 0.0
    soft, stiff = bottom_motion([BaseCompliance(1e5)]), bottom_motion([BaseCompliance(1e6)])
    assert soft > stiff > 0.0


def test_input_side_effects_change_only_the_probe():
    mesh = box_mesh(SIZE, GRID)
    path = _poke(SIZE[:2] / 2)
    times = np.array([0.5, 1.0])
    base = simulate(build_model(mesh, MASS, Material(5000.0)), path, 0.005, times)
    shifted = simulate(build_model(mesh, MASS, Material(5000.0), effects=[TimeOffset(0.1)]), path, 0.005, times)
    np.testing.assert_allclose(shifted.probe_centres, path.at(times + 0.1))
    moved = simulate(build_model(mesh, MASS, Material(5000.0), effects=[KinematicOffset((0.001, 0, -0.002))]), path, 0.005, times)
    np.testing.assert_allclose(moved.probe_centres, base.probe_centres + [0.001, 0, -0.002])
    bigger = simulate(build_model(mesh, MASS, Material(5000.0), effects=[ProbeRadius(0.006)]), path, 0.005, times)
    # the calibration placed the centre 1 mm too low: the sphere's lowest point is unchanged
    np.testing.assert_allclose(bigger.probe_centres, base.probe_centres + [0, 0, 0.001])
    assert bigger.probe_radius == 0.006
    # same depth, wider sphere: a larger force (Hertz: F ~ sqrt(R) d^1.5) and a wider dent
    assert -bigger.contact_force[1, 2] > -base.contact_force[1, 2]
    top = mesh.top_nodes()
    ring = top[np.abs(np.linalg.norm(mesh.nodes[top, :2] - SIZE[:2] / 2, axis=1) - 0.008) < 0.004]
    sink = lambda r: float(np.mean(mesh.nodes[ring, 2] - r.positions[1, ring, 2]))
    assert sink(bigger) > sink(base) > 0


@pytest.mark.parametrize("offset", [0.137, -0.061])
def test_a_clock_offset_replays_the_same_steps_read_later(offset):
    """With a clock offset c the step grid moves with the probe, so the replay is the one
    without the offset read at the output times plus c (frames before the start at rest):
    smooth in c, which the offset's fit needs. The force, stamped by the robot's clock as
    the kinematics are, is the replay's at the robot's sample of each output time: the
    same as without the offset."""
    mesh = box_mesh(SIZE, GRID)
    path = _poke(SIZE[:2] / 2)
    times = np.arange(0.0, 1.5, 1.0 / 15.0) + 0.01
    model = lambda effects: build_model(mesh, MASS, Material(5000.0), effects=effects)
    later = simulate(model([]), path, 0.005, np.clip(times + offset, 0.0, None))
    base = simulate(model([]), path, 0.005, times)
    shifted = simulate(model([TimeOffset(offset)]), path, 0.005, times)
    assert base.ok and shifted.ok and np.abs(base.contact_force).max() > 0.05
    assert np.abs(later.positions - base.positions).max() > 1e-4  # the offset matters to the camera
    np.testing.assert_allclose(shifted.positions, later.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(shifted.contact_force, base.contact_force, rtol=0, atol=1e-9)


def test_effects_round_trip_through_their_dicts():
    for e in [Gravity(), Inclusion(), Viscoelasticity(), Friction(), BaseCompliance(), ProbeRadius(), TimeOffset(), KinematicOffset()]:
        assert effect_from_dict(e.to_dict()) == e


def test_only_a_nonzero_gravity_or_a_fixed_foundation_sets_a_scale_for_E():
    """Effect.sets_youngs_scale, which the E fit's structural identifiability asks: a body
    force of known size (any nonzero g, the default g when absent) or a foundation of fixed
    stiffness; a foundation fitted to the surface moves with E, gravity does not."""
    from core.simulation.effects import EFFECT_KINDS

    setting = {k for k, cls in EFFECT_KINDS.items() if cls.sets_youngs_scale(cls().to_dict())}
    assert setting == {"gravity", "base_compliance"}
    gravity, base = EFFECT_KINDS["gravity"], EFFECT_KINDS["base_compliance"]
    assert gravity.sets_youngs_scale({"kind": "gravity"})
    assert gravity.sets_youngs_scale({"kind": "gravity", "g": [0.0, 0.5, 0.0]})
    assert not gravity.sets_youngs_scale({"kind": "gravity", "g": [0, 0, 0]})
    assert gravity.sets_youngs_scale({"kind": "gravity"}, fitted_over_youngs=True)
    assert base.sets_youngs_scale({"kind": "base_compliance", "stiffness": 1e5})
    assert not base.sets_youngs_scale({"kind": "base_compliance", "stiffness": 1e5}, fitted_over_youngs=True)


def test_a_fitted_gravity_stays_within_its_tilt_of_straight_down():
    """The gravity fit space keeps g within MAX_TILT_DEG of -z (a phantom rests on its
    support): vectors inside the cone are kept, others go to the cone's nearest point
    (checked against a brute-force search over the cone's surface)."""
    from core.simulation.effects import EFFECT_KINDS, PhantomContext
    from core.simulation.effects.body import MAX_TILT_DEG

    space = EFFECT_KINDS["gravity"].fit_space(PhantomContext(np.array([0.07, 0.04, 0.036])))
    rng = np.random.default_rng(0)
    t = np.tan(np.radians(MAX_TILT_DEG))
    # the cone's surface (and its apex), sampled finely
    az, h = np.meshgrid(np.linspace(0, 2 * np.pi, 721), np.linspace(0, 60, 1201))
    cone = np.stack([t * h * np.cos(az), t * h * np.sin(az), -h], axis=-1).reshape(-1, 3)
    # random vectors (about 4 % of the box lies in the cone) and fixed ones on both sides:
    # straight down, a few degrees off, upwards, sideways
    fixed = np.array([[0.0, 0.0, -9.81], [0.5, -0.8, -9.81], [-2.0, 1.0, -9.0], [0.0, 0.0, 9.81], [20.0, 0.0, -5.0]])
    kept = moved = 0
    for g in np.concatenate([fixed, rng.uniform(-30, 30, (40, 3))]):
        p = space.clip(g)
        tilt = np.degrees(np.arctan2(np.hypot(p[0], p[1]), -p[2])) if np.any(p) else 0.0
        assert tilt <= MAX_TILT_DEG + 1e-6
        if np.hypot(g[0], g[1]) <= t * -g[2]:
            kept += 1
            np.testing.assert_allclose(p, g)
        else:
            moved += 1
            best = cone[np.argmin(np.linalg.norm(cone - g, axis=1))]
            assert np.linalg.norm(p - g) <= np.linalg.norm(best - g) + 1e-9
            assert np.linalg.norm(p - best) < 0.1
    assert kept >= 3 and moved >= 2
