"""Residual fields on any observed surface: patches instead of the box's face bins.

The box's field (:class:`core.diagnosis.fields.FieldLayout`) bins the top face (and the
sides) on a grid. A phantom of any shape (``phantom.stl``) has no faces: its visible
rest surface (every surface point above the support, ``z > base_margin``) is cut into
``n_patches`` patches of similar area by k-means on the surface's super-sampled points
(Lloyd 1982; :func:`scipy.cluster.vq.kmeans2`, seeded), and a patch plays a bin's part.

The observable is the same: the measured surface's signed distance to the model along
its outward normal, positive outside. A measured point is tied (once, at rest) to its
nearest super-sampled rest surface point ``s`` of the mesh being replayed; its residual
in frame f is ``(p - x_s(f)) . n_s(f)``, with ``x_s`` the super-sampled point carried by
the deformed mesh (barycentric in its surface triangle, as the paper's metric) and
``n_s`` the deformed surface's interpolated outward normal. Tangential sliding of the
surface changes this only at second order (through the curvature); its derivative along
node-position directions is ``-(d x_s) . n_s`` (the normal's own change is
perpendicular to it and multiplies a residual along it).

A patch layout is one noise group (``"surface"`` of :data:`core.diagnosis.fields.NOISE_GROUPS`).
"""

from __future__ import annotations

import hashlib

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from core.diagnosis.caching import LruCache
from core.simulation.mesh import TetMesh
from core.simulation.metrics import surface_operator

__all__ = ["PatchLayout", "SurfaceSampler", "sampler_of", "field_layout"]

#: Index of the patch layout's noise group in :data:`core.diagnosis.fields.NOISE_GROUPS`.
SURFACE_GROUP = 5


