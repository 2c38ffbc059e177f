"""Import ROS bags (a dVRK recording) into a recorded session (``tissue-session/1``).

Each bag becomes one sequence of the session: the probe pose topic
(``geometry_msgs/PoseStamped`` or ``geometry_msgs/TransformStamped``, e.g. the dVRK's
``/PSM1/measured_cp``) becomes ``kinematics.csv`` and the depth-camera topic
(``sensor_msgs/PointCloud2``) becomes ``frames.csv`` plus one PLY per message. ROS1
``.bag`` files and ROS2 bags (a folder with ``metadata.yaml``, or a single ``.db3``
(sqlite3) or ``.mcap`` file) are read with the ``rosbags`` library, whose typestores
deserialise every message (the definitions embedded in the bag, else ROS2 Humble's).

What a bag does not carry comes from the caller (see :class:`BagImportConfig`): the
phantom's size and mass, the probe radius, the depth accuracy, the role of each
sequence, and the calibration the format requires: ``calibration/corners.csv`` (the
probe touching the phantom's top corners, robot frame) is given as a CSV file in the
session format. Optional extras come from topics: forces
(``geometry_msgs/WrenchStamped``), the camera intrinsics (``sensor_msgs/CameraInfo``)
and the reference cloud of the phantom at rest (a ``PointCloud2`` topic), or from files
(``reference.ply``, ``phantom.stl``).

ROS data are SI already (REP 103: metres, seconds); positions farther than 5 m from the
robot origin or clouds whose median point lies farther than 5 m from the camera are
refused as millimetres, by the same checks the session reader applies. Times are the
messages' header stamps (or the bags' log times), relative to an origin per bag.

The session is written by :class:`core.io.SessionWriter`: into a hidden temporary
sibling folder that is moved into place only when every bag was read, so a failed
import leaves nothing behind and never touches an existing session.

This module holds the import itself (:class:`BagImportConfig`, :func:`import_bags`, its
results, and pass 2, which streams the clouds into the session). Reading a bag and
decoding its messages live in :mod:`core.io.rosbag_reader`, pass 1 (scanning one bag's
topics into poses, forces, intrinsics, reference and the cloud plan) in
:mod:`core.io.rosbag_scan`; the public names of both that callers use (:class:`BagError`,
:func:`pointcloud2_xyz`, the message types) are re-exported here.
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import TissueTwinError, UnitsError
from core.io.checks import FORMAT, check_cloud_metres
from core.io.meta import CameraSpec, SessionMeta
from core.io.ply import read_ply
from core.io.records import Corners, Kinematics
from core.io.rosbag_reader import (
    CAMERA_INFO_TYPE,
    CLOUD_TYPE,
    FORCE_TYPE,
    NS_PER_S,
    POSE_TYPES,
    Bag,
    BagError,
    decode_cloud,
    pointcloud2_xyz,
    short_type,
    stamp_text,
)
from core.io.rosbag_scan import Scan, scan_bag
from core.io.tables import read_corners
from core.io.writer import SessionExistsError, SessionWriter

__all__ = [
    "BagError",
    "BagImportConfig",
    "BagImportResult",
    "ImportedSequence",
    "POSE_TYPES",
    "CLOUD_TYPE",
    "FORCE_TYPE",
    "CAMERA_INFO_TYPE",
    "default_roles",
    "import_bags",
    "pointcloud2_xyz",
]

PAPER_PHANTOM_SIZE = (0.0687, 0.0393, 0.0358)
"""Default phantom box, m (x length, y width, z height; Wu et al. 2020, Sec. 4.1)."""
PAPER_PHANTOM_MASS = 0.10401
"""Default phantom mass, kg (Wu et al. 2020, Sec. 4.1)."""
PAPER_PROBE_RADIUS = 0.005
"""Default probe sphere radius, m (``SESSION_FORMAT.md``'s example and the virtual lab's
nominal probe)."""

ProgressCallback = Callable[[float, str], None]


@dataclass(frozen=True)
class BagImportConfig:
    """Topics, clocks and the metadata a bag does not carry. Defaults: the dVRK's PSM1
    pose, a RealSense point cloud, the paper's phantom (Wu et al. 2020)."""

    pose_topic: str = "/PSM1/measured_cp"
    """Probe pose, ``PoseStamped`` or ``TransformStamped``, robot base frame, m."""
    cloud_topic: str = "/camera/depth/color/points"
    """Depth clouds, ``PointCloud2`` with float ``x``, ``y``, ``z`` fields, camera frame, m."""
    force_topic: str | None = None
    """Optional ``WrenchStamped``: the force the probe applies to the phantom, robot base
    frame, N; interpolated linearly to the pose stamps (``fx, fy, fz`` columns)."""
    negate_force: bool = False
    """The force topic reports the reaction (phantom on probe): flip its sign."""
    camera_info_topic: str | None = None
    """Optional ``CameraInfo``: its first message gives ``camera.intrinsics``."""
    reference_topic: str | None = None
    """Optional ``PointCloud2`` of the phantom at rest with no instrument in view: its
    first message (in the first bag holding the topic) becomes
    ``calibration/reference.ply``."""
    time_source: str = "header"
    """``"header"``: the messages' ``header.stamp``; ``"log"``: the time the bag recorded
    each message (for publishers that leave stamps at zero)."""
    t0_ns: int | None = None
    """Time origin, integer ns of ROS time (``sec * 1e9 + nanosec``), for every bag:
    ``t = (stamp - t0_ns) / 1e9`` s. None: per bag, the earliest pose or cloud stamp (so
    each sequence starts at t = 0)."""
    tip_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Probe sphere centre in the pose's child (tool) frame, m: the kinematics are
    ``position + R(quaternion) @ tip_offset``."""
    phantom_size: tuple[float, float, float] = PAPER_PHANTOM_SIZE
    """Box size, m: x length, y width, z height."""
    phantom_mass: float = PAPER_PHANTOM_MASS
    """kg."""
    probe_radius: float = PAPER_PROBE_RADIUS
    """Sphere radius, m."""
    depth_accuracy: float = 0.002
    """Depth noise scale of the camera, m (the virtual lab's SR300 figure)."""
    camera_rate_hz: float | None = None
    """Nominal frame rate, Hz; None: 1 / median interval of all imported frames."""
    names: tuple[str, ...] | None = None
    """Sequence name per bag; None: ``seq00``, ``seq01``, ..."""
    roles: tuple[str, ...] | None = None
    """Role per bag (``train``/``validation``/``test``); None: :func:`default_roles`."""

    def __post_init__(self) -> None:
        if self.time_source not in ("header", "log"):
            raise ValueError(f"time_source must be 'header' or 'log', got {self.time_source!r}")
        off = np.asarray(self.tip_offset, dtype=np.float64)
        if off.shape != (3,) or not np.isfinite(off).all():
            raise ValueError(f"tip_offset must be 3 finite numbers (m), got {self.tip_offset!r}")
        if self.t0_ns is not None and not isinstance(self.t0_ns, (int, np.integer)):
            raise ValueError(f"t0_ns must be an integer number of nanoseconds, got {self.t0_ns!r}")
        if self.camera_rate_hz is not None and not self.camera_rate_hz > 0:
            raise ValueError(f"camera_rate_hz must be positive, got {self.camera_rate_hz!r}")
        for name in ("pose_topic", "cloud_topic"):
            if not getattr(self, name):
                raise ValueError(f"{name} must be a topic name, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class ImportedSequence:
    """What one bag became (evidence for the caller; nothing here is needed to read the
    session)."""

    name: str
    """Sequence name (folder under ``sequences/``)."""
    role: str
    """``train``, ``validation`` or ``test``."""
    bag: Path
    """The bag it came from."""
    pose_type: str
    """Message type of the pose topic, e.g. ``geometry_msgs/msg/PoseStamped``."""
    t0_ns: int
    """Time origin of this sequence, ns of ROS time (``t = (stamp - t0_ns) / 1e9``)."""
    kinematics_rows: int
    """Rows of ``kinematics.csv`` (pose messages with distinct stamps)."""
    frames: int
    """Depth frames written."""
    duplicate_poses: int
    """Pose messages dropped because an earlier one had the same stamp."""
    duplicate_clouds: int
    """Cloud messages dropped because an earlier one had the same stamp."""
    empty_clouds: int
    """Cloud messages dropped because no point was finite (the frame number is skipped)."""
    nonfinite_points: int
    """NaN/inf points dropped from the written clouds (invalid depth pixels)."""
    frames_outside_kinematics: int
    """Frames whose time lies outside the kinematics' time span (a clock problem when
    large)."""
    force_rows_clamped: int = 0
    """Kinematics rows before the first or after the last force sample (given the
    nearest force, within two force periods)."""
    frame_ids: dict = field(default_factory=dict)
    """``header.frame_id`` values seen per topic kind (``pose``, ``cloud``)."""


@dataclass(frozen=True)
class BagImportResult:
    """The written session and what each bag became."""

    path: Path
    """The session folder."""
    sequences: tuple[ImportedSequence, ...]
    camera_rate_hz: float
    """Written ``camera.rate_hz``."""
    intrinsics: dict | None
    """Written ``camera.intrinsics`` (from the camera-info topic), or None."""
    reference: str | None
    """Where ``calibration/reference.ply`` came from (``"<bag> <topic>"`` or a file), or None."""


def default_roles(n: int) -> tuple[str, ...]:
    """Roles of ``n`` imported sequences when none are given.

    One bag: ``test`` (a replay evaluates it); two: ``train``, ``test``; three or more:
    ``validation``, ``test``, then ``train`` (the virtual lab's ``small`` preset order), so
    that fitting, training and evaluating all find their sequences.
    """
    if n < 1:
        raise ValueError(f"need at least one sequence, got {n}")
    if n == 1:
        return ("test",)
    if n == 2:
        return ("train", "test")
    return ("validation", "test") + ("train",) * (n - 2)


# --------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------


@dataclass
class _BagPlan:
    path: Path
    name: str
    role: str
    scan: Scan
    t0_ns: int


def _load_corners(corners: Corners | str | os.PathLike) -> Corners:
    if isinstance(corners, Corners):
        return corners
    return read_corners(Path(corners))


def import_bags(
    bags: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    corners: Corners | str | os.PathLike,
    config: BagImportConfig = BagImportConfig(),
    reference: str | os.PathLike | None = None,
    phantom_stl: str | os.PathLike | None = None,
    overwrite: bool = False,
    callback: ProgressCallback | None = None,
) -> BagImportResult:
    """Turn ROS bags (one per sequence) into a session folder (``tissue-session/1``).

    Per bag: the pose topic becomes ``kinematics.csv`` (sorted by stamp; a message whose
    stamp repeats an earlier one is dropped), the cloud topic becomes one frame per
    message (frame number = the message's rank in stamp order, so a frame dropped for
    holding no finite point leaves a gap), NaN/inf points are dropped, and
    ``t = (stamp - t0) / 1e9`` s. Each bag is read twice (everything but the cloud
    points, then the clouds), one cloud in memory at a time (plus at most 64 held back
    to restore stamp order).

    Args:
        bags: ROS1 ``.bag`` files, ROS2 bag folders, or ROS2 ``.db3``/``.mcap`` files, in
            sequence order (formats may be mixed).
        out: the session folder to create.
        corners: ``calibration/corners.csv`` content: :class:`core.io.Corners` or the
            path of a CSV in the session format (``corner,x,y,z``, robot frame, m).
        config: topics, clocks and metadata (:class:`BagImportConfig`).
        reference: a PLY file to store as ``calibration/reference.ply`` (camera frame, m);
            exclusive with ``config.reference_topic``.
        phantom_stl: an STL of the phantom's rest surface (phantom frame, m), copied.
        overwrite: replace an existing session at ``out`` (as ``generate --overwrite``).
        callback: ``callback(fraction in [0, 1], message)`` for progress.

    Returns:
        :class:`BagImportResult`.

    Raises:
        BagError: a path that is not a readable bag (missing, truncated, not a bag); a
            missing topic (the message lists the bag's topics), a topic of the wrong
            type or without messages; zero header stamps; a non-finite or zero-norm pose;
            clouds without float x/y/z fields, or none with a finite point; forces not
            covering the poses.
        UnitsError: positions > 5 m from the robot origin or clouds with median
            distance > 5 m (millimetres).
        core.errors.SessionFormatError: bad corners file, names, roles or metadata (as
            the session reader would say).
        core.io.SessionExistsError: ``out`` exists and ``overwrite`` is false (checked
            before any bag is read).
        TissueTwinError: no bag, or as many names/roles as bags not given.
    """
    report = callback or (lambda fraction, message: None)
    paths = [Path(b) for b in bags]
    out = Path(out)
    if not paths:
        raise TissueTwinError("no bag given: pass one ROS bag per sequence")
    if reference is not None and config.reference_topic is not None:
        raise TissueTwinError("give either a reference PLY file or a reference topic, not both")
    if not overwrite and (out.exists() or out.is_symlink()):
        raise SessionExistsError(f"{out}: already exists; pass overwrite=True (--overwrite) to replace it")
    names = tuple(config.names) if config.names else tuple(f"seq{i:02d}" for i in range(len(paths)))
    roles = tuple(config.roles) if config.roles else default_roles(len(paths))
    for what, values in (("names", names), ("roles", roles)):
        if len(values) != len(paths):
            raise TissueTwinError(f"{len(paths)} bag(s) but {len(values)} sequence {what} "
                                  f"{list(values)}: give one per bag")
    # the metadata as far as it is known now must pass the reader's checks
    probe_meta = {"format": FORMAT,
                  "phantom": {"shape": "box", "size": [float(v) for v in config.phantom_size],
                              "mass": config.phantom_mass, "fixed": "bottom"},
                  "probe": {"shape": "sphere", "radius": config.probe_radius},
                  "camera": {"rate_hz": config.camera_rate_hz or 1.0,
                             "depth_accuracy": config.depth_accuracy},
                  "sequences": [{"name": n, "role": r} for n, r in zip(names, roles)]}
    base = SessionMeta.from_json(probe_meta, out / "session.json")
    corner_data = _load_corners(corners)
    ref_points = None if reference is None else read_ply(reference)
    if ref_points is not None:
        check_cloud_metres(Path(reference), ref_points)
    ref_source = None if reference is None else str(reference)

    # ---- pass 1: poses, forces, cloud stamps, intrinsics, reference --------------------
    plans: list[_BagPlan] = []
    intrinsics: dict | None = None
    n_bags = len(paths)
    for i, (path, name, role) in enumerate(zip(paths, names, roles)):
        report(0.2 * i / n_bags, f"{path.name}: poses and stamps")
        with Bag(path, config.time_source) as bag:
            scan = scan_bag(bag, config, intrinsics=intrinsics is None,
                            reference=config.reference_topic is not None and ref_points is None)
        if config.t0_ns is not None:
            t0_ns = int(config.t0_ns)
        else:
            t0_ns = int(min(scan.poses.stamps[0], scan.clouds.stamps[scan.clouds.keep].min()))
        if intrinsics is None:
            intrinsics = scan.intrinsics
        if scan.reference is not None and ref_points is None:
            ref_points, ref_source = scan.reference, f"{path} {config.reference_topic}"
        plans.append(_BagPlan(path, name, role, scan, t0_ns))
    if config.camera_info_topic and intrinsics is None:
        raise BagError(paths[0], f"no bag has the camera-info topic {config.camera_info_topic!r}")
    if config.reference_topic and ref_points is None:
        raise BagError(paths[0], f"no bag has the reference topic {config.reference_topic!r}")

    if config.camera_rate_hz is not None:
        rate = float(config.camera_rate_hz)
    else:
        gaps = np.concatenate([np.diff(np.sort(p.scan.clouds.stamps[p.scan.clouds.keep])) for p in plans])
        if gaps.size == 0:
            raise BagError(paths[0], f"cannot measure the camera rate from one frame per bag on "
                                     f"{config.cloud_topic!r}: pass camera_rate_hz (--camera-rate)")
        rate = float(NS_PER_S / np.median(gaps))

    source = {
        "kind": "ros-bag",
        "importer": "tissuetwin import-bag",
        "topics": {k: v for k, v in (("pose", config.pose_topic), ("cloud", config.cloud_topic),
                                     ("force", config.force_topic),
                                     ("camera_info", config.camera_info_topic),
                                     ("reference", config.reference_topic)) if v},
        "time_source": config.time_source,
        "tip_offset": [float(v) for v in config.tip_offset],
    }
    if config.force_topic:
        source["negate_force"] = bool(config.negate_force)
    raw = {"format": FORMAT, "source": source,
           "sequences": [{"name": p.name, "role": p.role, "bag": p.path.name, "t0_ns": p.t0_ns,
                          "pose_type": short_type(p.scan.poses.msgtype)} for p in plans]}
    meta = SessionMeta(phantom=base.phantom, probe=base.probe,
                       camera=CameraSpec(rate_hz=rate, depth_accuracy=config.depth_accuracy,
                                         intrinsics=intrinsics),
                       sequences=base.sequences, raw=raw)

    # ---- pass 2: write ----------------------------------------------------------------
    results: list[ImportedSequence] = []
    total_frames = max(sum(int(p.scan.clouds.keep.sum()) for p in plans), 1)
    done = 0
    with SessionWriter(out, meta, overwrite=overwrite) as writer:
        writer.write_corners(corner_data)
        if ref_points is not None:
            writer.write_reference(ref_points)
        if phantom_stl is not None:
            writer.write_phantom_stl(Path(phantom_stl))
        for plan in plans:
            poses = plan.scan.poses
            kt = (poses.stamps - plan.t0_ns).astype(np.float64) / NS_PER_S
            writer.write_kinematics(plan.name, Kinematics(
                t=kt, position=poses.position, quaternion=poses.quaternion, force=plan.scan.force))
            stats = _write_clouds(writer, plan, config, kt,
                                  lambda k, m, _d=done: report(0.2 + 0.8 * (_d + k) / total_frames, m))
            done += int(plan.scan.clouds.keep.sum())
            results.append(ImportedSequence(
                name=plan.name, role=plan.role, bag=plan.path, pose_type=poses.msgtype,
                t0_ns=plan.t0_ns, kinematics_rows=int(kt.size), frames=stats["frames"],
                duplicate_poses=poses.duplicates,
                duplicate_clouds=int((~plan.scan.clouds.keep).sum()), empty_clouds=stats["empty"],
                nonfinite_points=stats["nonfinite"], frames_outside_kinematics=stats["outside"],
                force_rows_clamped=plan.scan.force_clamped,
                frame_ids={"pose": sorted(poses.frame_ids), "cloud": sorted(plan.scan.clouds.frame_ids)},
            ))
        path = writer.finish()
    report(1.0, f"{sum(r.frames for r in results)} frames from {n_bags} bag(s)")
    return BagImportResult(path=path, sequences=tuple(results), camera_rate_hz=rate,
                           intrinsics=intrinsics, reference=ref_source)


def _write_clouds(writer: SessionWriter, plan: _BagPlan, config: BagImportConfig,
                  kin_t: np.ndarray, progress: Callable[[int, str], None]) -> dict:
    """Pass 2: stream the cloud topic into ``writer`` in stamp order (a heap holds back at
    most ``lag`` clouds, the most any arrives late in the bag's log order)."""
    topic = config.cloud_topic
    cp = plan.scan.clouds
    kept = np.flatnonzero(cp.keep)
    rank = np.empty(cp.stamps.size, dtype=np.int64)
    rank[kept[np.argsort(cp.stamps[kept], kind="stable")]] = np.arange(kept.size)
    every = max(kept.size // 50, 1)
    stats = {"frames": 0, "empty": 0, "nonfinite": 0, "outside": 0}
    heap: list[tuple[int, int, np.ndarray, int]] = []  # (rank, stamp ns, points, total)
    next_rank = 0

    def flush(limit: int) -> None:
        nonlocal next_rank
        while len(heap) > limit:
            r, stamp, points, total = heapq.heappop(heap)
            assert r == next_rank, (r, next_rank)  # the planned lag guarantees stamp order
            next_rank += 1
            if points.shape[0] == 0:
                stats["empty"] += 1
                continue
            stats["nonfinite"] += total - points.shape[0]
            t = (stamp - plan.t0_ns) / NS_PER_S
            if not kin_t[0] <= t <= kin_t[-1]:
                stats["outside"] += 1
            try:  # the writer's millimetre check, reported against the bag and topic
                writer.write_frame(plan.name, r, t, points)
            except UnitsError as exc:
                raise UnitsError(plan.path, f"cloud topic {topic!r}, message at {stamp_text(stamp)} s: "
                                            f"{exc.problem}") from None
            stats["frames"] += 1
            if r % every == 0:
                progress(r, f"{plan.name}: frame {r + 1}/{kept.size}")

    with Bag(plan.path, config.time_source) as bag:
        conns, _ = bag.connections(topic, (CLOUD_TYPE,), "cloud")
        for i, (_, stamp, msg) in enumerate(bag.messages(conns, f"cloud topic {topic!r}")):
            if i >= cp.stamps.size or stamp != cp.stamps[i]:
                raise BagError(plan.path, f"cloud topic {topic!r} changed while it was read")
            if not cp.keep[i]:
                continue
            points, total = decode_cloud(bag, topic, stamp, msg)
            heapq.heappush(heap, (int(rank[i]), stamp, points, total))
            flush(cp.lag)
        flush(0)
    if stats["frames"] == 0:
        raise BagError(plan.path, f"cloud topic {topic!r}: none of its {kept.size} clouds has a "
                                  f"finite point")
    return stats
