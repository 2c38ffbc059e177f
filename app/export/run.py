"""Read a run folder of the project's own commands into a :class:`Twin`: the calibrated
model (mesh, material, supports, body forces, effects) and, for a replay, its node
trajectories.

Two kinds of RUN are understood:

- a **replay** (``tissuetwin replay``, :func:`core.simulation.replay.write_replay`):
  ``replay.json`` gives E, Poisson's ratio, the grid, the effects and the session;
  ``<sequence>.npz`` the node trajectories, probe centres, forces and per-frame errors
  (and, for a phantom given by ``phantom.stl``, the replayed mesh itself);
- a **diagnosis** (``tissuetwin diagnose``, ``diagnosis.json`` of ``SESSION_FORMAT.md``):
  the calibrated model is the base model plus ``extended.effects`` at the reported
  Young's modulus; it has no trajectories, and its probe paths are the sessions'
  kinematics through the robot calibration (corner touches) and the claimed input effects.

The mesh is the replay's own: :func:`core.simulation.mesh.box_mesh` of the session's
phantom size and the grid for a box; for an STL phantom the Gmsh mesh the replay stored in
its npz (``rest_nodes``, ``tets``; :func:`app.run_mesh.npz_mesh`), and for a diagnosis of
one :func:`core.simulation.meshing.phantom_mesh` of the session's ``phantom.stl`` at the
default element size (the grid does not apply). The fixed nodes, supports, per-element moduli and body
forces come from the effects' own ``configure`` hooks on a
:class:`core.simulation.model.ModelBuilder`, so every exporter sees exactly the model the
replay simulates. All quantities SI, phantom frame (box ``[0, size]`` or the STL's frame,
z up, bottom at z = 0).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from core.errors import TissueTwinError

__all__ = ["Trajectory", "Twin", "build_twin", "load_run"]

NPZ_KEYS = ("times", "positions", "frame_errors", "probe_centres", "contact_force", "grid")
"""Arrays of a replay's ``<sequence>.npz`` (:func:`core.simulation.replay.write_replay`)."""

UNSUPPORTED = {
    "viscoelasticity": "viscoelasticity (standard linear solid) has no counterpart in the exported "
                       "elastic force field; exported as purely elastic",
}
"""Effect kinds no exporter represents, with the note printed when a twin carries one."""


@dataclass(frozen=True)
class Trajectory:
    """One sequence of a run.

    Attributes:
        name, role: the sequence's name and role (train, validation, test).
        times: (F,) s, camera frame times.
        probe_centres: (F, 3) m, phantom frame, the probe sphere's centre the model saw
            (input effects applied).
        positions: (F, N, 3) m, phantom frame, node positions (None for a diagnosis;
            NaN rows after a divergence).
        frame_errors: (F,) m, mean cloud-to-mesh distance per frame, or None.
        contact_force: (F, 3) N, force of the probe on the phantom, phantom frame, or None.
    """

    name: str
    role: str
    times: np.ndarray
    probe_centres: np.ndarray
    positions: np.ndarray | None = None
    frame_errors: np.ndarray | None = None
    contact_force: np.ndarray | None = None


