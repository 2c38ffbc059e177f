"""Probe trajectories of the virtual lab: pokes into the top and the sides of the box.

A sequence is planned like the recordings of Wu et al. 2020 (Sec. 4.1: "interactions
consist of probes to the top and sides of the phantom"): the probe waits above the
phantom, travels at a safe height, approaches a face from outside, presses along the
inward normal to a requested depth, holds, sometimes slides along the surface while
pressed, retracts and rests. Between knots the sphere centre follows a minimum-jerk
profile (Flash & Hogan 1985), so velocities are continuous and zero at every knot,
like a position-controlled dVRK PSM.

Everything is in the phantom frame (box ``[0, sx] x [0, sy] x [0, sz]``, z up), SI units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.preparation.shape import BoxShape

__all__ = [
    "FACE_NORMALS",
    "INTERPOLATIONS",
    "Poke",
    "ProbeTrajectory",
    "ProbingConfig",
    "ProbePlan",
    "plan_sequence",
    "tool_rotation",
    "penetration_depth",
    "plan_from_path",
    "PathBuilder",
    "Stroke",
    "DEFAULT_PATH_TILT_DEG",
    "MAX_PATH_PENETRATION",
]

DEFAULT_PATH_TILT_DEG = 25.0
"""Shaft tilt from vertical of a given path's tool (:func:`plan_from_path`), degrees: the
middle of :attr:`ProbingConfig.tilt_range_deg`."""
MAX_PATH_PENETRATION = 0.015
"""Deepest a given path's sphere may reach into the rest box, m (:func:`plan_from_path`);
the lab's planned pokes reach at most 10 mm."""

#: Outward unit normals of the faces a probe may press, phantom frame.
FACE_NORMALS: dict[str, np.ndarray] = {
    "+z": np.array([0.0, 0.0, 1.0]),
    "+x": np.array([1.0, 0.0, 0.0]),
    "-x": np.array([-1.0, 0.0, 0.0]),
    "+y": np.array([0.0, 1.0, 0.0]),
    "-y": np.array([0.0, -1.0, 0.0]),
}


@dataclass(frozen=True)
class ProbingConfig:
    """How pokes are drawn. Ranges are ``(low, high)``, sampled uniformly."""

    depth_range: tuple[float, float] = (0.003, 0.010)
    """Indentation of the sphere's lowest (innermost) point below the rest surface, m."""
    speed_range: tuple[float, float] = (0.003, 0.015)
    """Mean speed of the press and retract strokes, m/s."""
    hold_range: tuple[float, float] = (0.5, 1.5)
    """Time held at full depth, s."""
    slide_probability: float = 0.35
    """Probability that a poke slides along the surface while pressed."""
    slide_length_range: tuple[float, float] = (0.004, 0.012)
    """Length of a slide, m (shortened to stay inside the allowed area)."""
    slide_speed_range: tuple[float, float] = (0.003, 0.010)
    """Mean speed of a slide, m/s."""
    rest_range: tuple[float, float] = (0.3, 1.5)
    """Pause at the safe height between pokes, s."""
    side_probability: float = 0.4
    """Probability that a poke goes into a side face (if the tool tilt allows one)."""
    travel_speed: float = 0.03
    """Mean speed of moves in free space, m/s."""
    clearance_range: tuple[float, float] = (0.003, 0.006)
    """Gap between sphere and surface where a press stroke starts, m."""
    safe_height: float = 0.010
    """Gap between the sphere and the top face while travelling, m."""
    edge_margin: float = 0.010
    """Minimum distance of a contact point from any edge of its face, m."""
    bottom_margin: float = 0.008
    """Side contacts stay this far above the bottom plus one probe radius, m."""
    tilt_range_deg: tuple[float, float] = (15.0, 35.0)
    """Angle of the shaft from vertical, degrees (constant per sequence)."""
    start_rest_range: tuple[float, float] = (0.5, 1.0)
    """Time the probe waits at its start position before the first poke, s."""
    top_region: tuple[float, float, float, float] | None = None
    """``(x0, y0, x1, y1)``, m: top-face contact points are drawn in this rectangle
    (intersected with the edge margins): a palpation that searches a suspect region, as
    a surgeon palpates over a suspected tumour. None: anywhere on the top face."""
    face_cycle: tuple[str, ...] | None = None
    """Kinds of face poked in turn, each ``"side"`` (a side face the shaft's tilt allows,
    drawn at random; the top if none does) or ``"top"``: ``("side", "top")`` presses a side
    first, then the top, and so on. None: each poke goes into a side with
    ``side_probability``."""
    max_strain: float | None = None
    """On a phantom of any shape (:func:`core.lab.surface_probing.plan_surface_sequence`):
    a press goes at most this fraction of the body's thickness under the contact deep
    (the drawn depth capped). None: the drawn depth. The box's deepest press, 10 mm into
    36 mm, is 0.28; 9.6 mm into the apex of a 25 mm dome (0.38) inverts elements of a
    fine replay mesh under the probe."""


