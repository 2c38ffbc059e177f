"""The moves a palpation plan chooses from (:mod:`core.diagnosis.planner`): presses and
slides within the robot's limits, on the paper's box or on any phantom's surface.

On the box: presses into the top at a grid of points, slides across the top along x and
along y, presses into the middle of each side face. On any other shape (``phantom.stl``):
presses at the diagnosis's surface patches that a tool can reach from above (spread over
the surface by farthest-point sampling), each along the surface's inward normal, and
slides along the two most upward-facing of them. Every move starts and ends at a safe
height above the phantom, presses no deeper than ``max_depth`` (checked along the whole
path against the rest shape), and moves no faster than ``speed`` in contact.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.errors import TissueTwinError
from core.lab.probing import ProbeTrajectory
from core.preparation.shape import BoxShape, RestShape

__all__ = ["PlanLimits", "PlanError", "Move", "candidate_moves", "surface_moves", "check_move", "move_path",
           "MIN_JERK_PEAK"]

MIN_JERK_PEAK = 15.0 / 8.0
"""Peak over mean speed of a minimum-jerk segment (Flash & Hogan 1985)."""

class PlanError(TissueTwinError):
    """No palpation within the limits can reach the phantom (the message says why)."""


@dataclass(frozen=True)
class PlanLimits:
    """What a plan may ask of the robot.

    Attributes:
        max_depth: deepest indentation of the sphere below the rest surface, m.
        speed: fastest probe speed while in contact, m/s.
        travel_speed: speed of moves in free space, m/s.
        edge_margin: contact points stay this far inside their face's edges, m.
        bottom_margin: side contacts stay this far above the bottom plus a radius, m.
        safe_height: gap between the sphere and the top while travelling, m.
        hold: time held at full depth, s.
        slide_length: length of a slide across the top, m.
        duration: most seconds of probing in the plan.
        camera_rate: frame rate of the camera the plan assumes, Hz (the session's).
    """

    max_depth: float = 0.008
    speed: float = 0.010
    travel_speed: float = 0.03
    edge_margin: float = 0.008
    bottom_margin: float = 0.006
    safe_height: float = 0.010
    hold: float = 1.0
    slide_length: float = 0.010
    duration: float = 20.0
    camera_rate: float = 15.0


@dataclass(frozen=True)
class Move:
    """One candidate move of the probe.

    Attributes:
        name: short id. description: plain language ("slide 10 mm across the top ...").
        face: "+z" or a side face. knots_t: (K,) s from the move's start. knots_p: (K, 3)
            sphere centres, m, phantom frame (minimum-jerk between knots).
    """

    name: str
    description: str
    face: str
    knots_t: np.ndarray
    knots_p: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.knots_t[-1])


def within_duration(moves: list[Move], lim: PlanLimits) -> list[Move]:
    """The moves that fit in the plan's ``lim.duration`` on their own.

    A move is never cut short (its hold and its return to rest are what make it
    informative), so one longer than the whole plan cannot be part of it.

    Raises:
        PlanError: no move fits; the message names the shortest and its length.
    """
    fit = [m for m in moves if m.duration <= lim.duration + 1e-9]
    if not fit:
        shortest = min(moves, key=lambda m: m.duration) if moves else None
        raise PlanError(f"no move fits in a {lim.duration:.1f} s plan" + (
            f": the shortest, {shortest.name}, takes {shortest.duration:.1f} s" if shortest else ""))
    return fit


def press_move(name, description, face, start_above, approach, pressed, slide_to, lim: PlanLimits) -> Move:
    t, p = [0.0], [np.asarray(start_above, float)]

    def go(target, speed):
        target = np.asarray(target, float)
        d = float(np.linalg.norm(target - p[-1]))
        if d > 1e-9:
            # minimum jerk peaks at 15/8 of a segment's mean speed: ``speed`` is the peak
            t.append(t[-1] + max(MIN_JERK_PEAK * d / speed, 0.1))
            p.append(target)

    def wait(dt):
        t.append(t[-1] + dt)
        p.append(p[-1].copy())

    go(approach, lim.travel_speed)
    go(pressed, lim.speed)
    wait(lim.hold)
    if slide_to is not None:
        go(slide_to, lim.speed)
        wait(0.5 * lim.hold)
        go(slide_to + (approach - pressed), lim.speed)
    else:
        go(approach, lim.speed)
    go(start_above if slide_to is None else np.array([p[-1][0], p[-1][1], start_above[2]]), lim.travel_speed)
    wait(1.0)  # back at rest before the next move
    return Move(name, description, face, np.asarray(t), np.asarray(p))


def candidate_moves(size, radius: float, limits: PlanLimits | None = None) -> list[Move]:
    """The moves a plan chooses from on a box of ``size`` (3,) m with a probe of ``radius`` m.

    Raises:
        PlanError: the box leaves no room for a contact point within the margins, or the
            limits allow no indentation.
    """
    lim = limits or PlanLimits()
    size = np.asarray(size, dtype=np.float64)
    sx, sy, sz = (float(v) for v in size)
    m = lim.edge_margin
    if not lim.max_depth > 0.0005:
        raise PlanError(f"the depth limit {lim.max_depth * 1e3:.2f} mm allows no press the data could see (at least 0.5 mm)")
    if sx <= 2 * m or sy <= 2 * m:
        raise PlanError(f"the top face ({sx * 1e3:.1f} x {sy * 1e3:.1f} mm) has no point {m * 1e3:.0f} mm from its edges")
    d = float(lim.max_depth)
    z_safe = sz + radius + lim.safe_height
    clear = 0.003
    moves: list[Move] = []
    xs = np.linspace(m, sx - m, 4)[1:3] if sx > 4 * m else [sx / 2]
    ys = [sy / 2] if sy < 4 * m else [m + (sy - 2 * m) / 3, sy - m - (sy - 2 * m) / 3]
    for x in xs:
        for y in ys:
            top = np.array([x, y, sz])
            moves.append(press_move(f"press-top-{x * 1e3:.0f}-{y * 1e3:.0f}",
                                f"press the top at x = {x * 1e3:.0f} mm, y = {y * 1e3:.0f} mm to {d * 1e3:.0f} mm "
                                f"at {lim.speed * 1e3:.0f} mm/s, hold {lim.hold:.1f} s",
                                "+z", top + [0, 0, radius + lim.safe_height], top + [0, 0, radius + clear],
                                top + [0, 0, radius - d], None, lim))
    L = float(lim.slide_length)
    for axis, (lo_u, hi_u) in ((0, (m, sx - m)), (1, (m, sy - m))):
        if hi_u - lo_u < L:
            continue
        c = np.array([sx / 2, sy / 2, sz])
        a = c.copy()
        a[axis] = c[axis] - L / 2
        b = c.copy()
        b[axis] = c[axis] + L / 2
        name = "xy"[axis]
        moves.append(press_move(f"slide-top-{name}",
                            f"press the top at its centre to {d * 1e3:.0f} mm and slide {L * 1e3:.0f} mm along +{name} "
                            f"at {lim.speed * 1e3:.0f} mm/s",
                            "+z", a + [0, 0, radius + lim.safe_height], a + [0, 0, radius + clear],
                            a + [0, 0, radius - d], b + [0, 0, radius - d], lim))
    zmid = max(sz / 2, lim.bottom_margin + radius)
    if zmid < sz - m:
        for face, n, u in (("+x", (1, 0, 0), (sx, sy / 2)), ("-x", (-1, 0, 0), (0.0, sy / 2)),
                           ("+y", (0, 1, 0), (sx / 2, sy)), ("-y", (0, -1, 0), (sx / 2, 0.0))):
            n = np.array(n, dtype=np.float64)
            pt = np.array([u[0], u[1], zmid])
            above = pt + n * (radius + clear + 0.003)
            above[2] = z_safe
            moves.append(press_move(f"press-{face}", f"press the {face} face at mid height ({zmid * 1e3:.0f} mm) to "
                                f"{d * 1e3:.0f} mm at {lim.speed * 1e3:.0f} mm/s, hold {lim.hold:.1f} s",
                                face, above, pt + n * (radius + clear), pt + n * (radius - d), None, lim))
    box = BoxShape(size)
    for mv in moves:
        check_move(mv, box, radius, lim)
    if not moves:
        raise PlanError("no move fits the phantom within the limits")
    return moves


def check_move(mv: Move, shape: RestShape, radius: float, lim: PlanLimits) -> None:
    """Check a move against the limits along its whole path (every 5 ms).

    Args:
        mv: the move. shape: the rest phantom. radius: the probe's, m. lim: the limits.

    Raises:
        PlanError: it presses deeper than ``lim.max_depth``, or (on the box) touches the
            phantom outside its faces.
    """
    tr = ProbeTrajectory(mv.knots_t, mv.knots_p)
    t = np.arange(0.0, mv.duration + 1e-9, 0.005)
    c = tr(t)
    depth = shape.penetration_depth(c, radius)
    if depth.max() > lim.max_depth + 1e-6:
        raise PlanError(f"move {mv.name} would press {depth.max() * 1e3:.2f} mm deep (limit {lim.max_depth * 1e3:.2f} mm)")
    inside = depth > 0
    if shape.is_box and np.any(inside):
        lo, hi = -radius, shape.size + radius
        if np.any(c[inside] < lo) or np.any(c[inside] > hi):
            raise PlanError(f"move {mv.name} would touch the phantom outside its faces")


def surface_moves(shape: RestShape, radius: float, sites: tuple[np.ndarray, np.ndarray], limits: PlanLimits | None = None,
                  *, n_presses: int = 6, min_up: float = 0.2) -> list[Move]:
    """The moves a plan chooses from on a phantom of any shape (module docstring).

    Args:
        shape: the rest phantom (phantom frame, m). radius: the probe's, m.
        sites: (points (S, 3), outward normals (S, 3)) where presses may go: the
            diagnosis's surface patches (their centres are projected onto the surface).
        limits: the robot's limits. n_presses: presses to spread over the sites.
        min_up: a site's normal has at least this z component (a tool reaches it from
            above), and its point is ``bottom_margin`` plus a radius above the support.

    Returns:
        Presses (``face`` "+z" where the surface faces up, within 25 degrees of +z, else
        "surface"), then up to two slides.

    Raises:
        PlanError: the limits allow no indentation, or no site is reachable.
    """
    lim = limits or PlanLimits()
    if not lim.max_depth > 0.0005:
        raise PlanError(f"the depth limit {lim.max_depth * 1e3:.2f} mm allows no press the data could see (at least 0.5 mm)")
    pts, _ = shape.project(np.asarray(sites[0], dtype=np.float64).reshape(-1, 3))
    _, nrm = shape.project(pts + 1e-4 * np.asarray(sites[1], dtype=np.float64).reshape(-1, 3))
    ok = (nrm[:, 2] >= min_up) & (pts[:, 2] >= lim.bottom_margin + radius)
    pts, nrm = pts[ok], nrm[ok]
    if not len(pts):
        raise PlanError("no part of the phantom's seen surface can be pressed from above within the margins")
    # farthest-point sampling from the highest site: presses spread over the surface
    order = [int(np.argmax(pts[:, 2]))]
    dist = np.linalg.norm(pts - pts[order[0]], axis=1)
    while len(order) < min(n_presses, len(pts)):
        order.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(pts - pts[order[-1]], axis=1))
    d = float(lim.max_depth)
    z_safe = float(shape.size[2]) + radius + lim.safe_height
    clear = 0.003

    def above(p, n):
        a = p + n * (radius + clear + 0.003)
        return np.array([a[0], a[1], z_safe])

    moves: list[Move] = []
    for i in order:
        p, n = pts[i], nrm[i]
        face = "+z" if n[2] >= np.cos(np.radians(25.0)) else "surface"
        moves.append(press_move(f"press-{p[0] * 1e3:.0f}-{p[1] * 1e3:.0f}-{p[2] * 1e3:.0f}",
                                f"press the surface at ({p[0] * 1e3:.0f}, {p[1] * 1e3:.0f}, {p[2] * 1e3:.0f}) mm along its "
                                f"normal to {d * 1e3:.0f} mm at {lim.speed * 1e3:.0f} mm/s, hold {lim.hold:.1f} s",
                                face, above(p, n), p + n * (radius + clear), p + n * (radius - d), None, lim))
    L = float(lim.slide_length)
    for i in sorted(range(len(pts)), key=lambda k: -nrm[k, 2])[:1]:
        p, n = pts[i], nrm[i]
        for axis in (0, 1):
            u = np.eye(3)[axis] - n * n[axis]  # the axis in the tangent plane
            if np.linalg.norm(u) < 0.3:
                continue
            u /= np.linalg.norm(u)
            ends, ends_n = shape.project(np.stack([p - u * L / 2, p + u * L / 2]))
            ends_n = shape.project(ends + 1e-4 * ends_n)[1]
            if np.any(ends[:, 2] < lim.bottom_margin + radius):
                continue
            name = "xy"[axis]
            # a chord of a convex surface dips below it: press shallower by the excess
            for depth in (d, 0.75 * d, 0.5 * d):
                mv = press_move(f"slide-{name}-{p[0] * 1e3:.0f}-{p[1] * 1e3:.0f}",
                                f"press the surface at ({ends[0][0] * 1e3:.0f}, {ends[0][1] * 1e3:.0f}, "
                                f"{ends[0][2] * 1e3:.0f}) mm to {depth * 1e3:.0f} mm and slide {L * 1e3:.0f} mm along "
                                f"+{name} at {lim.speed * 1e3:.0f} mm/s", "+z" if n[2] >= np.cos(np.radians(25.0)) else "surface",
                                above(ends[0], ends_n[0]), ends[0] + ends_n[0] * (radius + clear),
                                ends[0] + ends_n[0] * (radius - depth), ends[1] + ends_n[1] * (radius - depth), lim)
                try:
                    check_move(mv, shape, radius, lim)
                except PlanError:
                    continue
                moves.append(mv)
                break
    for mv in moves:
        check_move(mv, shape, radius, lim)
    return moves


def move_path(moves: Sequence[Move], size, radius: float, lim: PlanLimits) -> tuple[np.ndarray, np.ndarray]:
    """Knots of the moves played one after the other (each starts where the last ended, at
    a safe height), sampled every 10 ms."""
    t0 = 0.0
    ts, ps = [], []
    z_safe = float(size[2]) + radius + lim.safe_height
    prev = None
    for mv in moves:
        kt, kp = mv.knots_t, mv.knots_p
        if prev is not None:
            # travel at the safe height from the last move's end to this one's start
            hop = np.array([kp[0][0], kp[0][1], max(z_safe, kp[0][2])])
            d = float(np.linalg.norm(hop - prev))
            if d > 1e-9:
                t0 += max(d / lim.travel_speed, 0.1)
                ts.append(t0)
                ps.append(hop)
        ts += list(t0 + kt)
        ps += list(kp)
        t0 += float(kt[-1])
        prev = kp[-1]
    kt, kp = np.asarray(ts), np.asarray(ps)
    keep = np.concatenate([[True], np.diff(kt) > 1e-9])
    traj = ProbeTrajectory(kt[keep], kp[keep])
    t = np.arange(0.0, traj.duration + 1e-9, 0.01)
    return t, traj(t)