@dataclass(frozen=True)
class Twin:
    """The calibrated twin in exporter-neutral form (SI units, phantom frame).

    Attributes:
        kind: "replay", "diagnosis" or "parameters" (built by :func:`build_twin`).
        source: the RUN folder (None for "parameters").
        session: the session folder the run replayed (None if unknown).
        mesh: the :class:`core.simulation.mesh.TetMesh` (rest shape; ``grid`` None for an
            STL phantom's mesh).
        mass: phantom mass, kg. density: mass / mesh volume, kg/m^3.
        youngs_modulus: bulk E, Pa. poisson_ratio: nu.
        element_youngs: (E,) Pa, each element's modulus (an inclusion raises some).
        node_mass: (N,) kg, lumped (a quarter of each tet's mass to each of its nodes).
        fixed: (N,) bool, nodes held at rest. support_stiffness: (N,) N/m springs to rest.
        gravity: (3,) m/s^2, the sum of the gravity effects (zero without one).
        friction: Coulomb coefficient of the probe contact.
        probe_radius: m, after any probe_radius effect.
        rayleigh_mass: 1/s, rayleigh_stiffness: s, dt: s (the replay's numerics).
        effects: the effect dicts ``{"kind": ..., **parameters}`` of the model.
        notes: what an export cannot represent (printed by the CLI).
        sequences: {name: :class:`Trajectory`}.
        youngs_source: where E came from (for twin.json).
    """

    kind: str
    source: Path | None
    session: Path | None
    mesh: object
    mass: float
    density: float
    youngs_modulus: float
    poisson_ratio: float
    element_youngs: np.ndarray
    node_mass: np.ndarray
    fixed: np.ndarray
    support_stiffness: np.ndarray
    gravity: np.ndarray
    friction: float
    probe_radius: float
    rayleigh_mass: float
    rayleigh_stiffness: float
    dt: float
    effects: tuple
    notes: tuple = ()
    sequences: dict = field(default_factory=dict)
    youngs_source: str = ""

    @property
    def grid(self) -> tuple[int, int, int] | None:
        """(nx, ny, nz) of a box grid, None for an STL phantom's mesh."""
        return None if self.mesh.grid is None else tuple(self.mesh.grid)

    def effect_objects(self) -> list:
        from core.simulation import effect_from_dict

        return [effect_from_dict(e) for e in self.effects]

    def static_positions(self) -> np.ndarray:
        """(N, 3) m: the model's quasi-static equilibrium under its body forces and
        supports (:func:`core.simulation.static_equilibrium`), the rest shape without them.

        Raises:
            SimulationError: the phantom collapses (far too soft for its weight)."""
        from core.simulation import Material, SimulationConfig, build_model, static_equilibrium

        if not np.any(self.gravity):
            return np.array(self.mesh.nodes, dtype=np.float64)
        model = build_model(self.mesh, self.mass, Material(self.youngs_modulus, self.poisson_ratio),
                            SimulationConfig(dt=self.dt, rayleigh_mass=self.rayleigh_mass,
                                             rayleigh_stiffness=self.rayleigh_stiffness),
                            self.effect_objects(), factorize=False)
        return static_equilibrium(model)[0].x

    def describe(self) -> dict:
        """The twin's parameters as JSON (``twin.json`` beside every export)."""
        return {
            "format": "tissuetwin-export/1",
            "kind": self.kind,
            "source": None if self.source is None else str(self.source),
            "session": None if self.session is None else str(self.session),
            "frame": "phantom frame, m, z up, bottom face at z = 0",
            "grid": None if self.grid is None else list(self.grid),
            **({} if self.grid is not None else {"mesh": {"kind": "stl", "mesher": "gmsh"}}),
            "nodes": int(self.mesh.n_nodes), "tetrahedra": int(self.mesh.n_tets),
            "size_m": [float(v) for v in self.mesh.size],
            "youngs_modulus_pa": self.youngs_modulus, "youngs_modulus_from": self.youngs_source,
            "element_youngs_range_pa": [float(self.element_youngs.min()), float(self.element_youngs.max())],
            "poisson_ratio": self.poisson_ratio, "mass_kg": self.mass, "density_kg_m3": self.density,
            "gravity_m_s2": [float(v) for v in self.gravity],
            "fixed_nodes": int(self.fixed.sum()), "supported_nodes": int((self.support_stiffness > 0).sum()),
            "friction": self.friction, "probe_radius_m": self.probe_radius,
            "rayleigh_mass_per_s": self.rayleigh_mass, "rayleigh_stiffness_s": self.rayleigh_stiffness, "dt_s": self.dt,
            "effects": list(self.effects), "notes": list(self.notes),
            "sequences": {n: {"role": s.role, "frames": int(s.times.size), "trajectories": s.positions is not None}
                          for n, s in self.sequences.items()},
        }


