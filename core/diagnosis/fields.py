"""Residual fields: where and when the replayed surface disagrees with the measured one.

The observable is the measured surface's signed distance to the model along the face
normal, binned on the faces of the rest box:

- **top face**: every measured point over the top face's interior gets its signed
  vertical residual ``z_point - z_model(x, y)`` (:func:`core.identification.residuals.top_residuals`);
- **side faces** (``FieldLayout.side_rows > 0``): a point whose nearest rest face is a
  side face, within 10 mm of it and away from its edges, gets ``(p - model) . n`` with
  ``n`` the face's outward normal and the model face interpolated the same way
  (:func:`face_residuals`). The cameras of this field see sides at grazing angles, so
  each face has its own noise level (``residual_field`` returns the scatter per face).

Residuals are averaged in a fixed grid of bins on the rest faces. A run of the model is
thus an (F, B) field of bin means with fixed (F, B) point counts, which is what the
candidate signatures and fits of :mod:`core.diagnosis.engine` work on. Positive means
the measured surface lies outside the model's.

Noise is separated from systematic error by the scatter of points inside a bin and
frame: for a smooth surface that scatter is the sensor noise, and a bin mean of ``n``
points has variance ``sigma^2 / n`` under noise alone.
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass

import numpy as np

from core.diagnosis.field_kernels import (box_field, box_field_tangent, face_geometry, face_residuals_kernel,
                                          face_residuals_tangent_kernel)
from core.preparation import Clouds, release_pages
from core.preparation.shape import BoxShape, RestShape


__all__ = ["FieldLayout", "FACES", "NOISE_GROUPS", "face_residuals", "face_residuals_tangent", "frame_bins", "KeptPoints", "Ragged", "residual_field",
           "residual_field_tangent", "phase_labels", "PHASES"]

PHASES = ("rest", "loading", "holding", "unloading", "sliding")
"""Labels of :func:`phase_labels`, in this order."""

FACES = ("top", "-x", "+x", "-y", "+y")
"""Faces of the residual field, in bin order: (normal axis, at the high end) of each."""
NOISE_GROUPS = FACES + ("surface",)
"""Noise groups of a field's bins: the box's faces, then ``"surface"``, the single group of
a phantom of any shape (:class:`core.diagnosis.patches.PatchLayout`)."""
_FACE_AXIS = {"top": (2, True), "-x": (0, False), "+x": (0, True), "-y": (1, False), "+y": (1, True)}


@dataclass(frozen=True)
class FieldLayout:
    """A grid of bins over the interior of the rest top face, and optionally the sides.

    Bin order: the top's ``bins[0] x bins[1]`` bins (x-major), then, with
    ``side_rows > 0``, the faces -x and +x (``bins[1] x side_rows`` bins over (y, z),
    y-major) and -y and +y (``bins[0] x side_rows`` over (x, z), x-major).

    Attributes:
        size: (3,) phantom box size, m.
        bins: (bx, by) number of bins along x and y.
        margin: bins start this far (m) from the faces' edges (as ``top_residuals``).
        side_rows: bins along z on each side face (0: top face only).
        side_tolerance: a side face takes points within this distance (m) of its rest
            plane. A side bulges by a fraction of a millimetre; a top dented near an edge
            dips by several, and with a looser tolerance its points there were taken for
            the side's (measured: -2.3 mm "side residuals" beside a deep top press on a
            session of the replay's own model).
        side_top_margin: side bins end this far (m) below the top face: a press near an
            edge dents the top down to a few millimetres above the probe's depth.
    """

    size: tuple[float, float, float]
    bins: tuple[int, int] = (16, 8)
    margin: float = 0.004
    side_rows: int = 0
    side_tolerance: float = 0.002
    side_top_margin: float = 0.010

    @property
    def top_bins(self) -> int:
        return int(self.bins[0] * self.bins[1])

    def _face_shape(self, face: str) -> tuple[int, int]:
        bx, by = self.bins
        return {"top": (bx, by), "-x": (by, self.side_rows), "+x": (by, self.side_rows),
                "-y": (bx, self.side_rows), "+y": (bx, self.side_rows)}[face]

    def faces(self) -> tuple[str, ...]:
        """The faces that have bins, in bin order."""
        return FACES if self.side_rows > 0 else FACES[:1]

    def face_offsets(self) -> dict[str, int]:
        """First bin index of each face."""
        out, k = {}, 0
        for f in self.faces():
            out[f] = k
            a, b = self._face_shape(f)
            k += a * b
        return out

    @property
    def n_bins(self) -> int:
        return int(sum(a * b for a, b in (self._face_shape(f) for f in self.faces())))

    def face_of_bin(self) -> np.ndarray:
        """(B,) index into :data:`FACES` of each bin's face."""
        out = np.zeros(self.n_bins, dtype=np.int64)
        for f, k in self.face_offsets().items():
            a, b = self._face_shape(f)
            out[k:k + a * b] = FACES.index(f)
        return out

    def _edges(self, face: str) -> tuple[int, int, np.ndarray, np.ndarray]:
        """In-plane axes (u, v) of a face and its bin edges along them, m."""
        axis, _ = _FACE_AXIS[face]
        u, v = [a for a in (0, 1, 2) if a != axis]
        nu, nv = self._face_shape(face)
        m = self.margin
        # side faces: their v axis is z, kept clear of the top's edge by ``side_top_margin``
        top = self.side_top_margin if face != "top" else m
        return u, v, np.linspace(m, self.size[u] - m, nu + 1), np.linspace(m, self.size[v] - top, nv + 1)

    def centres(self) -> np.ndarray:
        """(B, 2) top-face bin centres (x, y), m, phantom frame, x-major order (top bins only)."""
        return self.centres3()[: self.top_bins, :2]

    def centres3(self) -> np.ndarray:
        """(B, 3) bin centres on the rest faces, m, phantom frame, in bin order."""
        out = []
        for f in self.faces():
            axis, high = _FACE_AXIS[f]
            u, v, eu, ev = self._edges(f)
            cu, cv = 0.5 * (eu[1:] + eu[:-1]), 0.5 * (ev[1:] + ev[:-1])
            gu, gv = np.meshgrid(cu, cv, indexing="ij")
            c = np.zeros((gu.size, 3))
            c[:, u], c[:, v] = gu.ravel(), gv.ravel()
            c[:, axis] = self.size[axis] if high else 0.0
            out.append(c)
        return np.concatenate(out)

    def normals3(self) -> np.ndarray:
        """(B, 3) outward unit normal of each bin's rest face, phantom frame, in bin order."""
        out = np.zeros((self.n_bins, 3))
        face_of = self.face_of_bin()
        for fi, f in enumerate(FACES):
            axis, high = _FACE_AXIS[f]
            out[face_of == fi, axis] = 1.0 if high else -1.0
        return out

    def measured_on(self, prepared, grid, element_size):
        """What the residuals are measured on: the box grid ``grid`` (nx, ny, nz) itself
        (``prepared`` and ``element_size`` are not needed; see :class:`PatchLayout`'s)."""
        return tuple(grid)

    def residuals(self, points: np.ndarray, bins: np.ndarray, frames: np.ndarray, positions: np.ndarray,
                  grid) -> np.ndarray:
        """(M,) signed residual of each binned point (M, 3) against its face of the box
        grid ``grid`` (:func:`face_residuals`), m; ``bins`` (M,) its bin, ``frames`` (M,)
        its frame in ``positions`` (F, N, 3)."""
        fb = self.face_of_bin()[bins]
        r = np.empty(points.shape[0])
        for k in np.unique(fb):
            m = fb == k
            r[m] = face_residuals(points[m], positions, grid, self.size, FACES[k], frames=frames[m])
        return r

    def residuals_tangent(self, points: np.ndarray, bins: np.ndarray, frames: np.ndarray, positions: np.ndarray,
                          dpositions: np.ndarray, grid) -> np.ndarray:
        """(p, M) derivatives of :meth:`residuals` along ``dpositions`` (p, F, N, 3)."""
        fb = self.face_of_bin()[bins]
        dr = np.empty((dpositions.shape[0], points.shape[0]))
        for k in np.unique(fb):
            m = fb == k
            dr[:, m] = face_residuals_tangent(points[m], positions, dpositions, grid, self.size, FACES[k], frames[m])
        return dr

    def index(self, points: np.ndarray) -> np.ndarray:
        """(M,) bin index of each (M, 3) point, -1 where no face takes it.

        The top takes what ``top_residuals`` keeps (interior, within 10 mm below the
        top); a side face takes, of the rest, points whose nearest rest face it is,
        within ``side_tolerance`` of it and ``margin`` from its edges."""
        p = np.asarray(points, dtype=np.float64)
        m, (sx, sy, sz) = self.margin, self.size
        keep = (p[:, 0] > m) & (p[:, 0] < sx - m) & (p[:, 1] > m) & (p[:, 1] < sy - m) & (p[:, 2] > sz - 0.010)
        bx, by = self.bins
        i = np.clip(((p[:, 0] - m) / (sx - 2 * m) * bx).astype(int), 0, bx - 1)
        j = np.clip(((p[:, 1] - m) / (sy - 2 * m) * by).astype(int), 0, by - 1)
        out = np.where(keep, i * by + j, -1)
        if self.side_rows <= 0 or p.shape[0] == 0:
            return out
        dist = np.column_stack([np.abs(p[:, 2] - sz), np.abs(p[:, 0]), np.abs(sx - p[:, 0]),
                                np.abs(p[:, 1]), np.abs(sy - p[:, 1])])
        nearest = np.argmin(dist, axis=1)
        offsets = self.face_offsets()
        for fi, f in enumerate(FACES[1:], start=1):
            _, _, eu, ev = self._edges(f)
            u, v = [a for a in (0, 1, 2) if a != _FACE_AXIS[f][0]]
            nu, nv = len(eu) - 1, len(ev) - 1
            take = (~keep) & (nearest == fi) & (dist[:, fi] < self.side_tolerance)
            take &= (p[:, u] > eu[0]) & (p[:, u] < eu[-1]) & (p[:, v] > ev[0]) & (p[:, v] < ev[-1])
            a = np.clip(((p[:, u] - eu[0]) / (eu[-1] - eu[0]) * nu).astype(int), 0, nu - 1)
            b = np.clip(((p[:, v] - ev[0]) / (ev[-1] - ev[0]) * nv).astype(int), 0, nv - 1)
            out = np.where(take, offsets[f] + a * nv + b, out)
        return out


