"""Time stepping: probe contact, time-step convergence, divergence reporting."""

import numpy as np

from core.simulation import Material, ProbePath, SimulationConfig, build_model, box_mesh, simulate

SIZE = np.array([0.0687, 0.0393, 0.0358])


def _poke(depth=0.006, T=4.0, xy=(0.03, 0.02)):
    t = np.linspace(0.0, T, 401)
    d = np.interp(t, [0, 1, 2, 3, T], [-0.002, depth, depth, -0.002, -0.002])
    c = np.zeros((t.size, 3))
    c[:, 0], c[:, 1] = xy
    c[:, 2] = SIZE[2] + 0.005 - d
    return ProbePath(t, c)


def test_poke_indents_the_top_by_the_probe_depth_and_recovers():
    mesh = box_mesh(SIZE, (13, 5, 5))
    model = build_model(mesh, 0.10401, Material(5000.0, 0.44))
    out = np.array([0.0, 1.5, 3.9])
    res = simulate(model, _poke(), 0.005, out)
    assert res.ok
    top = mesh.top_nodes()
    # during the hold the surface under the probe is pushed down to the probe's depth: the
    # stiff contact lets the sphere sink ~0.1-0.2 mm, and a 6 x 10 mm triangle tangent to the
    # sphere can carry a node up to ~1 mm below its lowest point (measured: 6.93 mm for 6 mm)
    dz = res.positions[1][top, 2] - SIZE[2]
    assert -0.0075 < dz.min() < -0.0055
    # the probe pushes down: force on the phantom points to -z, order 0.1-1 N (Hertz: ~0.3 N)
    assert -1.0 < res.contact_force[1, 2] < -0.1
    # after retraction and ~1 s the dent has relaxed (stiffness damping tau = 0.1 s)
    assert np.abs(res.positions[2][top, 2] - SIZE[2]).max() < 2e-4
    assert np.abs(res.contact_force[2]).max() < 1e-6


def test_time_step_convergence():
    """Node positions at dt = 1/120 s stay within 0.1 mm of a dt = 1/480 s reference."""
    mesh = box_mesh(SIZE, (7, 3, 3))
    path = _poke(depth=0.008)
    out = np.linspace(0.1, 3.9, 20)
    ref = simulate(build_model(mesh, 0.1, Material(5000.0), SimulationConfig(dt=1 / 480, newton_iterations=2)), path, 0.005, out)
    coarse = simulate(build_model(mesh, 0.1, Material(5000.0), SimulationConfig(dt=1 / 120)), path, 0.005, out)
    err60 = simulate(build_model(mesh, 0.1, Material(5000.0), SimulationConfig(dt=1 / 60)), path, 0.005, out)
    e120 = np.abs(coarse.positions - ref.positions).max()
    e60 = np.abs(err60.positions - ref.positions).max()
    assert e120 < 1e-4
    assert e120 < e60  # first-order method: error shrinks with dt


def test_divergence_is_reported_not_raised():
    """An explicit integrator far beyond its stability limit blows up; the run ends
    with status 'diverged' and a reason, positions after it are NaN."""
    mesh = box_mesh(SIZE, (7, 3, 3))
    model = build_model(mesh, 0.1, Material(1e6), SimulationConfig(dt=1 / 60, integrator="symplectic_euler"))
    out = np.linspace(0.0, 3.0, 30)
    res = simulate(model, _poke(), 0.005, out)
    assert res.status == "diverged"
    assert "diverged at t =" in res.message
    assert np.isnan(res.positions[-1]).all()
    # the same model, implicit: fine
    ok = simulate(build_model(mesh, 0.1, Material(1e6), SimulationConfig(dt=1 / 60)), _poke(), 0.005, out)
    assert ok.ok and np.isfinite(ok.positions).all()


def test_stiff_contact_holds_without_chatter_and_barely_sinks():
    """During a hold the contact force is steady from step to step and the same at
    dt = 1/120 s and 1/960 s (the active-set contact solve; deciding contacts from the
    step's start alone alternated 0.91 N / 0 N every other step), and the sphere sinks
    less than 0.05 mm into the surface (the former 1e7 Pa/m penalty: ~0.45 mm)."""
    from core.simulation.contact import find_contacts
    from core.simulation.solver import step

    mesh = box_mesh(SIZE, (13, 5, 5))
    path = _poke(depth=0.006)
    holds = {}
    for dt in (1 / 120, 1 / 960):
        model = build_model(mesh, 0.10401, Material(5000.0, 0.44), SimulationConfig(dt=dt))
        state, prev, forces = model.initial_state(), path.at(np.array([0.0]))[0], []
        for t in np.arange(1, int(round(1.5 / dt)) + 1) * dt:
            c = path.at(np.array([t]))[0]
            state, info = step(model, state, c, 0.005, (c - prev) / dt)
            prev = c
            forces.append(info.contact_force[2])
        last = np.array(forces[-int(round(0.2 / dt)):])  # the last 0.2 s of a hold from 1.0 s
        assert last.max() - last.min() < 0.01 * abs(last.mean())
        holds[dt] = last.mean()
        pen = find_contacts(state.x, mesh.surface_triangles, c, 0.005).depth
        assert pen.size and pen.max() < 5e-5
    assert abs(holds[1 / 120] - holds[1 / 960]) < 0.02 * abs(holds[1 / 960])


def test_a_deep_press_inverts_corotational_elements_and_not_neo_hookean_ones():
    """The corotational linear law has no resistance to inversion: pressed half the box's
    height (18 mm of 36 mm) by the 5 mm sphere, the 13x5x5 replay turns elements under the
    probe inside out (measured 9 at once, in 25 of 81 frames); at 6 mm it turns none, and
    the stable neo-Hookean law turns none at 18 mm either. A diagnosis says so in its notes."""
    from types import SimpleNamespace

    from core.diagnosis.engine import inversion_notes
    from core.simulation.fem import inverted_elements

    mesh = box_mesh(SIZE, (13, 5, 5))
    out = np.linspace(0.0, 4.0, 81)
    counts = {}
    for law, depth, options in (("corotational", 0.006, {}), ("corotational", 0.018, {}),
                                ("stable_neo_hookean", 0.018, {"newton_iterations": 2})):
        model = build_model(mesh, 0.10401, Material(5000.0, 0.44, law=law), SimulationConfig(**options))
        res = simulate(model, _poke(depth), 0.005, out)
        assert res.ok
        counts[law, depth] = inverted_elements(mesh.nodes, mesh.tets, res.positions)
    assert counts["corotational", 0.006].max() == 0 and counts["stable_neo_hookean", 0.018].max() == 0
    assert counts["corotational", 0.018].max() >= 3
    assert counts["corotational", 0.018][0] == 0 and counts["corotational", 0.018][-1] == 0  # before and after the press
    # a single frame, and a diverged (NaN) frame, count none
    assert inverted_elements(mesh.nodes, mesh.tets, mesh.nodes) == 0
    assert inverted_elements(mesh.nodes, mesh.tets, np.full((1,) + mesh.nodes.shape, np.nan))[0] == 0
    runs = [SimpleNamespace(sequence="seq02", inverted=int(counts["corotational", 0.018].max())),
            SimpleNamespace(sequence="seq00", inverted=0)]
    note, = inversion_notes(runs, "corotational")
    assert "seq02" in note and "seq00" not in note and "--law stable_neo_hookean" in note
    assert inversion_notes(runs[1:], "corotational") == []
    neo, = inversion_notes(runs, "stable_neo_hookean")
    assert "seq02 (at most" in neo and "--element-size" in neo and "--law" not in neo