def build_twin(size, mass: float, youngs_modulus: float, poisson_ratio: float = 0.44, grid=(13, 5, 5),
               effects=(), *, probe_radius: float = 0.005, sequences: dict | None = None, kind: str = "parameters",
               source: Path | None = None, session: Path | None = None, youngs_source: str = "given",
               mesh=None) -> Twin:
    """The twin of a phantom from its parameters: a box, or any ``mesh``.

    Args:
        size: (3,) box size, m. mass: kg. youngs_modulus: Pa. poisson_ratio: nu.
        grid: (nx, ny, nz) nodes (the replay's mesh, :func:`core.simulation.box_mesh`).
        mesh: the :class:`core.simulation.mesh.TetMesh` to use instead of the box of
            ``size`` and ``grid`` (an STL phantom's), or None.
        effects: effect dicts of ``SESSION_FORMAT.md`` (or :class:`core.simulation.Effect`).
        probe_radius: the session's radius, m (a probe_radius effect overrides it).
        sequences: {name: :class:`Trajectory`}.

    Raises:
        TissueTwinError: (SimulationError) bad size, grid, material or effect.
    """
    from core.simulation import Effect, Material, SimulationConfig, box_mesh, effect_from_dict
    from core.simulation.model import ModelBuilder

    objs = [e if isinstance(e, Effect) else effect_from_dict(e) for e in effects]
    mesh = box_mesh(size, grid) if mesh is None else mesh
    Material(youngs_modulus, poisson_ratio)  # validates E and nu
    builder = ModelBuilder(mesh, float(mass))
    for e in objs:
        e.configure(builder)
    gravity = np.zeros(3)
    radius = float(probe_radius)
    for e in objs:
        if e.kind == "gravity":
            gravity += np.asarray(e.g, dtype=np.float64)
        if e.kind == "probe_radius":
            radius = float(e.radius)
    sim = SimulationConfig()
    notes = tuple(UNSUPPORTED[e.kind] for e in objs if e.kind in UNSUPPORTED)
    return Twin(
        kind=kind, source=source, session=session, mesh=mesh, mass=float(mass),
        density=float(builder.density), youngs_modulus=float(youngs_modulus), poisson_ratio=float(poisson_ratio),
        element_youngs=float(youngs_modulus) * np.asarray(builder.element_scale, dtype=np.float64),
        node_mass=np.asarray(builder.node_mass, dtype=np.float64), fixed=np.asarray(builder.fixed, dtype=bool),
        support_stiffness=np.asarray(builder.support_stiffness, dtype=np.float64), gravity=gravity,
        friction=float(builder.friction), probe_radius=radius, rayleigh_mass=sim.rayleigh_mass,
        rayleigh_stiffness=sim.rayleigh_stiffness, dt=sim.dt, effects=tuple(e.to_dict() for e in objs),
        notes=notes, sequences=dict(sequences or {}), youngs_source=youngs_source,
    )


def load_run(run, *, youngs: float | None = None, poisson: float | None = None, grid=None,
             session=None, sequences=None) -> Twin:
    """The calibrated twin of a replay or diagnosis folder.

    Args:
        run: a folder with ``replay.json`` (and its ``<sequence>.npz``) or ``diagnosis.json``
            (or the path of either file).
        youngs, poisson, grid: override E (Pa), nu and the node grid (a replay's npz
            trajectories need its own grid; an STL phantom has no grid and ignores a
            diagnosis's).
        session: the session folder, when the one the run names has moved.
        sequences: names to keep (default all).

    Raises:
        TissueTwinError: no such folder, neither file in it, a malformed JSON or npz
            (the file is named), a missing session, an unknown sequence, or a diagnosis
            that reports no Young's modulus (give ``youngs``).
    """
    path = Path(run)
    if path.is_file() and path.name in ("replay.json", "diagnosis.json"):
        path = path.parent
    if not path.is_dir():
        raise TissueTwinError(f"{path}: no such run folder (expected a folder with replay.json or diagnosis.json)")
    if (path / "replay.json").is_file():
        return _load_replay(path, youngs, poisson, grid, session, sequences)
    if (path / "diagnosis.json").is_file():
        return _load_diagnosis(path, youngs, poisson, grid, session, sequences)
    raise TissueTwinError(f"{path}: neither replay.json nor diagnosis.json is there; export needs the folder "
                          f"written by `tissuetwin replay` or `tissuetwin diagnose`")