def face_residuals(points: np.ndarray, positions: np.ndarray, grid, size, face: str,
                   frames: np.ndarray | None = None) -> np.ndarray:
    """Signed normal residuals (m) of measured points against one face of the model.

    Args:
        points: (M, 3) measured points already assigned to ``face``, m, phantom frame.
        positions: (N, 3) node positions of the grid mesh (grid-major order), m; or
            (F, N, 3) positions of F frames, with ``frames`` (M,) int giving each point's frame.
        grid: (nx, ny, nz). size: (3,) box size, m. face: one of :data:`FACES`.

    Returns:
        (M,) ``(p - model) . n`` for the face's outward normal ``n``: the point's normal
        coordinate minus the model face's, bilinear in the face's deformed nodes (cells
        located on the rest grid, in-plane node motion corrected to first order), as
        ``top_residuals`` does for the top (:func:`core.diagnosis.field_kernels._point_residual`).
    """
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    if pos.ndim == 2:
        pos = pos[None]
        frames = np.zeros(len(points), dtype=np.int64)
    gi, gf = face_geometry(grid, size)
    return face_residuals_kernel(np.ascontiguousarray(points, dtype=np.float64), pos,
                                 np.asarray(frames, dtype=np.int64), gi, gf, FACES.index(face))


def face_residuals_tangent(points: np.ndarray, positions: np.ndarray, dpositions: np.ndarray, grid, size,
                           face: str, frames: np.ndarray) -> np.ndarray:
    """Derivatives of :func:`face_residuals` along p directions of the node positions.

    Args:
        points: (M, 3) measured points of ``face``, m. positions: (F, N, 3) node positions,
            m; dpositions: (p, F, N, 3) their derivatives. frames: (M,) int frame of each point.

    Returns:
        (p, M) d residual, m per unit of each direction (the points' cells held, as the
        residual is bilinear within them).
    """
    gi, gf = face_geometry(grid, size)
    return face_residuals_tangent_kernel(np.ascontiguousarray(points, dtype=np.float64),
                                         np.ascontiguousarray(positions, dtype=np.float64),
                                         np.ascontiguousarray(dpositions, dtype=np.float64),
                                         np.asarray(frames, dtype=np.int64), gi, gf, FACES.index(face))