@dataclass(frozen=True)
class Poke:
    """One press of the probe into a face.

    Attributes:
        face: ``"+z"`` (top) or one of ``"+x", "-x", "+y", "-y"`` (sides).
        point: (3,) contact point on the rest surface where the press starts, m, phantom frame.
        depth: indentation of the sphere below the rest surface, m.
        speed: mean speed of the press and retract strokes, m/s.
        hold: time at full depth before sliding / retracting, s.
        slide_to: (3,) contact point where a slide ends (on the same face), or None.
        slide_speed: mean slide speed, m/s, or None.
        t_start: time the probe leaves its safe position for this poke, s.
        t_end: time it is back at a safe position, s.
    """

    face: str
    point: np.ndarray
    depth: float
    speed: float
    hold: float
    slide_to: np.ndarray | None
    slide_speed: float | None
    t_start: float
    t_end: float

    @property
    def kind(self) -> str:
        """``"top"`` or ``"side"``."""
        return "top" if self.face == "+z" else "side"

    def to_dict(self) -> dict:
        """JSON-ready description (as in truth.json)."""
        out = {
            "kind": self.kind,
            "face": self.face,
            "point": [float(v) for v in self.point],
            "depth": float(self.depth),
            "speed": float(self.speed),
            "hold": float(self.hold),
            "t_start": float(self.t_start),
            "t_end": float(self.t_end),
        }
        if self.slide_to is not None:
            out["slide_to"] = [float(v) for v in self.slide_to]
            out["slide_speed"] = float(self.slide_speed)
        return out


def _min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk blend 10 s^3 - 15 s^4 + 6 s^5 on s in [0, 1] (Flash & Hogan 1985)."""
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


INTERPOLATIONS = ("min_jerk", "linear")
"""How :class:`ProbeTrajectory` blends between knots."""


@dataclass(frozen=True)
class ProbeTrajectory:
    """Sphere-centre path through knots, minimum-jerk (or linear) between consecutive knots.

    Attributes:
        knot_t: (M,) strictly increasing knot times, s; the path starts at knot_t[0].
        knot_p: (M, 3) sphere centres at the knots, m, phantom frame.
        interpolation: "min_jerk" (default; velocity zero at every knot, for planned
            pokes whose knots are stops) or "linear" (for densely sampled given paths,
            where stopping at every sample would make the motion jerky).

    Outside ``[knot_t[0], knot_t[-1]]`` the path is held at its end points.

    Raises:
        ValueError: knot_p not (M, 3), knot times empty or not strictly increasing,
            non-finite values, or an unknown interpolation.
    """

    knot_t: np.ndarray
    knot_p: np.ndarray
    interpolation: str = "min_jerk"

    def __post_init__(self):
        t = np.asarray(self.knot_t, dtype=np.float64).reshape(-1)
        p = np.asarray(self.knot_p, dtype=np.float64)
        if p.shape != (t.size, 3):
            raise ValueError(f"knot_p must be ({t.size}, 3), got {p.shape}")
        if t.size < 1 or (t.size > 1 and np.any(np.diff(t) <= 0)):
            raise ValueError("knot_t must be non-empty and strictly increasing")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise ValueError("knot_t and knot_p must be finite")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, got {self.interpolation!r}")
        object.__setattr__(self, "knot_t", t)
        object.__setattr__(self, "knot_p", p)

    @property
    def duration(self) -> float:
        """Time of the last knot, s."""
        return float(self.knot_t[-1])

    def __call__(self, t) -> np.ndarray:
        """(K, 3) sphere centres at times ``t`` (K,), m, phantom frame."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        kt, kp = self.knot_t, self.knot_p
        if kt.size == 1:
            return np.repeat(kp, t.size, axis=0)
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, kt.size - 2)
        s = np.clip((t - kt[i]) / (kt[i + 1] - kt[i]), 0.0, 1.0)
        w = (_min_jerk(s) if self.interpolation == "min_jerk" else s)[:, None]
        return kp[i] * (1.0 - w) + kp[i + 1] * w


