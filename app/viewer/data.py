"""Arrays the viewer shows, computed once per replay run and stored beside its results.

``write_viewer_arrays`` runs at the end of a replay job; ``load_run`` reads a run folder
back into :class:`SequenceArrays` (one per sequence). The viewer itself only consumes
these arrays.

Per-vertex error: every cleaned measured point has the paper's distance to the 3x
super-sampled mesh (Wu et al. 2020, Sec. 3.4); each point is assigned to its nearest
surface node of the deformed mesh, and a node's error is the mean over its points
(NaN when no point falls to it, e.g. hidden faces).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from app.viewer.diagnosis_data import DiagnosisLayers

__all__ = ["SequenceArrays", "RunArrays", "vertex_errors", "write_viewer_arrays", "load_run", "run_label"]

VIEWER_DIR = "viewer"


@dataclass(frozen=True)
class SequenceArrays:
    """Everything to scrub one replayed sequence; all float arrays float32, m, phantom frame.

    Attributes:
        name, role: the sequence.
        times: (F,) camera frame times, s.
        positions: (F, N, 3) FEM node positions.
        faces: (T, 3) surface triangles (node indices, outward).
        vertex_error: (F, N) per-node error, m (NaN: no measured point nearby).
        frame_errors: (F,) mean error of each frame, m.
        cloud_points: (P, 3) cleaned measured points of all frames, concatenated.
        cloud_offsets: (F + 1,) frame f owns ``cloud_points[offsets[f]:offsets[f+1]]``.
        probe_centres: (F, 3) probe sphere centres. probe_radius: m.
        corrected_positions: (F, N, 3) the corrected mesh of the run, or None.
        corrected_vertex_error: (F, N) its per-node error, m, or None.
        diagnosis: the diagnosis layers of a diagnose run
            (:class:`app.viewer.diagnosis_data.DiagnosisLayers`), or None.
    """

    name: str
    role: str
    times: np.ndarray
    positions: np.ndarray
    faces: np.ndarray
    vertex_error: np.ndarray
    frame_errors: np.ndarray
    cloud_points: np.ndarray
    cloud_offsets: np.ndarray
    probe_centres: np.ndarray
    probe_radius: float
    corrected_positions: np.ndarray | None = None
    corrected_vertex_error: np.ndarray | None = None
    diagnosis: "DiagnosisLayers | None" = None

    @property
    def n_frames(self) -> int:
        return int(self.times.size)

    def cloud(self, f: int) -> np.ndarray:
        """(M_f, 3) float32 cleaned points of frame ``f``."""
        return self.cloud_points[self.cloud_offsets[f]:self.cloud_offsets[f + 1]]


@dataclass(frozen=True)
class RunArrays:
    """A replay run: its label and sequences; ``diagnosis``: a diagnose run's ``view.json``
    (answers per kind, claimed causes and their geometry; :mod:`app.viewer.diagnosis_data`),
    else None; ``mesh``: the replayed mesh's :func:`app.run_mesh.mesh_summary` (kind "box"
    or "stl", grid, node and tet counts), or None for a run without sequences."""

    label: str
    sequences: dict[str, SequenceArrays]
    diagnosis: dict | None = None
    mesh: dict | None = None


def vertex_errors(positions: np.ndarray, mesh_or_grid, clouds, factor: int = 3) -> np.ndarray:
    """Per-node error of every frame (see the module docstring).

    Args:
        positions: (F, N, 3) node positions, m.
        mesh_or_grid: the replay's :class:`core.simulation.mesh.TetMesh` (a box grid or an
            STL phantom's Gmsh mesh), or a box grid (nx, ny, nz). The paper's metric is
            :func:`core.simulation.metrics.supersampled_surface` of it (the grid's
            trilinear super-sampling on a box, the surface triangles' otherwise).
        clouds: F arrays (M_f, 3) of measured points, m.
        factor: super-sampling of the paper's metric.

    Returns:
        (F, N) float32, m; NaN for nodes without points and for diverged frames.

    Raises:
        ValueError: ``positions`` is not (F, N, 3) for the mesh's N nodes.
    """
    from scipy.spatial import cKDTree

    from core.simulation.mesh import box_mesh
    from core.simulation.metrics import point_to_mesh_distances, supersampled_surface

    F, N, _ = positions.shape
    if isinstance(mesh_or_grid, (tuple, list, np.ndarray)):
        metric = tuple(int(g) for g in mesh_or_grid)
        surface = box_mesh(np.ptp(positions[0], axis=0) if F else np.ones(3), metric).surface_nodes
    else:
        metric, surface = mesh_or_grid, mesh_or_grid.surface_nodes
        if N != mesh_or_grid.n_nodes:
            raise ValueError(f"positions must be (F, {mesh_or_grid.n_nodes}, 3) for this mesh, got {positions.shape}")
    out = np.full((F, N), np.nan, dtype=np.float32)
    for f in range(F):
        pts = np.asarray(clouds[f], dtype=np.float64)
        if pts.shape[0] == 0 or not np.all(np.isfinite(positions[f])):
            continue
        d = point_to_mesh_distances(pts, supersampled_surface(positions[f], metric, factor))
        _, idx = cKDTree(positions[f][surface]).query(pts)
        nodes = surface[idx]
        sums = np.bincount(nodes, weights=d, minlength=N)
        counts = np.bincount(nodes, minlength=N)
        has = counts > 0
        out[f, has] = (sums[has] / counts[has]).astype(np.float32)
    return out


def write_viewer_arrays(prepared, result, out: str | Path) -> Path:
    """Write ``viewer/<sequence>.npz`` for each sequence of a replay.

    Args:
        prepared: the ``core.simulation.replay.PreparedSession`` the replay used (its
            cleaned clouds).
        result: the ``ReplayResult``.
        out: the run folder (where ``write_replay`` wrote).

    Returns:
        the ``viewer`` folder.
    """
    folder = Path(out) / VIEWER_DIR
    folder.mkdir(parents=True, exist_ok=True)
    mesh = result.mesh if result.mesh is not None else tuple(result.config.grid)  # the box grid for older results
    for name, s in result.sequences.items():
        clouds = prepared.sequences[name].clouds
        offsets = np.concatenate([[0], np.cumsum([c.shape[0] for c in clouds])]).astype(np.int64)
        points = np.concatenate(clouds).astype(np.float32) if clouds else np.zeros((0, 3), np.float32)
        np.savez_compressed(
            folder / f"{name}.npz",
            cloud_points=points,
            cloud_offsets=offsets,
            vertex_error=vertex_errors(s.simulation.positions, mesh, clouds, result.config.supersample),
            probe_radius=np.float64(prepared.probe_radius),
            role=np.str_(s.role),
        )
    return folder


def load_run(folder: str | Path, label: str = "") -> RunArrays:
    """Read a replay run folder (``replay.json``, ``<seq>.npz``, ``viewer/<seq>.npz``).

    The faces are the replayed mesh's surface triangles: an STL phantom's from the npz
    (:func:`app.run_mesh.npz_mesh`), a box's from its grid. A folder ``corrected/<seq>.npz``
    with ``positions`` (F, N, 3) (and optionally ``vertex_error``), written by a correcting
    analysis, adds the corrected mesh; a folder ``diagnosis/`` (a diagnose job's) adds the
    diagnosis layers.

    Raises:
        FileNotFoundError: the folder is not a replay run with viewer arrays.
        ValueError, TissueTwinError: an npz whose positions or mesh arrays do not fit.
    """
    from app.run_mesh import mesh_summary, npz_mesh
    from app.viewer.diagnosis_data import load_diagnosis_layers, load_diagnosis_view
    from core.simulation.mesh import box_mesh

    folder = Path(folder)
    meta = json.loads((folder / "replay.json").read_text())
    sequences = {}
    summary = None
    for name in meta["sequences"]:
        raw = np.load(folder / f"{name}.npz")
        view = np.load(folder / VIEWER_DIR / f"{name}.npz")
        positions = raw["positions"].astype(np.float32)
        mesh = npz_mesh(raw, folder / f"{name}.npz")
        if mesh is None:  # a box: its grid
            size = np.ptp(positions[0], axis=0) if positions.shape[0] else np.ones(3)
            mesh = box_mesh(size, tuple(int(g) for g in raw["grid"]))
        if positions.shape[1] != mesh.n_nodes:
            raise ValueError(f"{folder / f'{name}.npz'}: positions {positions.shape} do not fit its mesh of "
                             f"{mesh.n_nodes} nodes")
        faces = mesh.surface_triangles.astype(np.uint32)
        summary = summary or mesh_summary(mesh)
        corrected = corrected_err = None
        cpath = folder / "corrected" / f"{name}.npz"
        if cpath.exists():
            c = np.load(cpath)
            corrected = c["positions"].astype(np.float32)
            corrected_err = c["vertex_error"].astype(np.float32) if "vertex_error" in c else None
        sequences[name] = SequenceArrays(
            name=name,
            role=str(view["role"]),
            times=raw["times"].astype(np.float64),
            positions=positions,
            faces=faces,
            vertex_error=view["vertex_error"].astype(np.float32),
            frame_errors=raw["frame_errors"].astype(np.float32),
            cloud_points=view["cloud_points"].astype(np.float32),
            cloud_offsets=view["cloud_offsets"].astype(np.int64),
            probe_centres=raw["probe_centres"].astype(np.float32),
            probe_radius=float(view["probe_radius"]),
            corrected_positions=corrected,
            corrected_vertex_error=corrected_err,
            diagnosis=load_diagnosis_layers(folder, name),
        )
    return RunArrays(label=label or folder.name, sequences=sequences, diagnosis=load_diagnosis_view(folder),
                     mesh=summary)


def run_label(job_type: str, folder: str | Path, session: str, result: dict | None = None) -> str:
    """One line naming a viewer run: what made it, of which session, and the E its FEM
    layer was replayed with (read from the run's ``replay.json``, so a diagnose run shows
    the E it actually used, not a parameter it does not have).

    Args:
        job_type: ``"replay"``, ``"train"`` or ``"diagnose"``.
        folder: the run folder (``replay.json`` inside).
        session: the session's name.
        result: the job's summary (the network kind of a train job, the claimed kinds of a
            diagnose job), or None.

    Returns:
        e.g. ``"extended model (gravity) of s3, E 4970 Pa"``; ``"E ?"`` when the run's
        ``replay.json`` cannot be read.
    """
    result = result or {}
    try:
        E = float(json.loads((Path(folder) / "replay.json").read_text())["youngs_modulus"])
        e_text = f"E {E:.4g} Pa"
    except (OSError, ValueError, KeyError, TypeError):
        e_text = "E ?"
    if job_type == "diagnose":
        kinds = (result.get("extended") or {}).get("kinds") or []
        what = f"extended model ({' + '.join(kinds)})" if kinds else "extended model"
    elif job_type == "train":
        what = f"{str(result.get('model', '')).upper()} network".strip()
    else:
        what = job_type
    return f"{what} of {session}, {e_text}"