def residual_field_tangent(positions: np.ndarray, dpositions: np.ndarray, grid, layout: FieldLayout, points, bins,
                           counts) -> np.ndarray:
    """Derivatives (p, F, B) of :func:`residual_field`'s bin means along p directions of the
    node positions (``dpositions`` (p, F, N, 3)), m per unit of each direction; zero where a
    bin is empty or a frame diverged. Arguments as :func:`residual_field`."""
    F, B = counts.shape
    n_dir = dpositions.shape[0]
    out = np.zeros((n_dir, F, B))
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    ok = _ok_frames(pos, bins)
    if not np.any(ok) or n_dir == 0:
        return out
    if isinstance(layout, FieldLayout):
        dpos = np.ascontiguousarray(dpositions, dtype=np.float64)
        flat = _flat(points, bins)
        gi, gf = face_geometry(grid, layout.size)
        face_of = layout.face_of_bin()
        for frames in _blocks(flat.kstart, np.flatnonzero(ok)):
            box_field_tangent(flat.points, flat.cstart, flat.kept, flat.kstart, flat.bins, frames, pos, dpos,
                              face_of, gi, gf, counts, out)
            flat.release()
        return out
    n = np.where(ok[:, None], counts, 0).astype(np.float64)
    sums = np.zeros((n_dir, F * B))
    for fr, pts, bn in _chunks(points, bins, np.flatnonzero(ok)):
        dr = layout.residuals_tangent(pts, bn, fr, pos, dpositions, grid)
        flat_index = fr * B + bn
        for t in range(n_dir):
            sums[t] += np.bincount(flat_index, weights=dr[t], minlength=F * B)
    for t in range(n_dir):
        out[t] = np.divide(sums[t].reshape(F, B), n, out=np.zeros((F, B)), where=n > 0)
    return out


