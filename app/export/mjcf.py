"""Export a twin as a MuJoCo model (MJCF XML, MuJoCo >= 3.3 with 3D flex elasticity; written
and tested against mujoco 4.0).

The tet mesh becomes a ``dim="3"`` flex under ``<deformable>``: every free node is a body
with the replay's lumped node mass and three slide joints (MuJoCo's fast path for flex
elasticity), every fixed node a vertex of the world body (pinned); a compliant base
(base_compliance) gives its nodes' joints the spring stiffness to rest (N/m). Elasticity
is ``<elasticity young poisson damping>``: E, nu and the replay's Rayleigh beta (s).
MuJoCo's 3D flex elasticity is Saint Venant-Kirchhoff on the same linear tetrahedra,
which equals our corotational law for small strains and is softer in compression as the
strain grows (measured on a gravity sag, see the tests and the README). The Rayleigh
alpha on the mass has no counterpart (MuJoCo refuses joint damping on flex vertex
bodies); it is left out. An inclusion's per-element moduli are grouped into at most
``max_groups`` flexes of one modulus each, sharing the node bodies. The integrator is
``discrete`` (implicit in position; required for flex elasticity) at the replay's time
step, gravity from a gravity effect (zero otherwise). The probe is a mocap sphere at the
path's first centre; ``probe_path.csv`` (t s, x y z m) drives it via ``data.mocap_pos``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["element_groups", "mjcf_xml", "node_positions", "write_mjcf"]

SOLIMP = "0.99 0.999 0.001"
"""Contact impedance of the flex and the probe (MuJoCo ``solimp``)."""


def element_groups(element_youngs: np.ndarray, bulk: float, max_groups: int = 8) -> list[tuple[float, np.ndarray]]:
    """Split elements into groups of one modulus: [(E Pa, element indices)], bulk first.

    Elements exactly at ``bulk`` form one group; the others are binned on a log scale
    into at most ``max_groups - 1`` groups, each at the mean modulus of its elements
    (a homogeneous twin gives one group)."""
    E = np.asarray(element_youngs, dtype=np.float64)
    at_bulk = np.isclose(E, bulk, rtol=1e-12, atol=0.0)
    groups = [(float(bulk), np.flatnonzero(at_bulk))] if np.any(at_bulk) else []
    rest = np.flatnonzero(~at_bulk)
    if rest.size:
        values = np.unique(E[rest])
        if values.size <= max_groups - 1:
            groups += [(float(v), rest[E[rest] == v]) for v in values]
        else:
            edges = np.linspace(np.log(E[rest].min()), np.log(E[rest].max()), max_groups)
            bins = np.clip(np.digitize(np.log(E[rest]), edges[1:-1]), 0, max_groups - 2)
            groups += [(float(E[rest[bins == b]].mean()), rest[bins == b]) for b in np.unique(bins)]
    return groups


def _f(v) -> str:
    return repr(float(v))


def _v(a) -> str:
    return " ".join(_f(x) for x in np.asarray(a, dtype=np.float64).reshape(-1))


def mjcf_xml(twin, *, probe_centre=None, max_groups: int = 8, timestep: float | None = None) -> str:
    """The MJCF text of ``twin``.

    Args:
        twin: an :class:`app.export.run.Twin`.
        probe_centre: (3,) m, where the probe sphere (a mocap body) starts; None: no probe.
        max_groups: most flexes an inclusion's per-element moduli are grouped into.
        timestep: s (default: the replay's).
    """
    mesh = twin.mesh
    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    fixed = np.asarray(twin.fixed, dtype=bool)
    k = np.asarray(twin.support_stiffness, dtype=np.float64)
    bodies, names, verts = [], [], []
    for i, p in enumerate(nodes):
        if fixed[i]:
            names.append("world")
            verts.append(_v(p))
            continue
        names.append(f"node{i}")
        verts.append("0 0 0")
        m = float(twin.node_mass[i])
        spring = f' stiffness="{_f(k[i])}" springref="0"' if k[i] > 0 else ""
        joints = "".join(f'<joint name="node{i}_{a}" type="slide" axis="{ax}"{spring}/>'
                         for a, ax in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1")))
        inertia = _f(max(m, 1e-12) * 1e-6)
        bodies.append(f'    <body name="node{i}" pos="{_v(p)}"><inertial pos="0 0 0" mass="{_f(m)}" '
                      f'diaginertia="{inertia} {inertia} {inertia}"/>{joints}</body>')
    groups = element_groups(twin.element_youngs, twin.youngs_modulus, max_groups)
    friction = float(twin.friction)
    # a stiff contact, a steel probe on a gel: with MuJoCo's default solimp (0.9-0.95) a 5 mm
    # press on the 13x5x5 mesh dented the node under it by 3.2 mm, with these by 5.1 mm
    # on both sides: MuJoCo takes the larger condim and friction of the two (a geom's default is 1)
    coulomb = (f'condim="3" friction="{_f(friction)} 0.005 0.0001"' if friction > 0 else 'condim="1" friction="0 0 0"')
    contact = f'<contact contype="1" conaffinity="2" selfcollide="none" solimp="{SOLIMP}" {coulomb}/>'
    flexes = []
    for g, (E, elems) in enumerate(groups):
        name = "tissue" if g == 0 else f"tissue_E{g}"
        tets = np.asarray(mesh.tets)[elems]
        used, local = np.unique(tets, return_inverse=True)  # this flex's nodes, and its tets in their numbering
        elem = " ".join(str(int(v)) for v in local.ravel())
        flexes.append(
            f'    <flex name="{name}" dim="3" radius="0" body="{" ".join(names[i] for i in used)}"\n'
            f'          vertex="{" ".join(verts[i] for i in used)}"\n          element="{elem}">\n'
            f'      <elasticity young="{_f(E)}" poisson="{_f(twin.poisson_ratio)}" damping="{_f(twin.rayleigh_stiffness)}"/>\n'
            f'      {contact}\n    </flex>')
    probe = ""
    if probe_centre is not None:
        probe = (f'    <body name="probe" mocap="true" pos="{_v(probe_centre)}">'
                 f'<geom name="probe" type="sphere" size="{_f(twin.probe_radius)}" contype="2" conaffinity="1" '
                 f'solimp="{SOLIMP}" {coulomb} rgba="0.7 0.7 0.75 1"/></body>\n')
    spread = "" if len(groups) <= 1 else (
        f"\n  Inclusion: {len(groups)} flexes of one modulus each ({', '.join(f'{E:.4g}' for E, _ in groups)} Pa), "
        f"from per-element moduli {twin.element_youngs.min():.4g}-{twin.element_youngs.max():.4g} Pa.")
    notes = "".join(f"\n  Note: {n}." for n in twin.notes)
    dt = float(timestep if timestep is not None else twin.dt)
    kinds = ", ".join(e["kind"] for e in twin.effects) or "none"
    comment = f"""Tissue Twin calibrated twin, written by tissuetwin export (format mjcf).
  Source: {twin.source} ({twin.kind}); session: {twin.session}.
  SI units, phantom frame ({'box [0, size]' if twin.grid is not None else 'of phantom.stl'}, z up, bottom at z = 0). Effects: {kinds}.
  E {twin.youngs_modulus:.6g} Pa, nu {twin.poisson_ratio:.4g}, density {twin.density:.6g} kg/m^3, mass {twin.mass:.6g} kg;
  lumped node masses as in the replay; Rayleigh beta {twin.rayleigh_stiffness:g} s as flex damping
  (alpha {twin.rayleigh_mass:g} 1/s has no MuJoCo counterpart on flex vertex bodies).
  3D flex elasticity is Saint Venant-Kirchhoff: the replay's corotational law for small strains.{spread}{notes}
  Probe: the mocap body "probe"; move it along probe_path.csv with data.mocap_pos[0] = centre(t)."""
    comment = comment.replace("--", "- -")  # "--" may not appear in an XML comment
    return f"""<mujoco model="tissuetwin">
<!-- {comment} -->
  <option timestep="{_f(dt)}" gravity="{_v(twin.gravity)}" integrator="discrete" solver="Newton"
          iterations="200" tolerance="1e-7"/>
  <worldbody>
{chr(10).join(bodies)}
{probe}  </worldbody>
  <deformable>
{chr(10).join(flexes)}
  </deformable>
</mujoco>
"""


def write_mjcf(twin, out, *, sequence: str | None = None, max_groups: int = 8) -> list[Path]:
    """Write ``twin.xml`` and, when the twin has a probe path, ``probe_path.csv``.

    Args:
        twin: an :class:`app.export.run.Twin`.
        out: folder (created).
        sequence: whose probe path (default: the first test sequence, else the first).
        max_groups: see :func:`mjcf_xml`.

    Returns:
        The files written.

    Raises:
        TissueTwinError: an unknown sequence.
    """
    from app.export.sofa import pick_sequence, write_probe_path

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seq = pick_sequence(twin, sequence)
    written = [out / "twin.xml"]
    written[0].write_text(mjcf_xml(twin, probe_centre=None if seq is None else seq.probe_centres[0],
                                   max_groups=max_groups))
    if seq is not None:
        written.append(write_probe_path(seq, out / "probe_path.csv"))
    return written


def node_positions(model, data, twin) -> np.ndarray:
    """(N, 3) m, phantom frame: the twin's node positions in a MuJoCo state of
    :func:`mjcf_xml`'s model (free nodes are the bodies ``node<i>``, fixed ones stay at rest)."""
    import mujoco

    x = np.array(twin.mesh.nodes, dtype=np.float64)
    for i in np.flatnonzero(~np.asarray(twin.fixed, dtype=bool)):
        x[i] = data.xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"node{i}")]
    return x
