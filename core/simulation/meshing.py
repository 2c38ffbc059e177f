"""Tetrahedral meshes of any phantom: the STL check, Gmsh, node ordering, quality.

A session's ``phantom.stl`` (``SESSION_FORMAT.md``: watertight, metres, phantom frame,
z up, resting on z = 0) is filled with tetrahedra by Gmsh (Geuzaine & Remacle 2009), as
the paper filled its CAD surface (Wu et al. 2020, Sec. 4.2). Gmsh is chosen over TetGen
and fTetWild because it remeshes the STL's surface to a target element size (an STL of
a CAD or scanned surface has triangles of any size and shape), its Python package is a
self-contained wheel, and it reports element quality itself; TetGen keeps the input
triangles as they are and fTetWild's Python wrapper is young.

The nodes are then renumbered by reverse Cuthill-McKee (Cuthill & McKee 1969, George
1971; :func:`scipy.sparse.csgraph.reverse_cuthill_mckee`): the replay factorises its
system matrix once in banded storage (:mod:`core.simulation.model`), whose cost grows
with the square of the bandwidth, and Gmsh's own numbering has a bandwidth of the order
of the node count.

Meshes are cached by the STL's content hash and the element size, in
``$TISSUETWIN_CACHE_DIR/meshes`` (else ``$XDG_CACHE_HOME/tissuetwin/meshes``), and once
per process in memory.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from core.errors import MeshingError, SimulationError
from core.simulation.mesh import TetMesh, _boundary_triangles, _orient_positive, box_mesh

__all__ = [
    "MESH_VERSION",
    "MeshQuality",
    "check_stl",
    "default_element_size",
    "mean_edge_length",
    "refined_element_size",
    "mesh_quality",
    "phantom_mesh",
    "rcm_order",
    "tetrahedralise",
]

#: Bumped when the meshing recipe changes, so cached meshes are rebuilt.
MESH_VERSION = 3

#: Nodes of the paper's 13 x 5 x 5 grid: the default element size of an STL phantom
#: gives about this many nodes (:func:`default_element_size`).
PAPER_NODES = 13 * 5 * 5

#: Gmsh's Delaunay meshes hold about twice the nodes of a grid of the same spacing
#: (measured on the paper's box: 566 nodes at (V / 325)^(1/3)); 1.25^3 ~ 2 brings them back.
_DELAUNAY_FACTOR = 1.25
_MAX_EXTENT_M = 1.0
_GMSH_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class MeshQuality:
    """Quality of a tetrahedral mesh.

    Attributes:
        n_nodes, n_tets: counts.
        min_dihedral_deg: smallest dihedral angle of any tetrahedron, degrees (a regular
            tetrahedron has 70.5; slivers approach 0).
        max_aspect_ratio: largest ``R / (3 r)`` (circumradius over three inradii; 1 for a
            regular tetrahedron, growing without bound for degenerate ones).
        mean_aspect_ratio: its mean over the tetrahedra.
        bandwidth: largest ``|i - j|`` of two nodes sharing a tetrahedron (the system
            matrix's half-bandwidth in nodes).
        min_edge, max_edge: shortest and longest edge, m.
    """

    n_nodes: int
    n_tets: int
    min_dihedral_deg: float
    max_aspect_ratio: float
    mean_aspect_ratio: float
    bandwidth: int
    min_edge: float
    max_edge: float

    def to_json(self) -> dict:
        return {k: (int(v) if isinstance(v, (int, np.integer)) else float(v)) for k, v in self.__dict__.items()}


def mesh_quality(mesh: TetMesh) -> MeshQuality:
    """The :class:`MeshQuality` of ``mesh`` (vectorised over its tetrahedra)."""
    p = mesh.nodes[mesh.tets]  # (E, 4, 3)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    edges = np.stack([np.linalg.norm(p[:, b] - p[:, a], axis=1) for a, b in pairs], axis=1)
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    normals = np.stack([np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]) for a, b, c in faces], axis=1)
    areas = 0.5 * np.linalg.norm(normals, axis=2)  # (E, 4)
    unit = normals / np.maximum(2.0 * areas[..., None], 1e-300)
    # the dihedral angle at the edge shared by faces i and j is pi minus the angle
    # between their outward normals
    dihedral = []
    for i in range(4):
        for j in range(i + 1, 4):
            c = np.clip(np.einsum("ek,ek->e", unit[:, i], unit[:, j]), -1.0, 1.0)
            dihedral.append(np.pi - np.arccos(c))
    dihedral = np.degrees(np.stack(dihedral, axis=1))
    d = p[:, 1:] - p[:, :1]
    volume = np.abs(np.linalg.det(d)) / 6.0
    inradius = 3.0 * volume / np.maximum(areas.sum(axis=1), 1e-300)
    # circumradius: |a|^2 (b x c) + |b|^2 (c x a) + |c|^2 (a x b) over 12 V
    a, b, c = d[:, 0], d[:, 1], d[:, 2]
    num = (np.sum(a * a, 1)[:, None] * np.cross(b, c) + np.sum(b * b, 1)[:, None] * np.cross(c, a)
           + np.sum(c * c, 1)[:, None] * np.cross(a, b))
    circumradius = np.linalg.norm(num, axis=1) / np.maximum(12.0 * volume, 1e-300)
    aspect = circumradius / np.maximum(3.0 * inradius, 1e-300)
    t = mesh.tets
    band = int(np.max(t.max(axis=1) - t.min(axis=1))) if t.size else 0
    return MeshQuality(n_nodes=mesh.n_nodes, n_tets=mesh.n_tets, min_dihedral_deg=float(dihedral.min()),
                       max_aspect_ratio=float(aspect.max()), mean_aspect_ratio=float(aspect.mean()),
                       bandwidth=band, min_edge=float(edges.min()), max_edge=float(edges.max()))


def check_stl(path: str | os.PathLike):
    """Read ``phantom.stl`` and check that it can be a phantom's rest surface.

    Returns:
        The surface as a ``trimesh.Trimesh`` (phantom frame, m).

    Raises:
        MeshingError: (naming the file) it cannot be read or has no triangles; it is not
            watertight (holes, or edges shared by more than two triangles); its
            triangles are not consistently oriented; it encloses no volume or is
            inside out; it looks like millimetres (an extent above 1 m); or it does not
            rest on z = 0 (its lowest point more than 0.1 mm from the plane).
    """
    import trimesh  # noqa: PLC0415 (heavy)

    path = Path(path)
    try:
        surface = trimesh.load_mesh(str(path), file_type="stl", process=True)
    except Exception as exc:  # trimesh raises many types on bad input
        raise MeshingError(path, f"cannot read STL ({exc})") from exc
    if not isinstance(surface, trimesh.Trimesh) or len(surface.faces) == 0:
        raise MeshingError(path, "the STL holds no triangles")
    ext = np.asarray(surface.extents, dtype=np.float64)
    if not np.all(np.isfinite(surface.vertices)):
        raise MeshingError(path, "the STL holds NaN or infinite coordinates")
    if np.any(ext > _MAX_EXTENT_M):
        raise MeshingError(path, f"extents {np.round(ext, 3).tolist()} look like millimetres: the format uses metres "
                                 f"(scale the STL by 0.001)")
    if not surface.is_watertight:
        n_open = int(len(trimesh.grouping.group_rows(surface.edges_sorted, require_count=1)))
        raise MeshingError(path, f"the surface is not watertight ({n_open} edges with one triangle, or edges "
                                 f"shared by more than two): a phantom must be a closed surface")
    if not surface.is_winding_consistent:
        raise MeshingError(path, "the triangles are not consistently oriented (some normals point in, some out)")
    if surface.volume <= 0:
        raise MeshingError(path, f"the surface is inside out or encloses no volume (volume {surface.volume:.3g} m^3): "
                                 f"its normals must point out of the phantom")
    zmin = float(surface.bounds[0, 2])
    if abs(zmin) > 1e-4:
        raise MeshingError(path, f"the phantom must rest on z = 0 (phantom frame, z up); its lowest point is at "
                                 f"z = {zmin * 1e3:.2f} mm")
    return surface


def mean_edge_length(mesh: TetMesh) -> float:
    """Mean edge length of a tetrahedral mesh's tetrahedra, m (the size a refinement halves)."""
    p = mesh.nodes[mesh.tets]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    return float(np.mean([np.linalg.norm(p[:, b] - p[:, a], axis=1).mean() for a, b in pairs]))


def refined_element_size(mesh: TetMesh, element_size: float | None) -> float:
    """The element size (m) of a phantom mesh's refinement: half of ``element_size``, or of
    ``mesh``'s mean edge when the mesher chose the size (the diagnosis's fine reference,
    the E fit's refinement and E's model form all refine an STL phantom this way, as
    ``2 n - 1`` nodes per axis halve a box grid's)."""
    return (element_size or mean_edge_length(mesh)) / 2.0


def default_element_size(volume: float, nodes: int = PAPER_NODES) -> float:
    """Element size (m) that fills ``volume`` (m^3) with about ``nodes`` nodes, as the
    paper's 13 x 5 x 5 grid fills its block: the edge of a cube of ``volume / nodes``."""
    if not np.isfinite(volume) or volume <= 0:
        raise SimulationError(f"volume must be positive, got {volume}")
    return float(_DELAUNAY_FACTOR * (volume / nodes) ** (1.0 / 3.0))


def _bandwidth(tets: np.ndarray, order: np.ndarray) -> int:
    new_index = np.empty_like(order)
    new_index[order] = np.arange(order.size)
    t = new_index[tets]
    return int(np.max(t.max(axis=1) - t.min(axis=1)))


def _cuthill_mckee_from(graph: sp.csr_matrix, start: int) -> np.ndarray:
    """Reverse Cuthill-McKee order from a given start node (breadth-first, neighbours
    by increasing degree), for a connected graph."""
    n = graph.shape[0]
    degree = np.diff(graph.indptr)
    seen = np.zeros(n, dtype=bool)
    seen[start] = True
    order = [start]
    head = 0
    while head < len(order):
        v = order[head]
        head += 1
        nb = graph.indices[graph.indptr[v]:graph.indptr[v + 1]]
        nb = nb[~seen[nb]]
        nb = nb[np.argsort(degree[nb], kind="stable")]
        seen[nb] = True
        order.extend(nb.tolist())
    if len(order) < n:  # a disconnected mesh: the rest in scipy's order
        rest = np.flatnonzero(~seen)
        order.extend(rest.tolist())
    return np.asarray(order[::-1], dtype=np.int64)


def rcm_order(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(N,) int64 node order that keeps the stiffness matrix's bandwidth small: new node
    ``i`` is old node ``order[i]``.

    Reverse Cuthill-McKee (Cuthill & McKee 1969, George 1971), started from scipy's
    pseudo-peripheral node (:func:`scipy.sparse.csgraph.reverse_cuthill_mckee`) and from
    both ends of the mesh's principal axis, beside plain slabs along that axis; the order
    with the smallest largest bandwidth wins (on Gmsh meshes of elongated phantoms the
    axis starts give 20-30 % narrower bands than scipy's start)."""
    nodes = np.asarray(nodes, dtype=np.float64)
    n = nodes.shape[0]
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    graph = sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(n, n))
    axis = np.linalg.svd(nodes - nodes.mean(axis=0), full_matrices=False)[2][0]
    x = nodes @ axis
    candidates = [np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), dtype=np.int64),
                  _cuthill_mckee_from(graph, int(np.argmin(x))), _cuthill_mckee_from(graph, int(np.argmax(x))),
                  np.argsort(x, kind="stable").astype(np.int64)]
    return min(candidates, key=lambda order: _bandwidth(tets, order))