CHUNK_POINTS = 1_000_000
"""Binned points per pass of :func:`residual_field` and :func:`residual_field_tangent`: whole
frames are taken together up to about this many points, and a mapped sequence's pages are
released after each pass, so a paper-size sequence (1800 frames of ~15k points) is never
resident, nor copied, at once."""


def _ok_frames(pos: np.ndarray, bins) -> np.ndarray:
    """(F,) bool: frames with binned points and finite node positions (``pos`` (F, N, 3))."""
    finite = np.isfinite(pos).reshape(pos.shape[0], -1).all(axis=1)
    return finite & np.array([len(bins[f]) > 0 for f in range(pos.shape[0])], dtype=bool)


def _blocks(kstart: np.ndarray, use: np.ndarray):
    """Yield (n,) int64 runs of the frames ``use``, whole frames, about :data:`CHUNK_POINTS`
    binned points each (``kstart`` (F + 1,): first binned point of each frame)."""
    start = 0
    sizes = kstart[use + 1] - kstart[use]
    while start < use.size:
        stop, k = start, 0
        while stop < use.size and (stop == start or k + sizes[stop] <= CHUNK_POINTS):
            k += sizes[stop]
            stop += 1
        yield np.ascontiguousarray(use[start:stop], dtype=np.int64)
        start = stop


