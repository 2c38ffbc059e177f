"""Export a twin as a SOFA Python3 scene (``scene.py`` with ``createScene(rootNode)``).

The scene rebuilds the replay's model with SOFA components (SOFA v24.06+ names):
``EulerImplicitSolver`` with the replay's Rayleigh damping (alpha on M, beta on K, as in
:class:`core.simulation.SimulationConfig`), a ``SparseLDLSolver``, the tet mesh in a
``MechanicalObject`` + ``TetrahedronSetTopologyContainer``, ``TetrahedronFEMForceField``
with ``method="large"`` (corotational, the replay's law) and E, nu (a per-element
``youngModulus`` list when an inclusion makes elements stiffer), ``MeshMatrixMass`` with
the density (lumped: a quarter of each tet's mass per node, as the replay lumps),
``FixedProjectiveConstraint`` on the fixed base nodes, ``RestShapeSpringsForceField`` for a
compliant base (per-node stiffness = foundation stiffness x tributary area, N/m), and the
gravity of a gravity effect on the root node (zero otherwise). The probe path goes to
``probe_path.csv`` (t s, x y z m, phantom frame), read by a ``ProbeController`` that moves
a probe point; the contact itself is left to the user (a commented collision pipeline).

The scene is plain Python: it runs without SOFA up to the ``Sofa.Core`` import, so it can
be read and tested; it was never run in SOFA here (SOFA cannot be installed on this machine).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["PLUGINS", "scene_source", "write_sofa", "pick_sequence", "write_probe_path"]

PLUGINS = (
    "Sofa.Component.ODESolver.Backward",
    "Sofa.Component.LinearSolver.Direct",
    "Sofa.Component.StateContainer",
    "Sofa.Component.Topology.Container.Dynamic",
    "Sofa.Component.Mass",
    "Sofa.Component.SolidMechanics.FEM.Elastic",
    "Sofa.Component.Constraint.Projective",
    "Sofa.Component.SolidMechanics.Spring",
)
"""The SOFA plugins the scene's components live in (``RequiredPlugin`` lines)."""


def pick_sequence(twin, name: str | None = None):
    """The :class:`app.export.run.Trajectory` whose probe path an export carries:
    ``name``, else the first test sequence, else the first; None without sequences.

    Raises:
        TissueTwinError: ``name`` is not one of the twin's sequences."""
    from core.errors import TissueTwinError

    if name is not None:
        if name not in twin.sequences:
            raise TissueTwinError(f"no sequence {name!r} in {twin.source}; it has {list(twin.sequences)}")
        return twin.sequences[name]
    seqs = list(twin.sequences.values())
    return next((s for s in seqs if s.role == "test"), seqs[0] if seqs else None)


def write_probe_path(seq, path: Path) -> Path:
    """``t,x,y,z`` rows (s; m, phantom frame) of the probe sphere's centre at the sequence's frames."""
    rows = ["t,x,y,z"] + [f"{t!r},{c[0]!r},{c[1]!r},{c[2]!r}"
                          for t, c in zip(seq.times.tolist(), seq.probe_centres.tolist())]
    path.write_text("\n".join(rows) + "\n")
    return path


def _list(a, per_line: int = 1) -> str:
    """A Python list literal of ``a`` (exact floats), ``per_line`` items a line."""
    items = [repr(v) for v in np.asarray(a).tolist()]
    lines = [", ".join(items[i:i + per_line]) for i in range(0, len(items), per_line)]
    return "[\n    " + ",\n    ".join(lines) + ",\n]" if items else "[]"


