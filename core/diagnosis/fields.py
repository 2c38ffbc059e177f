"""Residual fields: where and when the replayed surface disagrees with the measured one.

The observable is the top face, which the camera sees from above: per frame, every
measured point over the top face's interior gets its signed vertical residual
``z_point - z_model(x, y)`` (:func:`core.identification.residuals.top_residuals`; on the
top face this is the signed distance along the surface normal to first order), and the
residuals are averaged in a fixed grid of bins on the rest top face. A run of the model
is thus an (F, B) field of bin means with fixed (F, B) point counts, which is what the
candidate signatures and fits of :mod:`core.diagnosis.engine` work on. Side faces are
seen at grazing angles by the cameras of this field and are left out of the fits; the
paper's point-to-mesh error, which includes them, is what gains are reported in.

Noise is separated from systematic error by the scatter of points inside a bin and
frame: for a smooth surface that scatter is the sensor noise, and a bin mean of ``n``
points has variance ``sigma^2 / n`` under noise alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.identification.residuals import top_residuals

__all__ = ["FieldLayout", "frame_bins", "residual_field", "phase_labels", "PHASES"]

PHASES = ("rest", "loading", "holding", "unloading", "sliding")
"""Labels of :func:`phase_labels`, in this order."""


@dataclass(frozen=True)
class FieldLayout:
    """A grid of bins over the interior of the rest top face.

    Attributes:
        size: (3,) phantom box size, m.
        bins: (bx, by) number of bins along x and y.
        margin: bins start this far (m) from the face's edges (as ``top_residuals``).
    """

    size: tuple[float, float, float]
    bins: tuple[int, int] = (16, 8)
    margin: float = 0.004

    @property
    def n_bins(self) -> int:
        return int(self.bins[0] * self.bins[1])

    def centres(self) -> np.ndarray:
        """(B, 2) bin centres (x, y), m, phantom frame, x-major order."""
        bx, by = self.bins
        ex = np.linspace(self.margin, self.size[0] - self.margin, bx + 1)
        ey = np.linspace(self.margin, self.size[1] - self.margin, by + 1)
        cx, cy = 0.5 * (ex[1:] + ex[:-1]), 0.5 * (ey[1:] + ey[:-1])
        return np.stack(np.meshgrid(cx, cy, indexing="ij"), axis=-1).reshape(-1, 2)

    def index(self, points: np.ndarray) -> np.ndarray:
        """(M,) bin index of each (M, 3) point, -1 where ``top_residuals`` drops it."""
        p = np.asarray(points, dtype=np.float64)
        m, (sx, sy, sz) = self.margin, self.size
        keep = (p[:, 0] > m) & (p[:, 0] < sx - m) & (p[:, 1] > m) & (p[:, 1] < sy - m) & (p[:, 2] > sz - 0.010)
        bx, by = self.bins
        i = np.clip(((p[:, 0] - m) / (sx - 2 * m) * bx).astype(int), 0, bx - 1)
        j = np.clip(((p[:, 1] - m) / (sy - 2 * m) * by).astype(int), 0, by - 1)
        return np.where(keep, i * by + j, -1)


def frame_bins(clouds, layout: FieldLayout) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Per frame: the kept points, their bin indices, and the (F, B) point counts.

    Args:
        clouds: F arrays (M_f, 3) of measured points, m, phantom frame.

    Returns:
        (points: F arrays (K_f, 3), bins: F int arrays (K_f,), counts: (F, B) int64).
    """
    pts, idx = [], []
    counts = np.zeros((len(clouds), layout.n_bins), dtype=np.int64)
    for f, c in enumerate(clouds):
        b = layout.index(c)
        keep = b >= 0
        pts.append(np.asarray(c, dtype=np.float64)[keep])
        idx.append(b[keep])
        counts[f] = np.bincount(b[keep], minlength=layout.n_bins)
    return pts, idx, counts


def residual_field(positions: np.ndarray, grid, layout: FieldLayout, points, bins, counts) -> tuple[np.ndarray, float, int]:
    """Bin means of the signed top residuals of one simulated sequence.

    Args:
        positions: (F, N, 3) simulated node positions, m, phantom frame.
        grid: (nx, ny, nz) of the mesh. layout, points, bins, counts: from :func:`frame_bins`.

    Returns:
        (field (F, B) float64 mean residual per bin, m (0 where a bin is empty or the
        frame diverged), within-bin sum of squared deviations, m^2, and its degrees of
        freedom): the last two estimate the noise variance.
    """
    F, B = counts.shape
    field = np.zeros((F, B))
    ss, dof = 0.0, 0
    for f in range(F):
        if points[f].shape[0] == 0 or not np.all(np.isfinite(positions[f])):
            continue
        r = top_residuals(points[f], positions[f], grid, layout.size, layout.margin)
        sums = np.bincount(bins[f], weights=r, minlength=B)
        n = counts[f]
        mean = np.divide(sums, n, out=np.zeros(B), where=n > 0)
        field[f] = mean
        ss += float(np.sum((r - mean[bins[f]]) ** 2))
        dof += int(r.size - np.count_nonzero(n))
    return field, ss, dof


def phase_labels(times: np.ndarray, centres: np.ndarray, size, radius: float, *, speed: float = 0.002) -> np.ndarray:
    """(F,) phase index into :data:`PHASES` of each frame, from the probe path.

    Args:
        times: (F,) s. centres: (F, 3) probe sphere centres at those times, m, phantom frame.
        size: (3,) box size, m. radius: probe radius, m.
        speed: indentation rate (m/s) above which a contact counts as loading or
            unloading, and lateral speed above which it counts as sliding.

    Indentation is the sphere's depth into the rest box (0 when clear): rest when it is
    0, loading / unloading when it grows / shrinks faster than ``speed``, sliding when
    the probe moves sideways faster than ``speed`` while pressing, holding otherwise.
    """
    size = np.asarray(size, dtype=np.float64)
    inside = np.clip(centres, 0.0, size)
    gap = np.linalg.norm(centres - inside, axis=1)
    depth_out = np.maximum(radius - gap, 0.0)
    depth_in = np.min(np.concatenate([centres, size - centres], axis=1), axis=1) + radius
    depth = np.where(gap > 0, depth_out, depth_in)
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