def _chunks(points, bins, use: np.ndarray):
    """Yield (frame index (K,) int64, points (K, 3) float64, bins (K,) int64) over the frames
    ``use``, whole frames at a time, about :data:`CHUNK_POINTS` points per chunk (each
    frame's points are read once: ``points`` may gather them from mapped clouds)."""
    kstart = np.concatenate([[0], np.cumsum([len(bins[f]) for f in range(len(bins))])]).astype(np.int64)
    for frames in _blocks(kstart, np.asarray(use, dtype=np.int64)):
        chunk = (np.concatenate([np.full(len(bins[f]), f, dtype=np.int64) for f in frames]),
                 np.concatenate([np.asarray(points[f], dtype=np.float64) for f in frames]),
                 np.concatenate([np.asarray(bins[f], dtype=np.int64) for f in frames]))
        if isinstance(points, KeptPoints):
            points.release()  # the chunk is copied out: its mapped pages can go
        yield chunk


class Ragged(SequenceABC):
    """F arrays stored as one flat (K, ...) array and (F + 1,) int64 ``starts``: ``self[f]``
    is the view ``flat[starts[f]:starts[f + 1]]``. ``nbytes``: the flat array's bytes.

    Raises:
        ValueError: ``starts`` does not rise from 0 to ``len(flat)``.
    """

    def __init__(self, flat: np.ndarray, starts: np.ndarray):
        starts = np.asarray(starts, dtype=np.int64)
        if starts.ndim != 1 or starts.size < 1 or starts[0] != 0 or starts[-1] != len(flat) or np.any(np.diff(starts) < 0):
            raise ValueError(f"ragged starts must rise from 0 to {len(flat)}")
        self.flat, self.starts = flat, starts

    def __len__(self) -> int:
        return int(self.starts.size - 1)

    def __getitem__(self, f):
        if isinstance(f, slice):
            return [self[i] for i in range(*f.indices(len(self)))]
        f = range(len(self))[f]
        return self.flat[self.starts[f]:self.starts[f + 1]]

    @property
    def nbytes(self) -> int:
        return int(self.flat.nbytes)


class KeptPoints(SequenceABC):
    """The binned points of each frame, read from the clouds when asked for.

    ``index[f]`` (a :class:`Ragged` of int32) indexes the points of ``clouds[f]`` that fall
    in a bin; ``self[f]`` is ``clouds[f][index[f]]`` ((K_f, 3), the clouds' dtype, m,
    phantom frame), gathered on each access. A worker keeps these for every sequence it
    replays: 4 bytes a point instead of a float32 copy's 12, the coordinates staying in the
    (mapped, shared, releasable) clouds; the compiled field reads them in place
    (:func:`core.diagnosis.field_kernels.box_field`). ``nbytes``: the indices' bytes.

    Raises:
        ValueError: ``clouds`` and ``index`` differ in their number of frames.
    """

    def __init__(self, clouds, index: Ragged):
        if len(clouds) != len(index):
            raise ValueError(f"{len(clouds)} frames of clouds but {len(index)} of kept indices")
        self.clouds, self.index = clouds, index

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, f):
        if isinstance(f, slice):
            return [self[i] for i in range(*f.indices(len(self)))]
        return np.asarray(self.clouds[f])[self.index[f]]

    @property
    def nbytes(self) -> int:
        return self.index.nbytes

    def release(self) -> bool:
        """Drop the clouds' mapped pages from the resident set
        (:func:`core.preparation.release_pages`); True when pages were released."""
        return release_pages(self.clouds)