def _cache_dir() -> Path:
    root = os.environ.get("TISSUETWIN_CACHE_DIR")
    if root:
        return Path(root) / "meshes"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "tissuetwin" / "meshes"


def _gmsh_version() -> str:
    from importlib.metadata import PackageNotFoundError, version  # noqa: PLC0415

    try:
        return version("gmsh")
    except PackageNotFoundError:
        return "none"


def tetrahedralise(path: str | os.PathLike, element_size: float | None = None, *, cache: bool = True) -> TetMesh:
    """Fill the phantom surface ``path`` (an STL) with tetrahedra.

    Args:
        path: ``phantom.stl`` (watertight, metres, phantom frame, resting on z = 0).
        element_size: target edge length, m; None gives :func:`default_element_size`
            of the enclosed volume (about the paper's 325 nodes).
        cache: read and write the mesh cache (module docstring).

    Returns:
        A :class:`TetMesh` with ``grid=None``, positively oriented tetrahedra, nodes in
        reverse Cuthill-McKee order, nodes within 1e-7 m of z = 0 put exactly on it (the
        ``fixed: bottom`` support), and ``size`` the surface's bounding-box extents.

    Raises:
        MeshingError: the STL fails :func:`check_stl`, Gmsh refuses it (for example a
            self-intersecting surface; the message carries Gmsh's words), or the result
            has inverted or degenerate tetrahedra.
    """
    path = Path(path).resolve()  # the mesher runs in the project's folder, not the caller's
    surface = check_stl(path)
    h = default_element_size(float(surface.volume)) if element_size is None else float(element_size)
    extent = float(np.max(surface.extents))
    if not np.isfinite(h) or h <= 0 or h > extent:
        raise MeshingError(path, f"element size {h} m must be positive and at most the phantom's extent {extent:.4g} m")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:32]
    key = f"{digest}-{h:.6e}-v{MESH_VERSION}-gmsh{_gmsh_version()}"
    return _tetrahedralise(str(path), key, h, cache)


