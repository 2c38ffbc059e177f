"""The phantom's rest shape: what every stage asks of it besides the mesh.

Contacts, presses and effect placement need the same few geometric questions answered
of the rest phantom, whatever its shape: how far a point is from its surface (signed:
positive outside), the nearest surface point and its outward normal, and where a sphere
fits inside it. :class:`BoxShape` answers them analytically for the paper's box
``[0, size]`` (the session without ``phantom.stl``); :class:`SurfaceShape` answers them
on a watertight triangle surface (``phantom.stl``) with trimesh's proximity queries
(closest point on the triangles; the sign from a winding-number containment test).

Everything is in the phantom frame (z up, resting on z = 0), SI units.
"""

from __future__ import annotations

from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

__all__ = ["RestShape", "BoxShape", "SurfaceShape", "rest_shape"]


class RestShape:
    """The rest phantom's geometry (abstract; see :class:`BoxShape`, :class:`SurfaceShape`).

    Attributes:
        size: (3,) float64, m: the upper corner of its bounding box (the box's size).
        lower: (3,) float64, m: the lower corner of its bounding box (the box's origin).
    """

    size: np.ndarray
    lower: np.ndarray = np.zeros(3)
    is_box: bool = False

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """(K,) float64 signed distance of ``points`` (K, 3) from the rest surface, m:
        positive outside, negative inside."""
        raise NotImplementedError

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest rest-surface points (K, 3) of ``points`` (K, 3) and the outward unit
        normals (K, 3) there, m, phantom frame."""
        raise NotImplementedError

    def penetration_depth(self, centres: np.ndarray, radius: float) -> np.ndarray:
        """(K,) how deep a sphere of ``radius`` (m) at ``centres`` (K, 3) reaches into the
        rest phantom, m: ``radius - clearance`` (negative when clear of it)."""
        return float(radius) - self.clearance(centres)

    def keep_inside(self, centre, radius: float) -> np.ndarray:
        """(3,) float64: ``centre`` (3,) m moved, if needed, so that a sphere of ``radius``
        (m) around it lies inside the rest phantom (as far as it fits: a sphere wider than
        the phantom stays where the last move put it)."""
        raise NotImplementedError

    def summit(self) -> tuple[np.ndarray, np.ndarray]:
        """The rest surface's highest point (3,) and its outward unit normal (3,), m,
        phantom frame: where a probe presses when nothing else says where."""
        raise NotImplementedError


class BoxShape(RestShape):
    """The box ``[0, size]`` (phantom frame), answered in closed form.

    Args:
        size: (3,) box size, m (x length, y width, z height).

    Raises:
        ValueError: not three positive lengths.
    """

    is_box = True

    def __init__(self, size):
        s = np.asarray(size, dtype=np.float64).reshape(-1)
        if s.shape != (3,) or not np.all(s > 0):
            raise ValueError(f"a box size is 3 positive lengths in m, got {size!r}")
        self.size = s

    def clearance(self, points):
        c = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        d_out = np.maximum(np.maximum(-c, c - self.size), 0.0)
        outside = np.linalg.norm(d_out, axis=1)
        inside = np.min(np.concatenate([c, self.size - c], axis=1), axis=1)
        return np.where(outside > 0, outside, -np.maximum(inside, 0.0))

    def project(self, points):
        c = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        # signed distance to each of the six face planes, positive outside: -x, +x, -y, +y, -z, +z
        planes = np.concatenate([-c, c - self.size], axis=1)[:, [0, 3, 1, 4, 2, 5]]
        face = np.argmax(planes, axis=1)  # outside: the face it is furthest beyond; inside: the nearest
        axis, upper = face // 2, face % 2 == 1
        q = np.clip(c, 0.0, self.size)
        rows = np.arange(c.shape[0])
        q[rows, axis] = np.where(upper, self.size[axis], 0.0)
        n = np.zeros_like(c)
        n[rows, axis] = np.where(upper, 1.0, -1.0)
        return q, n

    def keep_inside(self, centre, radius):
        return np.clip(np.asarray(centre, dtype=np.float64), float(radius), self.size - float(radius))

    def summit(self):
        """The middle of the top face, normal +z."""
        return np.array([self.size[0] / 2, self.size[1] / 2, self.size[2]]), np.array([0.0, 0.0, 1.0])


class SurfaceShape(RestShape):
    """A watertight triangle surface (the session's ``phantom.stl``), answered with
    trimesh's proximity queries.

    Args:
        vertices: (V, 3) float64, m, phantom frame. faces: (F, 3) int64, outward normals.

    Raises:
        ValueError: not a watertight surface enclosing a positive volume.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh  # noqa: PLC0415 (heavy)

        self.mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                                    process=True)
        if not self.mesh.is_watertight or self.mesh.volume <= 0:
            raise ValueError("the phantom surface must be watertight with outward normals")
        self.normals = np.asarray(self.mesh.face_normals, dtype=np.float64)
        self.areas = np.asarray(self.mesh.area_faces, dtype=np.float64)
        self.size = np.maximum(np.asarray(self.mesh.bounds[1], dtype=np.float64), 1e-9)
        self.lower = np.asarray(self.mesh.bounds[0], dtype=np.float64)
        self.top = float(self.mesh.bounds[1, 2])
        self._query = trimesh.proximity.ProximityQuery(self.mesh)

    def clearance(self, points):
        return -np.asarray(self._query.signed_distance(np.asarray(points, dtype=np.float64).reshape(-1, 3)))

    def project(self, points):
        closest, _, tri = self._query.on_surface(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        return np.asarray(closest, dtype=np.float64), self.normals[tri]

    def keep_inside(self, centre, radius):
        """See :meth:`RestShape.keep_inside`: alternating moves off the nearest surface
        point along its inward normal (a few suffice away from edges); where they do not
        settle (a wedge, such as a dome's rim), the point of the segment towards the
        shape's deepest interior point (:attr:`deepest`) nearest to ``centre`` that fits,
        by bisection."""
        r = float(radius)
        c = np.clip(np.asarray(centre, dtype=np.float64).reshape(3), self.mesh.bounds[0] + r, self.mesh.bounds[1] - r)
        for _ in range(6):  # a move off one face can bring it near another (an edge, a thin part)
            if float(self.clearance(c[None])[0]) <= -0.999 * r:
                return c
            p, n = self.project(c[None])
            c = p[0] - 1.001 * r * n[0]
        if float(self.clearance(c[None])[0]) <= -0.999 * r:
            return c
        anchor = self.deepest
        if float(self.clearance(anchor[None])[0]) > -0.999 * r:
            return anchor.copy()  # nothing fits: as deep as the shape allows
        lo, hi = 0.0, 1.0  # fraction of the way from c to the anchor: hi fits, lo does not
        for _ in range(20):
            mid = 0.5 * (lo + hi)
            if float(self.clearance((c + mid * (anchor - c))[None])[0]) <= -0.999 * r:
                hi = mid
            else:
                lo = mid
        return c + hi * (anchor - c)

    def summit(self):
        """The surface point nearest to 10 mm above the highest vertex (a dome's apex) and
        its normal (copies: the point is computed once)."""
        p, n = self._summit
        return p.copy(), n.copy()

    @cached_property
    def _summit(self) -> tuple[np.ndarray, np.ndarray]:
        v = np.asarray(self.mesh.vertices)
        p, n = self.project((v[int(np.argmax(v[:, 2]))] + np.array([0.0, 0.0, 0.01]))[None])
        return p[0], n[0]

    @cached_property
    def deepest(self) -> np.ndarray:
        """(3,) float64, m: the interior point farthest from the surface, among a 12^3
        grid over the bounds refined once around the best (the centre of the largest
        sphere that fits, to about a twelfth of the bounds' extent)."""
        lo, hi = self.mesh.bounds
        best = 0.5 * (lo + hi)
        for span in (hi - lo, (hi - lo) / 6.0):
            axes = [np.linspace(b - w / 2, b + w / 2, 12) for b, w in zip(best, span)]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
            best = grid[int(np.argmin(self.clearance(grid)))]
        return best


@lru_cache(maxsize=8)
def _surface_of_stl(path: str, mtime_ns: int, size_bytes: int) -> SurfaceShape:
    import trimesh  # noqa: PLC0415 (heavy)

    m = trimesh.load_mesh(path, file_type="stl", process=True)
    return SurfaceShape(np.asarray(m.vertices), np.asarray(m.faces))


def rest_shape(size, stl_path: str | Path | None = None) -> RestShape:
    """The rest shape of a session: its ``phantom.stl`` when given, else the box of ``size``.

    Args:
        size: (3,) box size, m. stl_path: ``phantom.stl`` (phantom frame, m) or None.

    Returns:
        A :class:`SurfaceShape` (cached per file and modification time) or a :class:`BoxShape`.

    Raises:
        ValueError: ``stl_path`` names an STL that is not a watertight surface (with the file's name).
    """
    if stl_path is None:
        return BoxShape(size)
    p = Path(stl_path)
    st = p.stat()
    try:
        return _surface_of_stl(str(p.resolve()), st.st_mtime_ns, st.st_size)
    except ValueError as exc:
        raise ValueError(f"{p}: {exc}") from exc
