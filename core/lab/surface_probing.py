"""Probe trajectories of the virtual lab on a phantom of any shape (an STL surface).

The box's planner (:func:`core.lab.probing.plan_sequence`) presses into the top and the
side faces; here the contact points are drawn over the *reachable* surface of any
watertight phantom: area-uniformly over the triangles whose outward normal the tool can
press along (the shaft leans out of the surface, ``n . shaft >= min_shaft_cosine``, and
the normal does not point down), above the support by a margin. The motion is the box
planner's: wait above the phantom, travel at a safe height, descend to an approach point
outside the surface along the normal, press along the inward normal to the requested
depth, hold, sometimes slide along the surface (a chord between two surface points),
retract, rest; minimum-jerk between knots (Flash & Hogan 1985). A poke whose travel
would bring the sphere into the phantom (possible on a non-convex surface) is redrawn.

Everything is in the phantom frame (z up, resting on z = 0), SI units.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from core.lab.probing import PathBuilder, Poke, ProbePlan, ProbeTrajectory, ProbingConfig, Stroke, tool_rotation
from core.preparation.shape import SurfaceShape

__all__ = ["ReachableSurface", "plan_surface_sequence", "surface_penetration_depth"]



class ReachableSurface(SurfaceShape):
    """A phantom's rest surface (:class:`core.preparation.shape.SurfaceShape`) with what
    the planner needs of it besides: area-uniform sampling of its triangles.

    Args:
        vertices: (V, 3) float64, m, phantom frame. faces: (F, 3) int64, outward normals.

    Raises:
        ValueError: not a watertight, consistently oriented surface.
    """

    def thickness(self, point: np.ndarray, normal: np.ndarray) -> float:
        """The body's thickness (m) under the surface ``point`` (3,) along its inward
        normal (``-normal``): the distance to where that ray leaves the body (trimesh's
        ray test); the point's height above the support when the ray finds no exit."""
        p, n = np.asarray(point, dtype=np.float64), np.asarray(normal, dtype=np.float64)
        hits, _, _ = self.mesh.ray.intersects_location(p[None] - 1e-6 * n[None], -n[None])
        d = np.linalg.norm(hits - p, axis=1) if len(hits) else np.zeros(0)
        d = d[d > 1e-5]
        return float(d.min()) if d.size else float(max(p[2], 0.0))

    def sample(self, rng: np.random.Generator, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One point drawn area-uniformly on the ``allowed`` (F,) bool triangles, and its
        outward normal."""
        weights = self.areas * allowed
        f = int(rng.choice(weights.size, p=weights / weights.sum()))
        a, b = rng.random(2)
        if a + b > 1.0:
            a, b = 1.0 - a, 1.0 - b
        tri = self.mesh.vertices[self.mesh.faces[f]]
        return tri[0] + a * (tri[1] - tri[0]) + b * (tri[2] - tri[0]), self.normals[f]


def surface_penetration_depth(centres: np.ndarray, surface: ReachableSurface, radius: float) -> np.ndarray:
    """(K,) how deep a sphere of ``radius`` at ``centres`` (K, 3) reaches into the rest
    phantom, m (``radius - clearance``; negative when clear): the STL counterpart of
    :func:`core.lab.probing.penetration_depth`."""
    return surface.penetration_depth(centres, radius)


def plan_surface_sequence(
    rng: np.random.Generator,
    *,
    surface: ReachableSurface,
    radius: float,
    duration: float,
    config: ProbingConfig = ProbingConfig(),
    tool_azimuth: float | None = None,
    min_shaft_cosine: float = 0.3,
) -> ProbePlan:
    """Plan random pokes over the reachable surface of any phantom (module docstring).

    Args:
        rng: the only source of randomness.
        surface: the rest surface (:class:`ReachableSurface`).
        radius: the probe's true radius, m.
        duration: sequence length, s.
        config: depths, speeds, holds, slides, clearances, tilt range and margins of the
            box planner (``edge_margin`` is unused: a curved surface has no face edges;
            ``bottom_margin`` keeps contacts this far above the support plus a radius;
            ``top_region`` (x0, y0, x1, y1) keeps contact points over that rectangle;
            ``max_strain`` caps a press's depth by the thickness under it;
            ``side_probability`` and ``face_cycle`` are unused).
        tool_azimuth: direction (rad) the shaft leans towards; random if None.
        min_shaft_cosine: smallest ``n . shaft`` of a pressed surface point.

    Returns:
        A :class:`ProbePlan`; each poke's ``face`` is ``"+z"`` where the surface faces up
        (normal within 25 degrees of +z) and ``"surface"`` elsewhere.

    Raises:
        ValueError: no reachable surface for this tool, or too short for one poke.
    """
    cfg = config
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    tilt = np.deg2rad(rng.uniform(*cfg.tilt_range_deg))
    azimuth = rng.uniform(0, 2 * np.pi) if tool_azimuth is None else float(tool_azimuth)
    R = tool_rotation(tilt, azimuth, rng.uniform(-np.pi, np.pi))
    shaft = -R[:, 2]
    centroids = surface.mesh.triangles_center
    allowed = ((surface.normals @ shaft >= min_shaft_cosine) & (surface.normals[:, 2] >= 0.05)
               & (centroids[:, 2] >= cfg.bottom_margin + radius))
    if cfg.top_region is not None:  # contacts over an (x, y) rectangle, as the box's top pokes
        x0, y0, x1, y1 = cfg.top_region
        allowed &= (centroids[:, 0] >= x0) & (centroids[:, 0] <= x1) & (centroids[:, 1] >= y0) & (centroids[:, 1] <= y1)
    if not np.any(allowed):
        raise ValueError("no part of the phantom's surface can be pressed with this tool tilt"
                         + (f" in top_region {cfg.top_region}" if cfg.top_region is not None else ""))
    bounds = surface.mesh.bounds
    z_safe = surface.top + radius + cfg.safe_height
    centre_xy = 0.5 * (bounds[0, :2] + bounds[1, :2])
    start = np.array([centre_xy[0] + rng.uniform(-0.01, 0.01), centre_xy[1] + rng.uniform(-0.005, 0.005),
                      z_safe + rng.uniform(0.0, 0.01)])
    b = PathBuilder(start)
    b.wait(rng.uniform(*cfg.start_rest_range))
    pokes: list[Poke] = []
    failures = 0
    while failures < (3 if pokes else 50):
        snap = b.snapshot()
        t_start = b.now
        point, n = surface.sample(rng, allowed)
        slide_to = slide_speed = None
        if rng.random() < cfg.slide_probability:
            tangent = np.cross(n, rng.standard_normal(3))
            tangent /= max(np.linalg.norm(tangent), 1e-12)
            target, n2 = surface.project(point + rng.uniform(*cfg.slide_length_range) * tangent)
            if np.linalg.norm(target[0] - point) > 0.002 and float(n2[0] @ shaft) >= min_shaft_cosine \
                    and target[0][2] >= cfg.bottom_margin + radius:
                slide_to = target[0]
                slide_speed = float(rng.uniform(*cfg.slide_speed_range))
        stroke = Stroke.draw(rng, cfg, point, n, radius, slide_to, z_safe)
        if cfg.max_strain is not None:  # the drawn depth, capped by the body's thickness under the contact
            cap = cfg.max_strain * surface.thickness(point, n)
            if slide_to is not None:
                cap = min(cap, cfg.max_strain * surface.thickness(slide_to, surface.project(slide_to[None])[1][0]))
            if stroke.depth > cap:
                stroke = replace(stroke, depth=float(cap))
        retract = stroke.retract
        travel = np.concatenate([np.linspace(stroke.above, stroke.approach, 12),
                                 np.linspace(retract, [retract[0], retract[1], z_safe], 12)])
        if np.any(surface.clearance(travel) < radius + 0.5 * stroke.clearance):
            failures += 1  # the descent would touch the phantom (a non-convex surface)
            continue
        stroke.execute(b, rng, cfg, slide_speed)
        depth, speed, hold = stroke.depth, stroke.speed, stroke.hold
        if b.now > duration:
            b.rollback(snap)
            failures += 1
            continue
        face = "+z" if n[2] >= np.cos(np.deg2rad(25.0)) else "surface"
        pokes.append(Poke(face, point, depth, speed, hold, slide_to, slide_speed, t_start, b.now))
    if not pokes:
        raise ValueError(f"a sequence of {duration} s is too short for one poke")
    if b.now < duration:
        b.wait(duration - b.now)
    return ProbePlan(ProbeTrajectory(np.asarray(b.t), np.asarray(b.p)), tuple(pokes), R, float(duration))