_TEMPLATE = '''"""SOFA scene of a Tissue Twin calibrated twin, written by `tissuetwin export --format sofa`.

Source: {source} ({kind}); session: {session}.
Units SI (m, kg, s, Pa, N), phantom frame ({frame}, z up, bottom face at z = 0).
Model: corotational linear tetrahedral FEM (TetrahedronFEMForceField method="large"),
implicit Euler with Rayleigh damping, lumped mass, {base}.
Effects of the calibrated model: {effects}
{notes}
Not validated in SOFA by the exporter (SOFA was not installable where it was written):
open it with `runSofa scene.py` or `python -m SofaRuntime scene.py` (SofaPython3, SOFA v24.06+;
before v24.06 rename FixedProjectiveConstraint to FixedConstraint).
The replay starts from the sagged equilibrium under gravity; this scene starts from the
rest shape and sags in the first few tenths of a second.
"""

import csv
import os

HERE = os.path.dirname(os.path.abspath(__file__))

YOUNGS_MODULUS = {E!r}  # Pa, bulk
POISSON_RATIO = {nu!r}
ELEMENT_YOUNGS = {element_youngs}  # Pa per tetrahedron (None: homogeneous)
DENSITY = {density!r}  # kg/m^3 (mass {mass!r} kg)
GRAVITY = {gravity}  # m/s^2
DT = {dt!r}  # s
RAYLEIGH_MASS = {alpha!r}  # 1/s, damping alpha * M
RAYLEIGH_STIFFNESS = {beta!r}  # s, damping beta * K
PROBE_RADIUS = {radius!r}  # m, sphere
FRICTION = {friction!r}  # Coulomb coefficient of the probe contact
PROBE_PATH = {probe_path}  # t,x,y,z rows: s; m, phantom frame (None: no path)
PLUGINS = {plugins}

POSITIONS = {positions}  # m, rest shape

TETRAHEDRA = {tets}

FIXED_NODES = {fixed}

SPRING_NODES = {spring_nodes}

SPRING_STIFFNESS = {spring_stiffness}  # N/m per node, to its rest position

try:
    import Sofa.Core

    _Controller = Sofa.Core.Controller
except ImportError:  # read or tested without SOFA
    _Controller = object


def read_probe_path(path):
    """(times [s], centres [[x, y, z] m]) of probe_path.csv."""
    times, centres = [], []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            times.append(float(row["t"]))
            centres.append([float(row["x"]), float(row["y"]), float(row["z"])])
    return times, centres


def probe_centre_at(times, centres, t):
    """The probe centre at time t: linear between samples, held outside them."""
    if t <= times[0]:
        return list(centres[0])
    for k in range(1, len(times)):
        if t <= times[k]:
            w = (t - times[k - 1]) / (times[k] - times[k - 1])
            return [a + w * (b - a) for a, b in zip(centres[k - 1], centres[k])]
    return list(centres[-1])


class ProbeController(_Controller):
    """Moves the probe's MechanicalObject along probe_path.csv at every time step."""

    def __init__(self, *args, **kwargs):
        self.root = kwargs.pop("root")
        self.probe = kwargs.pop("probe")
        self.times, self.centres = kwargs.pop("path")
        if _Controller is not object:
            _Controller.__init__(self, *args, **kwargs)

    def onAnimateBeginEvent(self, event):
        t = self.times[0] + float(self.root.time.value)
        self.probe.position.value = [probe_centre_at(self.times, self.centres, t)]


def createScene(rootNode):
    for plugin in PLUGINS:
        rootNode.addObject("RequiredPlugin", name=plugin)
    rootNode.gravity = GRAVITY
    rootNode.dt = DT
    rootNode.addObject("DefaultAnimationLoop")

    tissue = rootNode.addChild("Tissue")
    tissue.addObject("EulerImplicitSolver", name="odesolver", rayleighMass=RAYLEIGH_MASS,
                     rayleighStiffness=RAYLEIGH_STIFFNESS)
    tissue.addObject("SparseLDLSolver", name="linearsolver", template="CompressedRowSparseMatrixMat3x3d")
    tissue.addObject("MechanicalObject", name="dofs", template="Vec3d", position=POSITIONS)
    tissue.addObject("TetrahedronSetTopologyContainer", name="topology", position=POSITIONS,
                     tetrahedra=TETRAHEDRA)
    tissue.addObject("TetrahedronSetGeometryAlgorithms", name="geometry", template="Vec3d")
    tissue.addObject("MeshMatrixMass", name="mass", massDensity=DENSITY, lumping=True)
    tissue.addObject("TetrahedronFEMForceField", name="fem", method="large",
                     youngModulus=ELEMENT_YOUNGS if ELEMENT_YOUNGS is not None else YOUNGS_MODULUS,
                     poissonRatio=POISSON_RATIO)
    if FIXED_NODES:
        tissue.addObject("FixedProjectiveConstraint", name="fixed_base", indices=FIXED_NODES)
    if SPRING_NODES:
        tissue.addObject("RestShapeSpringsForceField", name="base_springs", points=SPRING_NODES,
                         stiffness=SPRING_STIFFNESS)

    if PROBE_PATH is not None:
        path = read_probe_path(os.path.join(HERE, PROBE_PATH))
        probe = rootNode.addChild("Probe")
        centre = probe.addObject("MechanicalObject", name="centre", template="Vec3d", position=[path[1][0]])
        # Contact (the replay: a frictionless, or Coulomb FRICTION, sphere of PROBE_RADIUS pressing
        # on the surface) is left to the user, e.g. a collision pipeline with
        #   rootNode.addObject("CollisionPipeline"); rootNode.addObject("BruteForceBroadPhase")
        #   rootNode.addObject("BVHNarrowPhase"); rootNode.addObject("MinProximityIntersection", ...)
        #   rootNode.addObject("CollisionResponse", response="PenalityContactForceField")
        #   probe.addObject("SphereCollisionModel", radius=PROBE_RADIUS) and a TriangleCollisionModel
        #   on the tissue's surface.
        rootNode.addObject(ProbeController(name="probe_controller", root=rootNode, probe=centre, path=path))
    return rootNode
'''