@dataclass
class _Flat:
    """Binned points as :func:`core.diagnosis.field_kernels.box_field` reads them."""

    points: np.ndarray
    cstart: np.ndarray
    kept: np.ndarray
    kstart: np.ndarray
    bins: np.ndarray
    source: object = None

    def release(self) -> None:
        if isinstance(self.source, KeptPoints):
            self.source.release()


def _flat(points, bins) -> _Flat:
    """The binned points and bins as flat arrays: read in place from :func:`frame_bins`'s
    (mapped clouds, indices, bins), else gathered (any F arrays (K_f, 3) and (K_f,))."""
    if isinstance(points, KeptPoints) and isinstance(points.clouds, Clouds) and isinstance(bins, Ragged) \
            and np.array_equal(points.index.starts, bins.starts):
        return _Flat(points.clouds.points, points.clouds.offsets, points.index.flat, bins.starts, bins.flat, points)
    sizes = np.array([len(bins[f]) for f in range(len(bins))], dtype=np.int64)
    kstart = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    gathered = [np.asarray(points[f], dtype=np.float64).reshape(-1, 3) for f in range(len(bins))]
    pts = np.concatenate(gathered) if gathered else np.zeros((0, 3))
    kept = np.arange(kstart[-1], dtype=np.int64) - np.repeat(kstart[:-1], sizes)
    flat_bins = np.concatenate([np.asarray(bins[f], dtype=np.int64) for f in range(len(bins))]) if len(bins) \
        else np.zeros(0, dtype=np.int64)
    return _Flat(pts, kstart, kept, kstart, flat_bins)


def frame_bins(clouds, layout: FieldLayout) -> tuple[KeptPoints, Ragged, np.ndarray]:
    """Per frame: the kept points, their bin indices, and the (F, B) point counts.

    Args:
        clouds: F arrays (M_f, 3) of measured points, m, phantom frame (kept by
            reference: the points are read from them when used), or
            :class:`core.preparation.Clouds`.

    Returns:
        (points: :class:`KeptPoints`, F arrays (K_f, 3) of the clouds' dtype on access;
        bins: F arrays (K_f,) int16 (int32 past 32767 bins), a :class:`Ragged`;
        counts: (F, B) int64). A paper-size sequence (1800 frames of ~15k points) keeps
        ~0.16 GB of indices and bins instead of ~0.43 GB of float32 points and int32 bins.
    """
    kept, idx = [], []
    bin_type = np.int16 if layout.n_bins <= np.iinfo(np.int16).max else np.int32
    counts = np.zeros((len(clouds), layout.n_bins), dtype=np.int64)
    for f, c in enumerate(clouds):
        b = layout.index(c)
        keep = np.flatnonzero(b >= 0)
        kept.append(keep.astype(np.int32))
        idx.append(b[keep].astype(bin_type))
        counts[f] = np.bincount(b[keep], minlength=layout.n_bins)
    starts = np.concatenate([[0], np.cumsum([k.size for k in kept])]).astype(np.int64)
    flat_kept = np.concatenate(kept) if kept else np.zeros(0, dtype=np.int32)
    flat_bins = np.concatenate(idx) if idx else np.zeros(0, dtype=bin_type)
    return KeptPoints(clouds, Ragged(flat_kept, starts)), Ragged(flat_bins, starts), counts