class SurfaceSampler:
    """A mesh's super-sampled surface points as (P, 3) node indices and barycentric
    weights (from :func:`core.simulation.metrics.surface_operator`), with a KD-tree of
    their rest positions."""

    def __init__(self, mesh: TetMesh, factor: int = 3):
        S = surface_operator(mesh, factor).tocsr()
        P = S.shape[0]
        nodes = np.zeros((P, 3), dtype=np.int64)
        weights = np.zeros((P, 3))
        for r in range(P):
            a, b = S.indptr[r], S.indptr[r + 1]
            k = b - a
            nodes[r, :k], weights[r, :k] = S.indices[a:b], S.data[a:b]
            nodes[r, k:] = S.indices[a]  # padding with weight 0
        self.mesh, self.nodes, self.weights = mesh, nodes, weights
        self.rest = np.einsum("pk,pkj->pj", weights, mesh.nodes[nodes])
        self.tree = cKDTree(self.rest)
        self.triangles = np.asarray(mesh.surface_triangles)
        T, N = self.triangles.shape[0], mesh.nodes.shape[0]
        # node x triangle incidence: a node's (area-weighted) normal is the sum of its
        # triangles' cross products, for every frame in one sparse product
        self._incidence = sparse.csr_matrix((np.ones(3 * T), (self.triangles.T.ravel(), np.tile(np.arange(T), 3))),
                                            shape=(N, T))
        self._samples = LruCache(self.SAMPLES_CACHE_BYTES, lambda a: a.nbytes)

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance (M,) m, index (M,)) of each point's nearest rest sample."""
        return self.tree.query(np.asarray(points, dtype=np.float64).reshape(-1, 3))

    SAMPLES_CACHE_BYTES = 64 << 20
    """Most bytes of nearest-sample indices :meth:`samples_of` keeps (least recently used out)."""

    def samples_of(self, points: np.ndarray) -> np.ndarray:
        """(M,) int64 index of each point's nearest rest sample, remembered by the points'
        content: a diagnosis measures the same binned points of a sequence against
        hundreds of runs of the same mesh, and the KD-tree query was a third of a coarse
        dome run's field."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        key = hashlib.blake2b(p.tobytes(), digest_size=16).digest()
        hit = self._samples.get_recent(key)
        if hit is None:
            hit = self.tree.query(p)[1].astype(np.int64)
            self._samples.put(key, hit)
        return hit

    def normals(self, positions: np.ndarray) -> np.ndarray:
        """(P, 3) outward unit normals at the samples for (N, 3) node positions."""
        return self._point_normals(np.asarray(positions, dtype=np.float64)[None], np.zeros(self.rest.shape[0], dtype=np.int64),
                                   np.arange(self.rest.shape[0]))

    def residuals(self, points: np.ndarray, frames: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(M,) signed residuals (m) of points (M, 3) in frames (M,) against positions (F, N, 3)."""
        s = self.samples_of(points)
        pos = np.asarray(positions, dtype=np.float64)
        x = np.einsum("mk,mkj->mj", self.weights[s], pos[frames[:, None], self.nodes[s]])
        n = self._point_normals(pos, frames, s)
        return np.einsum("mj,mj->m", points - x, n)

    def residuals_tangent(self, points: np.ndarray, frames: np.ndarray, positions: np.ndarray,
                          dpositions: np.ndarray) -> np.ndarray:
        """(p, M) derivatives of :meth:`residuals` along (p, F, N, 3) node-position directions."""
        s = self.samples_of(points)
        pos = np.asarray(positions, dtype=np.float64)
        n = self._point_normals(pos, frames, s)
        dx = np.einsum("mk,tmkj->tmj", self.weights[s], np.asarray(dpositions)[:, frames[:, None], self.nodes[s]])
        return -np.einsum("tmj,mj->tm", dx, n)

    def _point_normals(self, pos: np.ndarray, frames: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(M,) unit normals at samples ``s`` in ``frames`` of ``pos`` (F, N, 3): the
        barycentric mean of the nodes' sums of their triangles' cross products."""
        used, fi = np.unique(frames, return_inverse=True)
        fi = fi.reshape(-1)
        t = self.triangles
        out = np.empty((frames.size, 3))
        for a in range(0, used.size, self.NORMAL_FRAMES):  # (frames, nodes, 3) arrays of a few MB at a time
            b = min(a + self.NORMAL_FRAMES, used.size)
            m = (fi >= a) & (fi < b)
            p = pos[used[a:b]]  # (U, N, 3)
            face = np.cross(p[:, t[:, 1]] - p[:, t[:, 0]], p[:, t[:, 2]] - p[:, t[:, 0]])  # (U, T, 3)
            U, T = face.shape[0], face.shape[1]
            vn = (self._incidence @ face.transpose(1, 0, 2).reshape(T, 3 * U)).reshape(-1, U, 3)  # (N, U, 3)
            sm = s[m]
            nn = np.einsum("mk,mkj->mj", self.weights[sm], vn[self.nodes[sm], (fi[m] - a)[:, None]])
            out[m] = nn / np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300)
        return out

    NORMAL_FRAMES = 32
    """Frames whose vertex normals :meth:`_point_normals` builds together."""


_SAMPLERS: dict = {}


def sampler_of(mesh: TetMesh, factor: int = 3) -> SurfaceSampler:
    """The :class:`SurfaceSampler` of a mesh, built once per process."""
    key = (_mesh_key(mesh), factor)
    hit = _SAMPLERS.get(key)
    if hit is None:
        if len(_SAMPLERS) >= 8:
            _SAMPLERS.pop(next(iter(_SAMPLERS)))
        hit = _SAMPLERS[key] = SurfaceSampler(mesh, factor)
    return hit


def _mesh_key(mesh: TetMesh) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(mesh.nodes).tobytes())
    h.update(np.ascontiguousarray(mesh.tets).tobytes())
    return h.hexdigest()


class PatchLayout:
    """Patches of the visible rest surface of any mesh (module docstring): the
    :class:`core.diagnosis.fields.FieldLayout` interface for a phantom without faces.

    Args:
        mesh: the replay's rest mesh (phantom frame, m).
        n_patches: number of patches (k-means clusters of the surface samples).
        base_margin: surface points at most this high (m) belong to the support, unseen.
        max_distance: measured points farther than this from the rest surface (m) are not
            binned (the instrument, outliers; a dent is shallower).
        seed: the k-means seed.

    Attributes:
        size: the mesh's bounding-box size (3,), m. bins: ``(n_patches, 1)`` (maps are
            one column). top_bins, n_bins: ``n_patches``.
    """

    def __init__(self, mesh: TetMesh, n_patches: int = 32, *, base_margin: float = 0.003,
                 max_distance: float = 0.012, seed: int = 0):
        from scipy.cluster.vq import kmeans2

        sampler = sampler_of(mesh)
        rest = sampler.rest
        normals = sampler.normals(mesh.nodes)
        visible = rest[:, 2] > base_margin
        if np.count_nonzero(visible) < n_patches:
            raise ValueError(f"the mesh's visible surface has {np.count_nonzero(visible)} samples for {n_patches} patches")
        pts = rest[visible]
        rng = np.random.default_rng(seed)
        init = pts[rng.choice(pts.shape[0], n_patches, replace=False)]
        centres, labels = kmeans2(pts, init, iter=50, minit="matrix", seed=seed)
        # renumber patches top-down (highest first), then by x: a stable, readable order
        order = np.lexsort((centres[:, 0], -centres[:, 2]))
        rank = np.empty(n_patches, dtype=np.int64)
        rank[order] = np.arange(n_patches)
        self._patch_of_sample = np.full(rest.shape[0], -1, dtype=np.int64)
        self._patch_of_sample[visible] = rank[labels]
        used = np.unique(self._patch_of_sample[visible])
        if used.size != n_patches:  # an empty cluster: keep the numbering dense
            remap = np.full(n_patches, -1, dtype=np.int64)
            remap[used] = np.arange(used.size)
            self._patch_of_sample = np.where(self._patch_of_sample >= 0, remap[np.maximum(self._patch_of_sample, 0)], -1)
            n_patches = int(used.size)
        p_of = self._patch_of_sample
        self._centres = np.array([rest[p_of == k].mean(axis=0) for k in range(n_patches)])
        nsum = np.array([normals[p_of == k].sum(axis=0) for k in range(n_patches)])
        self._normals = nsum / np.maximum(np.linalg.norm(nsum, axis=1, keepdims=True), 1e-300)
        self._tree = sampler.tree
        self.max_distance = float(max_distance)
        self.n_patches = int(n_patches)
        self.size = tuple(float(v) for v in np.asarray(mesh.size))
        self.bins = (self.n_patches, 1)
        self._key = (_mesh_key(mesh), self.n_patches, float(base_margin), self.max_distance, int(seed))

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other) -> bool:
        return isinstance(other, PatchLayout) and other._key == self._key

    @property
    def top_bins(self) -> int:
        return self.n_patches

    @property
    def n_bins(self) -> int:
        return self.n_patches

    def faces(self) -> tuple[str, ...]:
        return ("surface",)

    def face_of_bin(self) -> np.ndarray:
        return np.full(self.n_patches, SURFACE_GROUP, dtype=np.int64)

    def centres3(self) -> np.ndarray:
        """(B, 3) patch centres on the rest surface (area-weighted means), m."""
        return self._centres.copy()

    def centres(self) -> np.ndarray:
        """(B, 2) patch centres (x, y), m."""
        return self._centres[:, :2].copy()

    def normals3(self) -> np.ndarray:
        """(B, 3) mean outward unit normal of each patch, rest surface."""
        return self._normals.copy()

    def measured_on(self, prepared, grid, element_size) -> TetMesh:
        """What the residuals are measured on: the replayed mesh of ``prepared``'s phantom
        (:func:`core.simulation.replay.replay_mesh` with ``grid`` and ``element_size``)."""
        from core.simulation.replay import replay_mesh

        return replay_mesh(prepared, grid, element_size)

    def residuals(self, points: np.ndarray, bins: np.ndarray, frames: np.ndarray, positions: np.ndarray,
                  mesh: TetMesh) -> np.ndarray:
        """(M,) signed residual of each binned point (M, 3) along the deformed surface's
        normal of the replayed ``mesh`` (:meth:`SurfaceSampler.residuals`), m; ``frames``
        (M,) its frame in ``positions`` (F, N, 3). ``bins`` is not needed (one noise group)."""
        return sampler_of(mesh).residuals(points, frames, positions)

    def residuals_tangent(self, points: np.ndarray, bins: np.ndarray, frames: np.ndarray, positions: np.ndarray,
                          dpositions: np.ndarray, mesh: TetMesh) -> np.ndarray:
        """(p, M) derivatives of :meth:`residuals` along ``dpositions`` (p, F, N, 3)."""
        return sampler_of(mesh).residuals_tangent(points, frames, positions, dpositions)

    def index(self, points: np.ndarray) -> np.ndarray:
        """(M,) patch of each (M, 3) point (its nearest rest sample's), -1 when that
        sample is unseen (the support) or farther than ``max_distance``."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if p.shape[0] == 0:
            return np.zeros(0, dtype=np.int64)
        d, s = self._tree.query(p)
        out = self._patch_of_sample[s]
        return np.where(d <= self.max_distance, out, -1)


def field_layout(prepared, cfg):
    """The residual field's layout of a session: bins on the box's faces
    (:class:`core.diagnosis.fields.FieldLayout`), or patches of any phantom's visible
    surface (``phantom.stl``; :class:`PatchLayout` on the replay's mesh).

    Args:
        prepared: a :class:`core.preparation.PreparedSession`.
        cfg: a :class:`core.diagnosis.DiagnosisConfig` (grid, element size, bins, patches).

    Raises:
        core.simulation.meshing.MeshingError: the STL cannot be meshed.
    """
    from core.diagnosis.fields import FieldLayout
    from core.simulation.replay import replay_mesh

    if prepared.stl_path is not None:
        return PatchLayout(replay_mesh(prepared, cfg.grid, cfg.element_size), cfg.surface_patches)
    return FieldLayout(tuple(float(v) for v in prepared.size), cfg.layout_bins, side_rows=cfg.side_rows)