def scene_source(twin, probe_path: str | None = "probe_path.csv") -> str:
    """The text of ``scene.py`` for ``twin`` (``probe_path``: the CSV beside it, or None)."""
    scale = np.asarray(twin.element_youngs, dtype=np.float64)
    heterogeneous = bool(np.ptp(scale) > 1e-12 * scale.max())
    springs = np.flatnonzero(twin.support_stiffness > 0)
    kinds = [e["kind"] for e in twin.effects]
    base = ("bottom nodes on springs (base_compliance)" if springs.size else "bottom nodes fixed")
    notes = "".join(f"Note: {n}.\n" for n in twin.notes)
    return _TEMPLATE.format(
        source=twin.source, kind=twin.kind, session=twin.session, base=base,
        frame="box [0, size]" if twin.grid is not None else "of phantom.stl",
        effects=", ".join(kinds) if kinds else "none (the paper's base model)", notes=notes,
        E=float(twin.youngs_modulus), nu=float(twin.poisson_ratio),
        element_youngs=_list(scale, 6) if heterogeneous else "None",
        density=float(twin.density), mass=float(twin.mass), gravity=repr([float(v) for v in twin.gravity]),
        dt=float(twin.dt), alpha=float(twin.rayleigh_mass), beta=float(twin.rayleigh_stiffness),
        radius=float(twin.probe_radius), friction=float(twin.friction),
        probe_path=repr(probe_path), plugins=_list(list(PLUGINS)),
        positions=_list(np.asarray(twin.mesh.nodes, dtype=np.float64)),
        tets=_list(np.asarray(twin.mesh.tets, dtype=np.int64), 4),
        fixed=_list(np.flatnonzero(twin.fixed).astype(np.int64), 16),
        spring_nodes=_list(springs.astype(np.int64), 16),
        spring_stiffness=_list(twin.support_stiffness[springs], 6),
    )


def write_sofa(twin, out, *, sequence: str | None = None) -> list[Path]:
    """Write ``scene.py`` and, when the twin has a probe path, ``probe_path.csv``.

    Args:
        twin: an :class:`app.export.run.Twin`.
        out: folder (created).
        sequence: whose probe path (default: the first test sequence, else the first).

    Returns:
        The files written.

    Raises:
        TissueTwinError: an unknown sequence.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seq = pick_sequence(twin, sequence)
    written = []
    if seq is not None:
        written.append(write_probe_path(seq, out / "probe_path.csv"))
    scene = out / "scene.py"
    scene.write_text(scene_source(twin, "probe_path.csv" if seq is not None else None))
    return [scene] + written