def residual_field(positions: np.ndarray, grid, layout: FieldLayout, points, bins, counts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin means of the signed normal residuals of one simulated sequence.

    Args:
        positions: (F, N, 3) simulated node positions, m, phantom frame.
        grid: (nx, ny, nz) of the mesh, or with a :class:`core.diagnosis.patches.PatchLayout`
            the replayed :class:`core.simulation.mesh.TetMesh`. layout, points, bins,
            counts: from :func:`frame_bins` (or any F arrays (K_f, 3) and (K_f,) of them).

    Returns:
        (field (F, B) float64 mean residual per bin, m (0 where a bin is empty or the
        frame diverged); per noise group of :data:`NOISE_GROUPS`, the within-bin sum of
        squared deviations (6,) m^2 and its degrees of freedom (6,)): the last two
        estimate each face's noise variance. The box's faces are done by one compiled pass
        over the points where they are stored (:func:`core.diagnosis.field_kernels.box_field`),
        a phantom's patches by one vectorised pass per chunk of frames.
    """
    F, B = counts.shape
    field = np.zeros((F, B))
    G = len(NOISE_GROUPS)
    ss, dof = np.zeros(G), np.zeros(G, dtype=np.int64)
    face_of = layout.face_of_bin()
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    ok = _ok_frames(pos, bins)
    if not np.any(ok):
        return field, ss, dof
    n = np.where(ok[:, None], counts, 0)
    points_per_group = np.zeros(G, dtype=np.int64)
    if isinstance(layout, FieldLayout):
        flat = _flat(points, bins)
        gi, gf = face_geometry(grid, layout.size)
        for frames in _blocks(flat.kstart, np.flatnonzero(ok)):
            box_field(flat.points, flat.cstart, flat.kept, flat.kstart, flat.bins, frames, pos, face_of, gi, gf,
                      counts, field, ss, points_per_group)
            flat.release()  # this block's mapped pages can go
    else:
        for fr, pts, bn in _chunks(points, bins, np.flatnonzero(ok)):
            fb = face_of[bn]
            r = layout.residuals(pts, bn, fr, pos, grid)
            flat_index = fr * B + bn
            # a chunk holds whole frames: their bin means are final once it is summed
            sums = np.bincount(flat_index, weights=r, minlength=F * B)
            mean = np.divide(sums, n.ravel(), out=np.zeros(F * B), where=n.ravel() > 0)
            rows = np.unique(fr)
            field[rows] = mean.reshape(F, B)[rows]
            ss += np.bincount(fb, weights=(r - mean[flat_index]) ** 2, minlength=G)
            points_per_group += np.bincount(fb, minlength=G)
    dof = points_per_group - np.bincount(np.broadcast_to(face_of, n.shape)[n > 0], minlength=G)
    return field, ss, dof.astype(np.int64)


def phase_labels(times: np.ndarray, centres: np.ndarray, size, radius: float, *, speed: float = 0.002,
                 depth: np.ndarray | None = None) -> np.ndarray:
    """(F,) phase index into :data:`PHASES` of each frame, from the probe path.

    Args:
        times: (F,) s. centres: (F, 3) probe sphere centres at those times, m, phantom frame.
        size: the rest phantom (:class:`core.preparation.shape.RestShape`), or (3,) the
            size of the box ``[0, size]``, m. radius: probe radius, m.
        speed: indentation rate (m/s) above which a contact counts as loading or
            unloading, and lateral speed above which it counts as sliding.
        depth: (F,) the sphere's depth into the rest phantom at ``centres``, m, when the
            caller has it (a surface's proximity query is not free); None: computed here.

    Indentation is the sphere's depth into the rest phantom (0 when clear): rest when it
    is 0, loading / unloading when it grows / shrinks faster than ``speed``, sliding when
    the probe moves sideways faster than ``speed`` while pressing, holding otherwise.
    """
    if depth is None:
        shape = size if isinstance(size, RestShape) else BoxShape(size)
        depth = shape.penetration_depth(centres, radius) if len(centres) else np.zeros(0)
    depth = np.maximum(np.asarray(depth, dtype=np.float64), 0.0)
    t = np.asarray(times, dtype=np.float64)
    if t.size < 2:
        return np.zeros(t.size, dtype=int)
    rate = np.gradient(depth, t)
    vel = np.gradient(centres, t, axis=0)
    lateral = np.linalg.norm(vel[:, :2], axis=1)
    labels = np.full(t.size, 2, dtype=int)  # holding
    labels[rate > speed] = 1
    labels[rate < -speed] = 3
    labels[(np.abs(rate) <= speed) & (lateral > speed)] = 4
    labels[depth <= 0] = 0
    return labels