def _read_json(p: Path) -> dict:
    try:
        data = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise TissueTwinError(f"{p}: not readable JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise TissueTwinError(f"{p}: expected a JSON object")
    return data


def _session_of(p: Path, data: dict, given):
    """(Session, folder): ``given``, else the JSON's ``session`` as written, else relative to the run."""
    from core.io import read_session

    if given is not None:
        candidates = [Path(given)]
    else:
        if not isinstance(data.get("session"), str):
            raise TissueTwinError(f"{p}: has no 'session' path; give the session folder (--session)")
        s = Path(data["session"])
        candidates = [s] if s.is_absolute() else [s, p.parent / s]
    for c in candidates:
        if (c / "session.json").is_file():
            return read_session(c), c
    raise TissueTwinError(f"{p}: its session {candidates[0]} is not there (no session.json); "
                          f"give the session folder (--session)")


def _selected(p: Path, names: list[str], wanted) -> list[str]:
    if wanted is None:
        return names
    unknown = [n for n in wanted if n not in names]
    if unknown:
        raise TissueTwinError(f"{p}: no sequence(s) {unknown}; it has {names}")
    return [n for n in names if n in wanted]


def _load_replay(folder: Path, youngs, poisson, grid, session, wanted) -> Twin:
    p = folder / "replay.json"
    data = _read_json(p)
    try:
        E = float(youngs if youngs is not None else data["youngs_modulus"])
        nu = float(poisson if poisson is not None else data["poisson_ratio"])
        run_grid = tuple(int(g) for g in data["grid"])
        effects = list(data.get("effects") or [])
        seqs = dict(data["sequences"])
        stl = (data.get("mesh") or {}).get("kind") == "stl"
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise TissueTwinError(f"{p}: not a replay.json of `tissuetwin replay` ({exc!r} missing or malformed)") from exc
    if stl and grid is not None:
        raise TissueTwinError(f"{p}: the replay's phantom is given by phantom.stl (an unstructured mesh); --grid "
                              f"{tuple(grid)} applies to box phantoms only")
    if grid is not None and tuple(grid) != run_grid:
        raise TissueTwinError(f"{p}: the replay's trajectories are on the {run_grid} grid; --grid {tuple(grid)} "
                              f"cannot be used with them")
    sess, sess_path = _session_of(p, data, session)
    meta = sess.meta
    mesh = _replay_stl_mesh(folder, p, data, list(seqs), sess) if stl else None
    trajectories = {}
    n_nodes = run_grid[0] * run_grid[1] * run_grid[2] if mesh is None else mesh.n_nodes
    for name in _selected(p, list(seqs), wanted):
        trajectories[name] = _read_npz(folder / f"{name}.npz", str(seqs[name].get("role", "")), n_nodes)
    return build_twin(meta.phantom.size, meta.phantom.mass, E, nu, run_grid, effects,
                      probe_radius=meta.probe.radius, sequences=trajectories, kind="replay", source=folder,
                      session=sess_path, youngs_source="--youngs" if youngs is not None else "replay.json", mesh=mesh)


def _replay_stl_mesh(folder: Path, p: Path, data: dict, names: list[str], sess):
    """The mesh an STL phantom's replay ran on: stored in its first sequence's npz
    (:func:`app.run_mesh.npz_mesh`), else (an npz without it) the session's
    ``phantom.stl`` meshed again at the replay's element size, which must give the node
    count ``replay.json`` states."""
    from app.run_mesh import npz_mesh
    from core.simulation.meshing import phantom_mesh

    info = data.get("mesh") or {}
    for name in names[:1]:
        f = folder / f"{name}.npz"
        try:
            with np.load(f) as z:
                mesh = npz_mesh(z, f)
        except (OSError, ValueError) as exc:
            raise TissueTwinError(f"{f}: not a readable npz of `tissuetwin replay` ({exc})") from exc
        if mesh is not None:
            return mesh
    if sess.phantom_stl is None:
        raise TissueTwinError(f"{p}: replayed an STL phantom, but its npz files hold no mesh and its session "
                              f"{sess.path} has no phantom.stl")
    mesh = phantom_mesh(sess.meta.phantom.size, sess.phantom_stl, element_size=info.get("element_size"))
    if info.get("nodes") is not None and int(info["nodes"]) != mesh.n_nodes:
        raise TissueTwinError(f"{p}: replayed a {info['nodes']}-node mesh; {sess.phantom_stl} meshes to "
                              f"{mesh.n_nodes} nodes now (the STL or the mesher changed)")
    return mesh


def _read_npz(f: Path, role: str, n_nodes: int) -> Trajectory:
    try:
        with np.load(f) as z:
            missing = [k for k in NPZ_KEYS if k not in z.files]
            if missing:
                raise TissueTwinError(f"{f}: missing array(s) {missing} of a replay's trajectories")
            arrays = {k: np.asarray(z[k]) for k in NPZ_KEYS}
    except TissueTwinError:
        raise
    except (OSError, ValueError) as exc:
        raise TissueTwinError(f"{f}: not a readable npz of `tissuetwin replay` ({exc})") from exc
    t, x = arrays["times"].astype(np.float64), arrays["positions"].astype(np.float64)
    F = t.size
    if x.shape != (F, n_nodes, 3):
        raise TissueTwinError(f"{f}: positions are {x.shape}, expected ({F}, {n_nodes}, 3) for the replay's mesh")
    return Trajectory(name=f.stem, role=role, times=t, positions=x,
                      frame_errors=arrays["frame_errors"].astype(np.float64).reshape(F),
                      probe_centres=arrays["probe_centres"].astype(np.float64).reshape(F, 3),
                      contact_force=arrays["contact_force"].astype(np.float64).reshape(F, 3))


def _diagnosis_youngs(p: Path, data: dict, grid) -> tuple[float, str]:
    """E (Pa) of the calibrated model and where it came from: the value a fit reported on
    this very grid (``grid_value`` or ``refined_value``) when there is one; on the
    diagnosis's default grid (13x5x5), the E its claimed causes were fitted and evaluated
    with (``replay_grid_value_used``: a gravity fitted there goes with that E, the sag being
    set by rho g / E); else the reported ``value``, else that one."""
    from core.diagnosis import DiagnosisConfig

    y = data.get("youngs_modulus")
    if not isinstance(y, dict):
        raise TissueTwinError(f"{p}: has no youngs_modulus object")
    for key in ("grid_value", "refined_value"):
        g = y.get(key)
        if isinstance(g, dict) and g.get("value") and tuple(g.get("grid") or ()) == tuple(grid):
            return float(g["value"]), f"diagnosis.json youngs_modulus.{key} (fitted on this grid)"
    used = y.get("replay_grid_value_used")
    if tuple(grid) == tuple(DiagnosisConfig().grid) and isinstance(used, (int, float)) and used > 0:
        return float(used), "diagnosis.json youngs_modulus.replay_grid_value_used (its causes' E on this grid)"
    for key in ("value", "replay_grid_value_used"):
        if isinstance(y.get(key), (int, float)) and y[key] > 0:
            return float(y[key]), f"diagnosis.json youngs_modulus.{key}"
    raise TissueTwinError(f"{p}: reports no Young's modulus ({y.get('reason') or 'value is null'}); give one with --youngs")


def _load_diagnosis(folder: Path, youngs, poisson, grid, session, wanted) -> Twin:
    from core.simulation.replay import ReplayConfig

    p = folder / "diagnosis.json"
    data = _read_json(p)
    if data.get("format") != "tissue-diagnosis/1":
        raise TissueTwinError(f"{p}: format is {data.get('format')!r}, expected 'tissue-diagnosis/1'")
    defaults = ReplayConfig()
    use_grid = tuple(int(g) for g in grid) if grid is not None else defaults.grid
    if youngs is not None:
        E, source = float(youngs), "--youngs"
    else:
        E, source = _diagnosis_youngs(p, data, use_grid)
    ext = data.get("extended") or {}
    effects = ext.get("effects")
    if effects is None:  # a diagnosis.json of another tool: the claimed causes' parameters
        effects = [{"kind": c["kind"], **(c.get("parameters") or {})} for c in data.get("causes") or []]
    if not isinstance(effects, list) or not all(isinstance(e, dict) and "kind" in e for e in effects):
        raise TissueTwinError(f"{p}: extended.effects must be a list of effect objects with a 'kind'")
    sess, sess_path = _session_of(p, data, session)
    meta = sess.meta
    mesh = None
    if sess.phantom_stl is not None:  # the diagnosis replayed the STL's mesh at its default element size
        from core.simulation.meshing import phantom_mesh

        mesh = phantom_mesh(meta.phantom.size, sess.phantom_stl)
    twin = build_twin(meta.phantom.size, meta.phantom.mass, E, poisson if poisson is not None else defaults.poisson_ratio,
                      use_grid, effects, probe_radius=meta.probe.radius, kind="diagnosis", source=folder,
                      session=sess_path, youngs_source=source, mesh=mesh)
    paths = _calibrated_paths(sess, twin, _selected(p, list(sess.sequences), wanted), defaults.path_smoothing)
    return replace(twin, sequences=paths)


def _calibrated_paths(sess, twin: Twin, names: list[str], smoothing: float) -> dict:
    """{name: Trajectory} of the probe centres at the camera frames: the kinematics
    through the robot calibration (Kabsch on the corner touches, or on the landmark
    touches when the session has them), smoothed as a replay does, with the twin's input
    effects (time, kinematic and radius offsets) applied."""
    from core.preparation.probe import ProbePath
    from core.registration import calibrate_robot

    meta = sess.meta
    if sess.landmark_touches is not None:
        from core.preparation import calibrate_robot_on_landmarks

        T = calibrate_robot_on_landmarks(sess).T
    else:
        T = calibrate_robot(sess.corners, meta.phantom.size, meta.probe.radius).T
    out = {}
    for name in names:
        seq = sess.sequences[name]
        kin = seq.kinematics
        path = ProbePath(kin.t, kin.position @ T[:3, :3].T + T[:3, 3]).smoothed(smoothing)
        radius = float(meta.probe.radius)
        for e in twin.effect_objects():
            path, radius = e.transform_probe(path, radius)
        t = np.asarray(seq.frames.t, dtype=np.float64)
        out[name] = Trajectory(name=name, role=seq.role, times=t, probe_centres=path.at(t))
    return out