@dataclass(frozen=True)
class ProbePlan:
    """A planned sequence: the true sphere-centre path, its pokes, the tool orientation.

    Attributes:
        trajectory: the true path of the sphere centre, phantom frame.
        pokes: the pokes in time order.
        R_phantom_tool: (3, 3) tool orientation; its z column points from the shaft to
            the tip (down into the phantom when poking from above); the shaft extends
            from the sphere centre along -z_tool.
        duration: sequence length, s.
    """

    trajectory: ProbeTrajectory
    pokes: tuple[Poke, ...]
    R_phantom_tool: np.ndarray
    duration: float

    @property
    def shaft_direction(self) -> np.ndarray:
        """(3,) unit vector from the sphere centre up along the shaft (= -z_tool)."""
        return -self.R_phantom_tool[:, 2]


def tool_rotation(tilt: float, azimuth: float, roll: float) -> np.ndarray:
    """(3, 3) R_phantom_tool whose shaft leans ``tilt`` rad from vertical towards
    ``azimuth`` (rad, from +x towards +y); ``roll`` turns the tool about its axis."""
    shaft = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
    z = -shaft
    ref = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def penetration_depth(centres: np.ndarray, size, radius: float) -> np.ndarray:
    """(K,) how deep a sphere of ``radius`` at ``centres`` (K, 3) reaches into the rest box
    ``[0, size]``, m: ``radius - distance(centre, box)`` (negative when clear of it).
    For centres inside the box the distance is taken as minus the depth of the centre."""
    return BoxShape(size).penetration_depth(centres, radius)


class PathBuilder:
    """Accumulates knots; times advance by distance / speed (at least ``min_dt``)."""

    min_dt = 0.05

    def __init__(self, start: np.ndarray):
        self.t = [0.0]
        self.p = [np.asarray(start, dtype=np.float64)]

    @property
    def now(self) -> float:
        return self.t[-1]

    @property
    def here(self) -> np.ndarray:
        return self.p[-1]

    def move(self, target, speed: float) -> None:
        target = np.asarray(target, dtype=np.float64)
        dist = float(np.linalg.norm(target - self.here))
        if dist < 1e-9:
            return
        self.t.append(self.now + max(dist / speed, self.min_dt))
        self.p.append(target)

    def wait(self, dt: float) -> None:
        if dt > 1e-6:
            self.t.append(self.now + dt)
            self.p.append(self.here.copy())

    def snapshot(self) -> tuple[int, int]:
        return len(self.t), len(self.p)

    def rollback(self, snap: tuple[int, int]) -> None:
        del self.t[snap[0]:]
        del self.p[snap[1]:]