@lru_cache(maxsize=8)
def _tetrahedralise(path: str, key: str, h: float, cache: bool) -> TetMesh:
    stored = _cache_dir() / f"{key}.npz"
    if cache and stored.is_file():
        try:
            with np.load(stored) as z:
                return _finish(z["nodes"], z["tets"], Path(path), reorder=False)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache entry is rebuilt below
    with tempfile.TemporaryDirectory(prefix="tissuetwin-gmsh-") as tmp:
        out = Path(tmp) / "mesh.npz"
        try:
            proc = subprocess.run([sys.executable, "-m", "core.simulation.gmsh_worker", path, repr(h), str(out)],
                                  capture_output=True, text=True, timeout=_GMSH_TIMEOUT_S,
                                  cwd=str(Path(__file__).resolve().parents[2]))
        except subprocess.TimeoutExpired as exc:
            raise MeshingError(path, f"Gmsh did not finish within {_GMSH_TIMEOUT_S:.0f} s at element size "
                                     f"{h * 1e3:.2f} mm") from exc
        if proc.returncode != 0 or not out.is_file():
            words = " ".join((proc.stderr or "").strip().splitlines()[-3:]) or f"exit status {proc.returncode}"
            if "intersect" in words.lower():
                raise MeshingError(path, f"the surface intersects itself, so it bounds no single volume (Gmsh: {words})")
            raise MeshingError(path, f"Gmsh could not fill the surface with tetrahedra: {words}")
        with np.load(out) as z:
            nodes, tets = z["nodes"], z["tets"]
    mesh = _finish(nodes, tets, Path(path))
    if cache:
        try:
            _cache_dir().mkdir(parents=True, exist_ok=True)
            tmp_file = stored.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp_file, nodes=mesh.nodes, tets=mesh.tets)
            os.replace(tmp_file, stored)
        except OSError:
            pass  # a read-only cache only costs the next call a re-mesh
    return mesh


