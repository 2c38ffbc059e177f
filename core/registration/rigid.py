"""Closed-form rigid (and similarity) point-set registration, and robot calibration.

* :func:`kabsch` -- least-squares rotation + translation (+ optional uniform scale)
  between paired points: Kabsch 1976 (Acta Cryst. A32:922), with the reflection-safe
  SVD correction and the scale estimate of Umeyama 1991 (IEEE TPAMI 13(4):376).
* :func:`calibrate_robot` -- ``T_phantom_robot`` from probe touches of the phantom's top
  corners, as in Wu et al. 2020, Sec. 3.2 ("we move the robot to touch each of the four
  corners of the phantom ... and perform a rigid registration").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.errors import RegistrationError

__all__ = ["RigidFit", "kabsch", "register_touches", "calibrate_robot", "corner_points_phantom", "apply_transform"]

#: Phantom-frame (x, y) of each corner label, as fractions of the phantom size
#: (``SESSION_FORMAT.md``, calibration/corners.csv).
_CORNER_XY: dict[str, tuple[int, int]] = {
    "x0y0": (0, 0),
    "x1y0": (1, 0),
    "x0y1": (0, 1),
    "x1y1": (1, 1),
}


@dataclass(frozen=True)
class RigidFit:
    """Result of a paired-point rigid registration.

    Attributes:
        T: (4, 4) float64 homogeneous transform ``T_target_source``: maps source-frame
            points into the target frame (``target ~= scale * R @ source + t``).
        rms: root-mean-square of ``residuals``, m (units of the input points).
        residuals: (N,) float64 Euclidean distance of each transformed source point to
            its target, m.
        scale: uniform scale folded into ``T[:3, :3]`` (1.0 for a rigid fit).
    """

    T: np.ndarray
    rms: float
    residuals: np.ndarray
    scale: float = 1.0


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (N, 3) points through a (4, 4) homogeneous transform; returns (N, 3) float64."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def _check_points(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite values")
    return a


def kabsch(
    source: np.ndarray,
    target: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    with_scale: bool = False,
) -> RigidFit:
    """Least-squares transform taking paired ``source`` points onto ``target`` points.

    Minimises ``sum_i w_i |s R p_i + t - q_i|^2`` over rotations ``R`` (det +1, never a
    reflection), translations ``t`` and, when ``with_scale``, a uniform scale ``s > 0``.
    Kabsch 1976; reflection correction and scale as in Umeyama 1991, Eqs. 39-42.

    Args:
        source: (N, 3) float, points ``p_i`` in the source frame, m.
        target: (N, 3) float, the matching points ``q_i`` in the target frame, m.
        weights: optional (N,) non-negative weights (need not sum to one); at least
            three points must have positive weight.
        with_scale: also estimate a uniform scale (Umeyama similarity transform).

    Returns:
        :class:`RigidFit` with ``T = T_target_source`` (scale folded into the 3x3 block).

    Raises:
        ValueError: shapes differ or are not (N, 3), fewer than 3 points, non-finite
            values, bad weights, or degenerate (coincident / collinear) source or target
            points, for which the rotation is not determined.
    """
    src = _check_points("source", source)
    dst = _check_points("target", target)
    if src.shape != dst.shape:
        raise ValueError(f"source and target must have the same shape, got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if weights is None:
        w = np.full(n, 1.0 / max(n, 1))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (n,):
            raise ValueError(f"weights must be ({n},), got {w.shape}")
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weights must be finite and non-negative")
    if np.count_nonzero(w > 0) < 3:
        raise ValueError(f"need at least 3 points with positive weight, got {np.count_nonzero(w > 0)}")
    w = w / w.sum()

    mu_s = w @ src
    mu_d = w @ dst
    xs = src - mu_s
    xd = dst - mu_d

    # Degeneracy: the weighted source and target spreads must span a plane (rank >= 2).
    scale_ref = max(np.sqrt(w @ np.sum(xs**2, axis=1)), np.sqrt(w @ np.sum(xd**2, axis=1)), 1e-300)
    for name, x in (("source", xs), ("target", xd)):
        sv = np.linalg.svd(np.sqrt(w)[:, None] * x, compute_uv=False)
        if sv[1] <= 1e-9 * max(scale_ref, 1e-12) or sv[1] <= 1e-8 * sv[0]:
            raise ValueError(
                f"{name} points are degenerate (coincident or collinear): singular values {sv}; "
                "the rotation is not determined"
            )

    cov = (w[:, None] * xd).T @ xs  # (3, 3) = sum w q p^T
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    if d == 0:
        d = 1.0
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    if with_scale:
        var_s = w @ np.sum(xs**2, axis=1)
        s = float(np.trace(np.diag(S) @ D) / var_s)
    else:
        s = 1.0
    t = mu_d - s * R @ mu_s

    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = t
    residuals = np.linalg.norm(apply_transform(T, src) - dst, axis=1)
    rms = float(np.sqrt(np.mean(residuals**2)))
    return RigidFit(T=T, rms=rms, residuals=residuals, scale=s)


def corner_points_phantom(
    labels: Sequence[str], phantom_size: np.ndarray, probe_radius: float
) -> np.ndarray:
    """Phantom-frame probe-sphere centres for corner touches.

    Args:
        labels: corner labels (``x0y0``, ``x1y0``, ``x0y1``, ``x1y1``), one per touch.
        phantom_size: (3,) box size (sx, sy, sz), m.
        probe_radius: probe sphere radius, m.

    Returns:
        (K, 3) float64: corner ``(ix*sx, iy*sy, sz)`` plus ``(0, 0, probe_radius)``.

    Raises:
        ValueError: an unknown label.
    """
    size = np.asarray(phantom_size, dtype=np.float64).reshape(3)
    out = np.empty((len(labels), 3))
    for k, label in enumerate(labels):
        key = str(label).strip().lower()
        if key not in _CORNER_XY:
            raise ValueError(f"unknown corner label {label!r}; expected one of {sorted(_CORNER_XY)}")
        ix, iy = _CORNER_XY[key]
        out[k] = (ix * size[0], iy * size[1], size[2] + probe_radius)
    return out


def calibrate_robot(
    corners,
    phantom_size,
    probe_radius: float,
    *,
    max_rms: float = 0.0015,
) -> RigidFit:
    """Estimate ``T_phantom_robot`` from probe touches of the phantom's top corners.

    Every row of ``corners`` (repeated touches included) is paired with its phantom-frame
    sphere centre (corner + (0, 0, probe_radius)) and a rigid Kabsch fit is solved
    (Wu et al. 2020, Sec. 3.2; Kabsch 1976).

    Args:
        corners: a ``core.io.Corners`` (``.labels`` tuple of str, ``.positions`` (K, 3)
            robot frame, m), or a pair ``(labels, positions)``.
        phantom_size: (3,) box size, m.
        probe_radius: probe sphere radius, m.
        max_rms: largest accepted rms residual, m (default 1.5 mm).

    Returns:
        :class:`RigidFit` with ``T = T_phantom_robot``; residuals per corner row, m.

    Raises:
        RegistrationError: fewer than three distinct corners, or rms > ``max_rms``
            (the message gives the rms in mm and the worst corner).
        ValueError: malformed positions or unknown labels.
    """
    if hasattr(corners, "labels") and hasattr(corners, "positions"):
        labels, positions = corners.labels, corners.positions
    else:
        labels, positions = corners
    labels = tuple(str(s) for s in labels)
    positions = _check_points("corner positions", positions)
    if len(labels) != positions.shape[0]:
        raise ValueError(f"{len(labels)} corner labels for {positions.shape[0]} positions")
    distinct = {s.strip().lower() for s in labels}
    if len(distinct) < 3:
        raise RegistrationError(
            f"need touches of at least 3 distinct corners, got {sorted(distinct)}", fitness=None, rms=None
        )
    target = corner_points_phantom(labels, phantom_size, probe_radius)
    return register_touches(positions, target, labels, what="corner", check="corner labels and probe radius",
                            max_rms=max_rms)


def register_touches(positions: np.ndarray, target: np.ndarray, labels: Sequence[str], *, what: str, check: str,
                     max_rms: float) -> RigidFit:
    """``T_phantom_robot`` by :func:`kabsch` of probe touches (N, 3), robot frame, onto
    their phantom-frame targets (N, 3), m, refused when it does not fit.

    Raises:
        RegistrationError: degenerate points, or rms > ``max_rms`` (the message gives the
            rms in mm, the worst ``what`` of ``labels`` and what to ``check``)."""
    try:
        fit = kabsch(positions, target)
    except ValueError as exc:
        raise RegistrationError(f"{what} registration is degenerate: {exc}") from exc
    if fit.rms > max_rms:
        worst = int(np.argmax(fit.residuals))
        raise RegistrationError(
            f"robot calibration rms {fit.rms * 1e3:.2f} mm exceeds {max_rms * 1e3:.2f} mm; "
            f"worst {what} {labels[worst]!r} (row {worst}) is off by {fit.residuals[worst] * 1e3:.2f} mm "
            f"-- check {check}",
            rms=fit.rms,
        )
    return fit