def _face_frame(face: str, size: np.ndarray):
    """(origin, u_axis, v_axis, u_range, v_range) of a face; u, v span its plane."""
    sx, sy, sz = size
    if face == "+z":
        return np.array([0.0, 0.0, sz]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), sx, sy
    if face in ("+x", "-x"):
        x = sx if face == "+x" else 0.0
        return np.array([x, 0.0, 0.0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), sy, sz
    y = sy if face == "+y" else 0.0
    return np.array([0.0, y, 0.0]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), sx, sz


def _allowed_box(face: str, size: np.ndarray, radius: float, cfg: ProbingConfig):
    """(lo, hi) of the face coordinates (u, v) where contact points may lie."""
    _, _, _, ulen, vlen = _face_frame(face, size)
    m = cfg.edge_margin
    lo = np.array([m, m])
    hi = np.array([ulen - m, vlen - m])
    if face != "+z":
        lo[1] = max(lo[1], cfg.bottom_margin + radius)
    elif cfg.top_region is not None:
        x0, y0, x1, y1 = cfg.top_region
        lo, hi = np.maximum(lo, [x0, y0]), np.minimum(hi, [x1, y1])
    if np.any(hi <= lo):
        raise ValueError(f"face {face} of a {size.tolist()} m box has no room for pokes with margin {m} m"
                         + (f" in top_region {cfg.top_region}" if face == "+z" and cfg.top_region is not None else ""))
    return lo, hi


def _draw_poke_geometry(rng, face, size, radius, cfg):
    origin, eu, ev, _, _ = _face_frame(face, size)
    lo, hi = _allowed_box(face, size, radius, cfg)
    uv = rng.uniform(lo, hi)
    point = origin + uv[0] * eu + uv[1] * ev
    slide_to = None
    slide_speed = None
    if rng.random() < cfg.slide_probability:
        ang = rng.uniform(0, 2 * np.pi)
        length = rng.uniform(*cfg.slide_length_range)
        uv2 = np.clip(uv + length * np.array([np.cos(ang), np.sin(ang)]), lo, hi)
        if np.linalg.norm(uv2 - uv) > 0.002:
            slide_to = origin + uv2[0] * eu + uv2[1] * ev
            slide_speed = float(rng.uniform(*cfg.slide_speed_range))
    return point, slide_to, slide_speed


@dataclass(frozen=True)
class Stroke:
    """One press of a poke, from a safe height down to a surface point, along its inward
    normal, and back up (the part the box's and any surface's planner share).

    Attributes:
        point: (3,) contact point on the rest surface, m. normal: (3,) its outward unit normal.
        depth, speed, hold, clearance: as :class:`ProbingConfig`'s ranges, drawn.
        slide_to: (3,) where a slide ends, or None. z_safe: travel height of the centre, m.
        radius: the probe's true radius, m.
    """

    point: np.ndarray
    normal: np.ndarray
    depth: float
    speed: float
    hold: float
    clearance: float
    slide_to: np.ndarray | None
    z_safe: float
    radius: float

    @classmethod
    def draw(cls, rng, cfg: ProbingConfig, point, normal, radius: float, slide_to, z_safe: float) -> "Stroke":
        """Depth, speed, hold and clearance drawn from ``cfg``, in this order."""
        depth = float(rng.uniform(*cfg.depth_range))
        speed = float(rng.uniform(*cfg.speed_range))
        hold = float(rng.uniform(*cfg.hold_range))
        clearance = float(rng.uniform(*cfg.clearance_range))
        return cls(np.asarray(point, dtype=np.float64), np.asarray(normal, dtype=np.float64), depth, speed, hold,
                   clearance, slide_to, float(z_safe), float(radius))

    @property
    def approach(self) -> np.ndarray:
        """(3,) sphere centre where the press starts, clear of the surface."""
        return self.point + self.normal * (self.radius + self.clearance)

    @property
    def above(self) -> np.ndarray:
        """(3,) the approach point raised to the travel height."""
        a = self.approach
        return np.array([a[0], a[1], self.z_safe])

    @property
    def retract(self) -> np.ndarray:
        """(3,) sphere centre where the press ends, clear of the surface again."""
        end = self.point if self.slide_to is None else self.slide_to
        return end + self.normal * (self.radius + self.clearance)

    def execute(self, b: "PathBuilder", rng, cfg: ProbingConfig, slide_speed: float | None) -> None:
        """Add the stroke's knots to ``b``: up to the travel height, over the approach
        point, down to it, press, hold, slide (a pause drawn after it), retract, up, rest
        (drawn)."""
        n, r = self.normal, self.radius
        b.move([b.here[0], b.here[1], self.z_safe], cfg.travel_speed)  # up to the safe height
        b.move(self.above, cfg.travel_speed)  # over the approach point, clear of the phantom
        b.move(self.approach, cfg.travel_speed)  # down beside / above the surface
        b.move(self.point + n * (r - self.depth), self.speed)
        b.wait(self.hold)
        if self.slide_to is not None:
            b.move(self.slide_to + n * (r - self.depth), slide_speed)
            b.wait(float(rng.uniform(0.2, 0.6)))
        retract = self.retract
        b.move(retract, self.speed)
        b.move([retract[0], retract[1], self.z_safe], cfg.travel_speed)
        b.wait(float(rng.uniform(*cfg.rest_range)))


def plan_sequence(
    rng: np.random.Generator,
    *,
    size,
    radius: float,
    duration: float,
    config: ProbingConfig = ProbingConfig(),
    tool_azimuth: float | None = None,
) -> ProbePlan:
    """Plan the pokes of one sequence and the true sphere-centre path.

    Args:
        rng: the only source of randomness.
        size: (3,) box size, m.
        radius: the probe's *true* radius, m (pokes reach ``depth`` with this sphere).
        duration: sequence length, s (at least ~6 s so one poke fits).
        config: ranges of depths, speeds, holds, ...
        tool_azimuth: direction (rad) the shaft leans towards; random if None.

    The probe starts above the top face, clear of the phantom, and approaches every
    face from outside along its normal; side faces are only poked when the shaft leans
    away from them (otherwise the shaft would cut through the phantom).
    """
    size = np.asarray(size, dtype=np.float64)
    cfg = config
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    if cfg.face_cycle is not None and not set(cfg.face_cycle) <= {"side", "top"}:
        raise ValueError(f"face_cycle entries must be 'side' or 'top', got {cfg.face_cycle!r}")
    tilt = np.deg2rad(rng.uniform(*cfg.tilt_range_deg))
    azimuth = rng.uniform(0, 2 * np.pi) if tool_azimuth is None else float(tool_azimuth)
    R = tool_rotation(tilt, azimuth, rng.uniform(-np.pi, np.pi))
    shaft = -R[:, 2]
    sides = [f for f in ("+x", "-x", "+y", "-y") if float(FACE_NORMALS[f] @ shaft) > 0.1]

    z_safe = size[2] + radius + cfg.safe_height
    start = np.array([
        size[0] / 2 + rng.uniform(-0.01, 0.01),
        size[1] / 2 + rng.uniform(-0.005, 0.005),
        z_safe + rng.uniform(0.0, 0.01),
    ])
    b = PathBuilder(start)
    b.wait(rng.uniform(*cfg.start_rest_range))
    pokes: list[Poke] = []
    failures = 0
    while failures < (3 if pokes else 50):
        snap = b.snapshot()
        t_start = b.now
        if cfg.face_cycle:
            to_side = cfg.face_cycle[len(pokes) % len(cfg.face_cycle)] == "side"
        else:  # drawn only when a side is allowed: the random stream of older sessions stays
            to_side = bool(sides) and rng.random() < cfg.side_probability
        face = sides[rng.integers(len(sides))] if (sides and to_side) else "+z"
        n = FACE_NORMALS[face]
        point, slide_to, slide_speed = _draw_poke_geometry(rng, face, size, radius, cfg)
        stroke = Stroke.draw(rng, cfg, point, n, radius, slide_to, z_safe)
        stroke.execute(b, rng, cfg, slide_speed)
        depth, speed, hold = stroke.depth, stroke.speed, stroke.hold
        if b.now > duration:
            b.rollback(snap)
            failures += 1
            continue
        pokes.append(Poke(face, point, depth, speed, hold, slide_to, slide_speed, t_start, b.now))
    if not pokes:
        raise ValueError(f"a sequence of {duration} s is too short for one poke")
    if b.now < duration:
        b.wait(duration - b.now)
    traj = ProbeTrajectory(np.asarray(b.t), np.asarray(b.p))
    return ProbePlan(traj, tuple(pokes), R, float(duration))


def plan_from_path(
    t,
    centres,
    *,
    size,
    radius: float,
    tool_azimuth: float,
    tilt_deg: float = DEFAULT_PATH_TILT_DEG,
    max_penetration: float = MAX_PATH_PENETRATION,
) -> ProbePlan:
    """A plan that follows a given sphere-centre path ("the virtual lab can execute a plan").

    Args:
        t: (K,) strictly increasing times, s, K >= 2, t[0] >= 0; the sequence lasts t[-1]
            (the path is held at its first point before t[0]).
        centres: (K, 3) true sphere centres, m, phantom frame; linearly interpolated.
        size: (3,) box size, m.
        radius: the probe's true radius, m.
        tool_azimuth: direction (rad, from +x towards +y) the shaft leans towards (the lab
            passes "away from the camera", as for random plans).
        tilt_deg: shaft angle from vertical, degrees; the tool is not rolled.
        max_penetration: the deepest the sphere may reach into the rest box, m, checked
            with :func:`penetration_depth` at the given points and on the path sampled at
            1 ms (a straight segment can cut a corner deeper than its end points).

    Returns:
        a :class:`ProbePlan` with no pokes.

    Raises:
        ValueError: wrong shapes, non-finite values, fewer than 2 points, times not
            strictly increasing or negative, or a path that enters deeper than
            ``max_penetration``.
    """
    tt = np.asarray(t, dtype=np.float64)
    pc = np.asarray(centres, dtype=np.float64)
    if tt.ndim != 1 or tt.size < 2:
        raise ValueError(f"path times must be (K,) with K >= 2, got shape {tt.shape}")
    if pc.shape != (tt.size, 3):
        raise ValueError(f"path centres must be ({tt.size}, 3) to match the times, got {pc.shape}")
    if not (np.all(np.isfinite(tt)) and np.all(np.isfinite(pc))):
        raise ValueError("path times and centres must be finite")
    bad = np.flatnonzero(np.diff(tt) <= 0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"path times must be strictly increasing; t[{i}] = {tt[i]} s, t[{i + 1}] = {tt[i + 1]} s")
    if tt[0] < 0:
        raise ValueError(f"path times must start at t >= 0, got {tt[0]} s")
    traj = ProbeTrajectory(tt, pc, interpolation="linear")
    dense = traj(np.linspace(tt[0], tt[-1], max(int(np.ceil((tt[-1] - tt[0]) * 1000)) + 1, 2)))
    depth = max(float(penetration_depth(pc, size, radius).max()), float(penetration_depth(dense, size, radius).max()))
    if depth > max_penetration:
        i = int(np.argmax(penetration_depth(pc, size, radius)))
        raise ValueError(f"the path enters the phantom {depth * 1e3:.1f} mm deep (sphere radius {radius * 1e3:.1f} mm; "
                         f"deepest given point {i} at t = {tt[i]:.3f} s, {pc[i].tolist()} m); at most "
                         f"{max_penetration * 1e3:.1f} mm allowed")
    R = tool_rotation(np.deg2rad(tilt_deg), float(tool_azimuth), 0.0)
    return ProbePlan(traj, (), R, float(tt[-1]))