def _finish(nodes: np.ndarray, tets: np.ndarray, path: Path, *, reorder: bool = True) -> TetMesh:
    """Renumber (RCM; a cached mesh is stored renumbered), snap the support plane,
    orient, and wrap as a read-only TetMesh."""
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or tets.ndim != 2 or tets.shape[1] != 4 or tets.size == 0:
        raise MeshingError(path, f"the mesher returned nodes {nodes.shape} and tets {tets.shape}")
    if reorder:
        order = rcm_order(nodes, tets)
        new_index = np.empty_like(order)
        new_index[order] = np.arange(order.size)
        nodes = nodes[order].copy()
        tets = new_index[tets]
    else:
        nodes = nodes.copy()
    nodes[np.abs(nodes[:, 2]) <= 1e-7, 2] = 0.0
    tets = _orient_positive(nodes, tets)
    d = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    vol = np.linalg.det(d) / 6.0
    if np.any(vol <= 1e-18):
        raise MeshingError(path, f"{int(np.sum(vol <= 1e-18))} degenerate tetrahedra in the mesh")
    tris = _boundary_triangles(nodes, tets)
    size = nodes.max(axis=0) - np.minimum(nodes.min(axis=0), 0.0)
    for a in (nodes, tets, tris, size):
        a.flags.writeable = False
    return TetMesh(nodes=nodes, tets=tets, surface_triangles=tris, grid=None, size=size)


def phantom_mesh(size, stl_path: str | os.PathLike | None = None, *, grid=(13, 5, 5),
                 element_size: float | None = None) -> TetMesh:
    """The replay's mesh of a phantom: the box grid when there is no STL, else the STL
    filled by :func:`tetrahedralise`.

    Args:
        size: (3,) box size, m (used only without an STL).
        stl_path: the session's ``phantom.stl`` or None.
        grid: (nx, ny, nz) node grid of the box (the paper's 13 x 5 x 5).
        element_size: target element size of an STL phantom, m (None: about the
            paper's node count, :func:`default_element_size`).

    Raises:
        SimulationError: a bad box size or grid. MeshingError: a bad STL.
    """
    if stl_path is None:
        return box_mesh(size, grid)
    return tetrahedralise(stl_path, element_size)
