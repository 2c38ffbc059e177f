"""What the viewer shows of a diagnosis (issue 19, item 3), written by the diagnose job
beside its ``diagnosis.json`` and read back with the run.

A diagnose job's ``viewer_run/`` folder is a replay run of the session's test sequences
with the base model (the FEM layer, :mod:`app.viewer.data`), the model extended by the
claimed causes as its corrected mesh (``corrected/``, when something was claimed), and
``diagnosis/``:

- ``diagnosis/<sequence>.npz``: ``base_residual`` (N,) float32, m: the base model's
  systematic residual per node, the time mean of its signed residual (below);
  ``extended_residual`` (N,) the same for the extended model (when something was
  claimed); ``change_<kind>`` (F, N) float32, m: what each claimed cause alone changes of
  the surface, the displacement of the model with that cause alone from the base model
  along the base surface's outward normal, per frame.
- ``diagnosis/view.json``: every kind's answer (found / confounded / not found above a
  size / cannot tell, with the size, its unit and the reason), the claimed causes, the
  geometry of those that have one (an inclusion's sphere, the gravity vector, a robot
  offset as an arrow at the probe, a probe's true radius) and the test errors.

Signed residual of a node at a frame: the mean, over the cleaned measured points whose
nearest surface node it is, of ``(p - x) . n`` with ``x`` the node and ``n`` its
area-weighted outward normal (phantom frame, m): positive where the measured surface
lies outside the model's, negative inside. NaN where no point falls to the node.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

__all__ = ["DiagnosisLayers", "vertex_normals", "signed_residuals", "cause_geometry", "write_diagnosis_run",
           "load_diagnosis_layers", "load_diagnosis_view", "DIAGNOSIS_DIR"]

DIAGNOSIS_DIR = "diagnosis"


@dataclass(frozen=True)
class DiagnosisLayers:
    """The diagnosis layers of one sequence (see the module docstring); float32, m.

    Attributes:
        base_residual: (N,) systematic signed residual of the base model.
        extended_residual: (N,) the same for the extended model, or None (nothing claimed).
        changes: {kind: (F, N) signed change of the surface by that claimed cause alone}.
    """

    base_residual: np.ndarray
    extended_residual: np.ndarray | None
    changes: dict[str, np.ndarray]


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted outward unit normals of the surface nodes.

    Args:
        positions: (N, 3) node positions, m. faces: (T, 3) outward surface triangles.

    Returns:
        (N, 3) float64; zero rows for nodes on no triangle.
    """
    p = np.asarray(positions, float)
    f = np.asarray(faces, np.int64)
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])  # length = 2 x area
    out = np.zeros_like(p)
    for k in range(3):
        np.add.at(out, f[:, k], n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def signed_residuals(positions: np.ndarray, faces: np.ndarray, clouds) -> np.ndarray:
    """Per-node signed residual of every frame (module docstring).

    Args:
        positions: (F, N, 3) node positions, m. faces: (T, 3) surface triangles.
        clouds: F arrays (M_f, 3) of cleaned measured points, m, phantom frame.

    Returns:
        (F, N) float32, m; NaN for nodes without points and for diverged frames.
    """
    from scipy.spatial import cKDTree

    F, N, _ = positions.shape
    surface = np.unique(np.asarray(faces, np.int64))
    out = np.full((F, N), np.nan, dtype=np.float32)
    for f in range(F):
        pts = np.asarray(clouds[f], dtype=np.float64)
        x = np.asarray(positions[f], np.float64)
        if pts.shape[0] == 0 or not np.all(np.isfinite(x)):
            continue
        normals = vertex_normals(x, faces)
        _, idx = cKDTree(x[surface]).query(pts)
        nodes = surface[idx]
        d = np.einsum("ij,ij->i", pts - x[nodes], normals[nodes])
        sums = np.bincount(nodes, weights=d, minlength=N)
        counts = np.bincount(nodes, minlength=N)
        has = counts > 0
        out[f, has] = (sums[has] / counts[has]).astype(np.float32)
    return out


def _time_mean(values: np.ndarray) -> np.ndarray:
    """(F, N) -> (N,) mean over the frames where a value exists; NaN where none does."""
    has = np.isfinite(values)
    s = np.where(has, values, 0.0).sum(axis=0)
    c = has.sum(axis=0)
    return np.where(c > 0, s / np.maximum(c, 1), np.nan).astype(np.float32)


def _normal_change(base: np.ndarray, other: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, N) float32: ``other - base`` along the base surface's outward normal, m."""
    out = np.full(base.shape[:2], np.nan, dtype=np.float32)
    for f in range(base.shape[0]):
        if np.all(np.isfinite(base[f])) and np.all(np.isfinite(other[f])):
            n = vertex_normals(base[f], faces)
            out[f] = np.einsum("ij,ij->i", other[f] - base[f], n).astype(np.float32)
    return out


def cause_geometry(effect: dict, size, youngs: dict | None = None) -> dict | None:
    """How the viewer draws a claimed cause, or None for kinds without a shape.

    Args:
        effect: a SESSION_FORMAT effect dict (``kind`` and its parameters, SI).
        size: (3,) the phantom's size, m (the gravity arrow starts above its top centre).
        youngs: the diagnosis's ``youngs_modulus`` (``value``, ``replay_grid_value_used``),
            or None. The sag is set by rho g / E, so a gravity fitted on the replay grid at
            its E reads, at the mesh-corrected E, as g x value / replay_grid_value_used; the
            label gives both.

    Returns:
        {"kind", "shape", ...}: ``"sphere"`` (``center``, ``radius``: an inclusion),
        ``"vector"`` (``origin``, ``vector``, m, drawn 15 mm per standard gravity: gravity),
        ``"probe_vector"`` (``vector``, m, at the probe, drawn 5x: a robot offset) or
        ``"probe_sphere"`` (``radius``: the probe's true radius); with a ``label``.
    """
    from core.diagnosis.youngs import gravity_at_reported_youngs

    kind = effect["kind"]
    sx, sy, sz = (float(v) for v in size)
    if kind == "inclusion":
        return {"kind": kind, "shape": "sphere", "center": [float(v) for v in effect["center"]],
                "radius": float(effect["radius"]),
                "label": f"inclusion: radius {effect['radius'] * 1e3:.1f} mm, {effect['stiffness_ratio']:.2g}x stiffer"}
    if kind == "gravity":
        g = np.asarray(effect["g"], float)
        label = f"gravity |g| {np.linalg.norm(g):.2f} m/s^2 (arrow 15 mm per 9.81)"
        at_E = gravity_at_reported_youngs(g, youngs)
        if at_E is not None:
            label += (f" at the replay grid's E {youngs['replay_grid_value_used']:.0f} Pa; {at_E:.2f} m/s^2 "
                      f"at the mesh-corrected E {youngs['value']:.0f} Pa")
        return {"kind": kind, "shape": "vector", "origin": [sx / 2, sy / 2, sz + 0.02],
                "vector": (g / 9.80665 * 0.015).tolist(), "label": label}
    if kind == "kinematic_offset":
        o = np.asarray(effect["offset"], float)
        return {"kind": kind, "shape": "probe_vector", "vector": (5.0 * o).tolist(),
                "label": f"robot offset {np.linalg.norm(o) * 1e3:.2f} mm (arrow 5x)"}
    if kind == "probe_radius":
        return {"kind": kind, "shape": "probe_sphere", "radius": float(effect["radius"]),
                "label": f"probe radius {effect['radius'] * 1e3:.2f} mm"}
    return None


def _answers(summary: dict) -> dict:
    from core.simulation.effects import EFFECT_KINDS

    det = summary.get("detectability") or {}
    out = {}
    for kind, answer in (summary.get("answers") or {}).items():
        d = det.get(kind) or {}
        cls = EFFECT_KINDS.get(kind)
        out[kind] = {"answer": answer, "min_size": d.get("min_size"), "unit": getattr(cls, "size_unit", ""),
                     "why": d.get("why", "")}
    return out


def write_diagnosis_run(prepared, summary: dict, grid, youngs: float, folder) -> dict:
    """Write a diagnose job's ``viewer_run`` (module docstring) for the test sequences (all
    sequences when none is a test one).

    Args:
        prepared: the ``core.preparation.PreparedSession`` the diagnosis used.
        summary: the diagnosis's JSON (``Diagnosis.to_json()``).
        grid: (nx, ny, nz) the replay grid of a box (an STL phantom is replayed on its
            Gmsh mesh, whose surface and metric the layers then use). youngs: Young's
            modulus of the replays, Pa.
        folder: where to write (created).

    Returns:
        {"corrected_shown": {sequence: "extended"} or {}, "layers": [layer names]}.
    """
    from app.viewer.data import vertex_errors, write_viewer_arrays
    from core.simulation import effect_from_dict
    from core.simulation.replay import ReplayConfig, replay, write_replay

    folder = Path(folder)
    tests = tuple(n for n, s in prepared.sequences.items() if s.role == "test") or tuple(prepared.sequences)
    base = ReplayConfig(youngs_modulus=youngs, grid=tuple(grid), sequences=tests)
    result = replay(prepared.path, base, prepared=prepared)
    write_replay(result, folder)
    write_viewer_arrays(prepared, result, folder)
    effects = [dict(e) for e in ((summary.get("extended") or {}).get("effects") or [])]

    def positions_with(chosen: list[dict]) -> dict[str, np.ndarray]:
        r = replay(prepared.path, replace(base, effects=tuple(effect_from_dict(dict(e)) for e in chosen)), prepared=prepared)
        return {n: r.sequences[n].simulation.positions for n in tests}

    extended = positions_with(effects) if effects else None
    alone = {e["kind"]: (extended if len(effects) == 1 else positions_with([e])) for e in effects}
    layers = ["base_residual"] + (["extended_residual"] + [f"change_{k}" for k in alone] if effects else [])
    (folder / DIAGNOSIS_DIR).mkdir(parents=True, exist_ok=True)
    if effects:
        (folder / "corrected").mkdir(exist_ok=True)
    size = None
    mesh = result.mesh  # the box grid of the session's size, or the STL phantom's mesh
    faces = mesh.surface_triangles
    for name in tests:
        base_pos = result.sequences[name].simulation.positions
        size = np.ptp(base_pos[0], axis=0)
        clouds = prepared.sequences[name].clouds
        arrays = {"base_residual": _time_mean(signed_residuals(base_pos, faces, clouds))}
        if extended is not None:
            ext = extended[name]
            np.savez_compressed(folder / "corrected" / f"{name}.npz", positions=ext,
                                vertex_error=vertex_errors(ext, mesh, clouds, base.supersample), mode=np.str_("extended"))
            arrays["extended_residual"] = _time_mean(signed_residuals(ext, faces, clouds))
            for kind, pos in alone.items():
                arrays[f"change_{kind}"] = _normal_change(base_pos, pos[name], faces)
        np.savez_compressed(folder / DIAGNOSIS_DIR / f"{name}.npz", **arrays)
    ext_summary = summary.get("extended") or {}
    view = {
        "answers": _answers(summary),
        "claimed": [{"kind": e["kind"], "parameters": {k: v for k, v in e.items() if k != "kind"}} for e in effects],
        "geometry": [g for e in effects
                     if (g := cause_geometry(e, size if size is not None else np.ones(3), summary.get("youngs_modulus")))],
        "youngs_modulus": float(youngs),
        "test_error": {"base": (summary.get("baseline") or {}).get("test_error"), "extended": ext_summary.get("test_error")},
        "layers": layers,
    }
    (folder / DIAGNOSIS_DIR / "view.json").write_text(json.dumps(view, indent=2))
    return {"corrected_shown": {n: "extended" for n in tests} if effects else {}, "layers": layers}


def load_diagnosis_layers(folder, sequence: str) -> DiagnosisLayers | None:
    """The diagnosis layers of ``sequence`` in a run folder, or None when it has none
    (a replay or train run)."""
    path = Path(folder) / DIAGNOSIS_DIR / f"{sequence}.npz"
    if not path.exists():
        return None
    with np.load(path) as z:
        return DiagnosisLayers(
            base_residual=z["base_residual"].astype(np.float32),
            extended_residual=z["extended_residual"].astype(np.float32) if "extended_residual" in z else None,
            changes={k[len("change_"):]: z[k].astype(np.float32) for k in z.files if k.startswith("change_")},
        )


def load_diagnosis_view(folder) -> dict | None:
    """A run folder's ``diagnosis/view.json``, or None (not a diagnose run)."""
    path = Path(folder) / DIAGNOSIS_DIR / "view.json"
    return json.loads(path.read_text()) if path.exists() else None
