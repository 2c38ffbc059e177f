"""The virtual lab's truth simulation: the finer, hyperelastic FEM that deforms the phantom.

This module holds one truth simulation as a picklable job (:class:`SimJob`, so that it
can run in a worker process), the truth's mesh (:func:`truth_mesh`), its model (built
once per process and cached in :data:`MODEL_CACHE`), the run itself (:func:`run_sim`),
the phantom at rest (:func:`rest_positions`), the stronger numerics tried when a run
diverges (:data:`TRUTH_RETRIES`) and the "material" entry of ``truth.json``
(:func:`material_truth`). Frame: the phantom frame; SI units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.lab.config import LabConfig, ProgressCallback
from core.lab.phantom import PHANTOM_DENSITY

__all__ = ["SimJob", "MODEL_CACHE", "TRUTH_RETRIES", "truth_mesh", "run_sim", "rest_positions", "material_truth"]

# --------------------------------------------------------------------------------------
# truth simulation (picklable so it can run in a worker process)
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimJob:
    """One truth simulation, everything it needs (picklable, for a worker process).

    Units SI: ``mass`` kg, ``youngs_modulus`` Pa, ``contact_stiffness_per_modulus`` 1/m,
    ``dt`` s, ``rayleigh_mass`` 1/s, ``rayleigh_stiffness`` s, ``radius`` m (the true
    probe radius). ``physical_effects``: complete effect dicts of the kinds of
    :data:`core.lab.config.PHYSICAL_EFFECTS`. ``path_t`` (K,) float64 s and
    ``path_centres`` (K, 3) float64 m: the probe sphere centre's path, phantom frame.
    ``output_times`` (F,) float64 s: the times of the returned positions (the camera
    frames).
    """

    mesh_spec: tuple
    """("grid", (nx, ny, nz), size) for the box, ("stl", path, element_size) otherwise."""
    mass: float
    youngs_modulus: float
    poisson_ratio: float
    law: str
    stiffening: float
    contact_stiffness_per_modulus: float
    dt: float
    newton_iterations: int
    rayleigh_mass: float
    rayleigh_stiffness: float
    physical_effects: tuple[dict, ...]
    path_t: np.ndarray
    path_centres: np.ndarray
    radius: float
    output_times: np.ndarray


def truth_mesh(spec: tuple):
    """The truth's mesh of a ``SimJob.mesh_spec`` (a box grid, or an STL filled by Gmsh;
    meshes are cached by content, so worker processes mesh an STL once).

    Args:
        spec: ``("grid", (nx, ny, nz), size (3,) m)`` or ``("stl", path, element_size m)``.

    Returns:
        the :class:`core.simulation.mesh.TetMesh`, phantom frame, m.

    Raises:
        SimulationError: a bad box size or grid.
        MeshingError: Gmsh cannot fill the STL (both are ``TissueTwinError``).
    """
    from core.simulation import box_mesh
    from core.simulation.meshing import tetrahedralise

    if spec[0] == "grid":
        return box_mesh(size=spec[2], grid=spec[1])
    return tetrahedralise(spec[1], spec[2])


def _build_model(job: SimJob):
    from core.simulation import Material, SimulationConfig, build_model, effect_from_dict

    mesh = truth_mesh(job.mesh_spec)
    return build_model(
        mesh,
        mass=job.mass,
        material=Material(youngs_modulus=job.youngs_modulus, poisson_ratio=job.poisson_ratio, law=job.law,
                          stiffening=job.stiffening),
        config=SimulationConfig(dt=job.dt, rayleigh_mass=job.rayleigh_mass,
                                rayleigh_stiffness=job.rayleigh_stiffness,
                                newton_iterations=job.newton_iterations,
                                contact_stiffness_per_modulus=job.contact_stiffness_per_modulus),
        effects=[effect_from_dict(d) for d in job.physical_effects],
    )


MODEL_CACHE: dict = {}
"""The truth model last built in this process, keyed by all it depends on, so that the
sequences of a session share one (:func:`core.lab.generate_session` clears it at the end)."""


TRUTH_RETRIES: tuple[tuple[int, int], ...] = ((3, 1), (3, 2), (5, 4))
"""(Newton iterations, dt divisor) tried in turn when a truth simulation diverges."""


def run_sim(job: SimJob, callback: ProgressCallback | None = None):
    """Run one truth simulation; returns (positions (F, N, 3) float32, contact force (F, 3),
    status, message, wall time).

    Positions are the mesh's nodes (m, phantom frame) at ``job.output_times``; the
    contact force (float64, N, phantom frame) is the probe's on the phantom; status is
    "ok" or "diverged" (a divergence is returned, not raised) with its message; wall
    time in s. ``callback(fraction, message)`` reports progress.

    Raises:
        SimulationError, MeshingError: the model cannot be built (see :func:`truth_mesh`).
    """
    from core.simulation import ProbePath, simulate

    key = (job.mesh_spec, job.mass, job.youngs_modulus, job.poisson_ratio, job.law, job.stiffening,
           job.contact_stiffness_per_modulus, job.dt, job.newton_iterations,
           job.rayleigh_mass, job.rayleigh_stiffness, repr(job.physical_effects))
    model = MODEL_CACHE.get(key)
    if model is None:
        MODEL_CACHE.clear()
        model = MODEL_CACHE[key] = _build_model(job)
    res = simulate(model, ProbePath(job.path_t, job.path_centres), job.radius, job.output_times,
                   callback=callback)
    return (res.positions.astype(np.float32), res.contact_force, res.status, res.message, res.wall_time)


def rest_positions(job: SimJob) -> np.ndarray:
    """(N, 3) node positions of the phantom at rest (sagged under body forces, if any).

    float64, m, phantom frame; only the model of ``job`` is used (not its probe path).

    Raises:
        SimulationError, MeshingError: the model cannot be built (see :func:`truth_mesh`).
    """
    from core.simulation import static_equilibrium

    model = _build_model(job)
    if np.any(model.body_force):
        return static_equilibrium(model)[0].x
    return model.mesh.nodes.copy()


def material_truth(cfg: LabConfig, size: np.ndarray) -> dict:
    """truth.json "material": law, citation, density and damping (and the stiffening of
    the "stable_yeoh" law).

    Args:
        cfg: the session's lab (after any variation): ``law``, ``stiffening``,
            ``rayleigh_mass`` (1/s) and ``rayleigh_stiffness`` (s) are read.
        size: (3,) phantom size, m (not used).

    Returns:
        a JSON-ready dict; density in kg/m^3 (:data:`core.lab.phantom.PHANTOM_DENSITY`).
    """
    citation = {
        "stable_neo_hookean": "stable Neo-Hookean, Smith, de Goes & Kim 2018",
        "stable_yeoh": "stable Neo-Hookean, Smith, de Goes & Kim 2018, plus a Yeoh-type stiffening term "
                       "stiffening * mu / 2 * (I_C - 3 - 2 (J - 1))^2, Yeoh 1993",
    }.get(cfg.law, cfg.law)
    out = {"law": cfg.law, "citation": citation}
    if cfg.law == "stable_yeoh":
        out["stiffening"] = float(cfg.stiffening)
    out.update({
        "density": PHANTOM_DENSITY,
        "rayleigh_mass": cfg.rayleigh_mass,
        "rayleigh_stiffness": cfg.rayleigh_stiffness,
    })
    return out

