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
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import TissueTwinError, UnitsError
from core.io.checks import FORMAT, check_cloud_metres, check_positions_metres
from core.io.meta import CameraSpec, SessionMeta
from core.io.ply import read_ply
from core.io.records import Corners, Kinematics
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

POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped")
"""Accepted message types of the pose topic (rosbags' names; ROS1's
``geometry_msgs/PoseStamped`` is the same type)."""
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
"""Message type of the cloud and reference topics."""
FORCE_TYPE = "geometry_msgs/msg/WrenchStamped"
"""Message type of the optional force topic."""
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
"""Message type of the optional camera-info topic."""

PAPER_PHANTOM_SIZE = (0.0687, 0.0393, 0.0358)
"""Default phantom box, m (x length, y width, z height; Wu et al. 2020, Sec. 4.1)."""
PAPER_PHANTOM_MASS = 0.10401
"""Default phantom mass, kg (Wu et al. 2020, Sec. 4.1)."""
PAPER_PROBE_RADIUS = 0.005
"""Default probe sphere radius, m (``SESSION_FORMAT.md``'s example and the virtual lab's
nominal probe)."""

_NS = 1_000_000_000
_FLOAT_FIELDS = {7: "f4", 8: "f8"}  # sensor_msgs/PointField FLOAT32, FLOAT64
_MAX_REORDER = 64
"""Most messages a cloud may arrive late (log order vs header stamps) and still be
ordered; clouds are buffered in memory for that many messages at most."""

ProgressCallback = Callable[[float, str], None]


class BagError(TissueTwinError):
    """A ROS bag cannot be read or lacks what the import needs.

    Attributes:
        path: the bag (file or folder), as given.
        problem: one sentence saying what is wrong (names the topic when there is one).
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


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
# PointCloud2
# --------------------------------------------------------------------------------------


def pointcloud2_xyz(msg: Any) -> tuple[np.ndarray, int]:
    """The ``x``, ``y``, ``z`` of a ``sensor_msgs/PointCloud2`` as an (N, 3) array.

    Handles any field offsets and ``point_step``, padded rows (``row_step > width *
    point_step``), organised (``height > 1``) and unorganised clouds, both byte orders,
    and float32 or float64 coordinates, with one numpy structured view (no per-point
    loop).

    Args:
        msg: a deserialised ``PointCloud2`` (rosbags typestore message, ROS1 or ROS2).

    Returns:
        ``(points, total)``: points (N, 3) float64 in the cloud's frame and unit, only the
        rows whose three coordinates are finite, in message order; ``total`` the number
        of points the message holds (``height * width``), so ``total - N`` were dropped.

    Raises:
        ValueError: a missing or non-float x/y/z field, a field outside ``point_step``, or
            ``data`` shorter than the header promises.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise ValueError(f"PointCloud2 lacks field(s) {missing}; has {sorted(fields)}")
    step = int(msg.point_step)
    height, width, row_step = int(msg.height), int(msg.width), int(msg.row_step)
    endian = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for c in "xyz":
        f = fields[c]
        if int(f.datatype) not in _FLOAT_FIELDS:
            raise ValueError(f"PointCloud2 field {c!r} must be FLOAT32 (7) or FLOAT64 (8), "
                             f"got datatype {int(f.datatype)}")
        fmt = endian + _FLOAT_FIELDS[int(f.datatype)]
        if int(f.offset) + np.dtype(fmt).itemsize > step:
            raise ValueError(f"PointCloud2 field {c!r} at offset {int(f.offset)} does not fit in "
                             f"point_step {step}")
        formats.append(fmt)
        offsets.append(int(f.offset))
    n = height * width
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if n == 0:
        return np.empty((0, 3), dtype=np.float64), 0
    if row_step < width * step:
        raise ValueError(f"PointCloud2 row_step {row_step} < width {width} x point_step {step}")
    need = (height - 1) * row_step + width * step
    if data.size < need:
        raise ValueError(f"PointCloud2 data holds {data.size} bytes, its header needs {need} "
                         f"({height} x {width} points, point_step {step}, row_step {row_step})")
    if row_step != width * step:  # drop the padding at the end of every row
        rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step),
                                               strides=(row_step, 1))
        data = np.ascontiguousarray(rows).reshape(-1)
    dtype = np.dtype({"names": ["x", "y", "z"], "formats": formats, "offsets": offsets,
                      "itemsize": step})
    view = np.frombuffer(data, dtype=dtype, count=n)
    points = np.empty((n, 3), dtype=np.float64)
    for j, c in enumerate("xyz"):
        points[:, j] = view[c]
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        points = points[finite]
    return points, n


# --------------------------------------------------------------------------------------
# Reading one bag
# --------------------------------------------------------------------------------------


def _stamp(ns: int) -> str:
    """Integer ns of ROS time as exact seconds (``1700000000.000000001``); a float would
    round at 1.7e9 s to about 0.2 us."""
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    return f"{sign}{abs(ns) // _NS}.{abs(ns) % _NS:09d}"


def _short(msgtype: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs/PoseStamped``."""
    return msgtype.replace("/msg/", "/")


_MAGIC = {b"#ROSBAG V2.0": "ROS1 bag", b"\x89MCAP": "MCAP file", b"SQLite format 3": "SQLite file"}


def _check_bag_path(path: Path) -> None:
    """Refuse what rosbags would misread, with a message saying what was expected."""
    if not (path.exists() or path.is_symlink()):
        raise BagError(path, "does not exist")
    expected = ("expected a ROS1 .bag file, a ROS2 bag folder (with metadata.yaml) or a "
                "ROS2 .db3 / .mcap file")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise BagError(path, f"folder without metadata.yaml: {expected}")
        return
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise BagError(path, f"cannot open ({exc.strerror})") from exc
    kind = next((k for m, k in _MAGIC.items() if head.startswith(m)), None)
    suffix = path.suffix.lower()
    if kind is None:
        raise BagError(path, f"not a ROS bag (starts with {head[:12]!r}): {expected}")
    want = {".bag": "ROS1 bag", ".mcap": "MCAP file", ".db3": "SQLite file"}.get(suffix)
    if want != kind:
        raise BagError(path, f"holds a {kind} but is named {path.name!r}: {expected} "
                             f"(rename it to the matching suffix)")


_CUT_SHORT = ("; if the recording was cut short, `rosbag reindex` (ROS1), `ros2 bag reindex` (sqlite3) "
              "or `mcap recover` (MCAP) may repair it")


@contextmanager
def _translate(path: Path, what: str, hint: str = ""):
    """Turn the many exceptions a damaged bag raises inside rosbags into :class:`BagError`."""
    try:
        yield
    except TissueTwinError:
        raise
    except Exception as exc:  # rosbags, struct, sqlite (apsw), lz4/zstd raise many types
        detail = str(exc) or type(exc).__name__
        raise BagError(path, f"cannot read the bag ({what}): {type(exc).__name__}: {detail}{hint}") from exc


class _Bag:
    """One open bag: its topics and deserialised messages (errors name the bag)."""

    def __init__(self, path: Path, time_source: str):
        from rosbags.highlevel import AnyReader  # noqa: PLC0415 (only when importing bags)
        from rosbags.typesys import Stores, get_typestore  # noqa: PLC0415

        self.path = path
        self.time_source = time_source
        _check_bag_path(path)
        with _translate(path, "opening it", _CUT_SHORT):
            self.reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self.reader.open()
        try:
            with _translate(path, "listing its topics"):
                self.topics = {name: (info.msgtype, info.msgcount, list(info.connections))
                               for name, info in self.reader.topics.items()}
        except BagError:
            self.reader.close()
            raise

    def close(self) -> None:
        with _translate(self.path, "closing it"):
            self.reader.close()

    def __enter__(self) -> _Bag:
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.close()
        except BagError:
            if exc[0] is None:
                raise

    def describe(self) -> str:
        """``/a (pkg/Type, 12 messages), ...`` for error messages."""
        if not self.topics:
            return "no topics at all"
        return ", ".join(f"{n} ({_short(t or '?')}, {c} messages)"
                         for n, (t, c, _) in sorted(self.topics.items()))

    def has(self, topic: str) -> bool:
        return topic in self.topics

    def connections(self, topic: str, accepted: Sequence[str], role: str) -> tuple[list, str]:
        """Connections of ``topic`` after checking it exists, has messages and one of the
        ``accepted`` types. Returns (connections, msgtype)."""
        if topic not in self.topics:
            raise BagError(self.path, f"no {role} topic {topic!r}; the bag has: {self.describe()}")
        msgtype, count, conns = self.topics[topic]
        types = {c.msgtype for c in conns}
        if len(types) != 1 or next(iter(types)) not in accepted:
            got = " and ".join(sorted(_short(t) for t in types))
            want = " or ".join(_short(t) for t in accepted)
            raise BagError(self.path, f"{role} topic {topic!r} carries {got}; expected {want}")
        if count == 0:
            raise BagError(self.path, f"{role} topic {topic!r} has no messages")
        return conns, next(iter(types))

    def messages(self, conns: list, what: str) -> Iterator[tuple[str, int, Any]]:
        """Yield ``(topic, stamp_ns, message)`` of ``conns`` in the bag's log order; the
        stamp is the header's or the log time, as configured. ``what`` names the topics in
        error messages."""
        it = self.reader.messages(connections=conns)
        while True:
            with _translate(self.path, f"reading {what}", _CUT_SHORT):
                try:
                    conn, log_ns, raw = next(it)
                except StopIteration:
                    return
                msg = self.reader.deserialize(raw, conn.msgtype)
            if self.time_source == "log":
                stamp = int(log_ns)
            else:
                st = msg.header.stamp
                stamp = int(st.sec) * _NS + int(st.nanosec)
            yield conn.topic, stamp, msg


def _frame_id(msg: Any) -> str:
    return str(getattr(msg.header, "frame_id", ""))


def _zero_stamps(bag: _Bag, topic: str, stamps: np.ndarray) -> None:
    if bag.time_source == "header" and stamps.size and not stamps.any():
        raise BagError(bag.path, f"every header.stamp of topic {topic!r} is zero: pass "
                                 f"time_source='log' (--time-source log) to use the bag's log times")


def _first_unique(stamps: np.ndarray) -> tuple[np.ndarray, int]:
    """Indices that sort ``stamps`` keeping the first (log-order) message per stamp."""
    order = np.argsort(stamps, kind="stable")
    keep = np.ones(order.size, dtype=bool)
    keep[1:] = np.diff(stamps[order]) != 0
    return order[keep], int((~keep).sum())


@dataclass
class _Poses:
    stamps: np.ndarray  # (K,) int64 ns, strictly increasing
    position: np.ndarray  # (K, 3) m, sphere centre, robot frame
    quaternion: np.ndarray  # (K, 4) x, y, z, w, unit norm
    msgtype: str
    duplicates: int
    frame_ids: set[str]


@dataclass
class _CloudPlan:
    """Cloud stamps in log order and how to put them in stamp order."""

    stamps: np.ndarray  # (M,) int64 ns, log order
    keep: np.ndarray  # (M,) bool: the first message with its stamp
    lag: int  # most messages one arrives (in log order) after its place in stamp order
    frame_ids: set[str]


@dataclass
class _Scan:
    """Pass 1 over one bag."""

    poses: _Poses
    clouds: _CloudPlan
    force: np.ndarray | None  # (K, 3) N at the pose stamps
    force_clamped: int
    intrinsics: dict | None
    reference: np.ndarray | None  # (N, 3) m, camera frame


def _scan(bag: _Bag, config: BagImportConfig, *, intrinsics: bool, reference: bool) -> _Scan:
    """Read every topic but the clouds' points in one pass over the bag (a ROS1 bag
    interleaves all topics in its chunks, so one pass reads the file once)."""
    pose_conns, pose_type = bag.connections(config.pose_topic, POSE_TYPES, "pose")
    cloud_conns, _ = bag.connections(config.cloud_topic, (CLOUD_TYPE,), "cloud")
    conns = {id(c): c for c in pose_conns + cloud_conns}
    topics = [config.pose_topic, config.cloud_topic]
    if config.force_topic:
        conns.update((id(c), c) for c in bag.connections(config.force_topic, (FORCE_TYPE,), "force")[0])
        topics.append(config.force_topic)
    want_info = intrinsics and bool(config.camera_info_topic) and bag.has(config.camera_info_topic)
    if want_info:
        info_conns = bag.connections(config.camera_info_topic, (CAMERA_INFO_TYPE,), "camera-info")[0]
        conns.update((id(c), c) for c in info_conns)
        topics.append(config.camera_info_topic)
    want_ref = reference and bool(config.reference_topic) and bag.has(config.reference_topic)
    if want_ref:
        conns.update((id(c), c) for c in bag.connections(config.reference_topic, (CLOUD_TYPE,), "reference")[0])
        topics.append(config.reference_topic)

    is_pose = pose_type == POSE_TYPES[0]
    pose_st, pose_v, pose_ids = [], [], set()
    cloud_st, cloud_ids = [], set()
    force_st, force_v = [], []
    info: dict | None = None
    ref: np.ndarray | None = None
    for topic, stamp, msg in bag.messages(list(conns.values()), f"topics {topics}"):
        if topic == config.pose_topic:
            if is_pose:
                p, q = msg.pose.position, msg.pose.orientation
            else:
                p, q = msg.transform.translation, msg.transform.rotation
            pose_st.append(stamp)
            pose_v.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
            pose_ids.add(_frame_id(msg))
        if topic == config.cloud_topic:
            cloud_st.append(stamp)
            cloud_ids.add(_frame_id(msg))
        if topic == config.force_topic:
            f = msg.wrench.force
            force_st.append(stamp)
            force_v.append((f.x, f.y, f.z))
        if want_info and info is None and topic == config.camera_info_topic:
            info = _intrinsics(bag, topic, msg)
        if want_ref and ref is None and topic == config.reference_topic:
            ref = _reference(bag, topic, stamp, msg)

    poses = _poses(bag, config, np.array(pose_st, dtype=np.int64),
                   np.array(pose_v, dtype=np.float64).reshape(-1, 7), pose_type, pose_ids)
    clouds = _plan_clouds(bag, config.cloud_topic, np.array(cloud_st, dtype=np.int64), cloud_ids)
    force, clamped = None, 0
    if config.force_topic:
        force, clamped = _force(bag, config, np.array(force_st, dtype=np.int64),
                                np.array(force_v, dtype=np.float64).reshape(-1, 3), poses.stamps)
    return _Scan(poses, clouds, force, clamped, info, ref)


def _poses(bag: _Bag, config: BagImportConfig, st: np.ndarray, v: np.ndarray, msgtype: str,
           frame_ids: set[str]) -> _Poses:
    """Sort, deduplicate and check the pose messages; move to the sphere centre."""
    topic = config.pose_topic
    _zero_stamps(bag, topic, st)
    idx, dup = _first_unique(st)
    st, v = st[idx], v[idx]
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise BagError(bag.path, f"pose topic {topic!r} has a non-finite pose at "
                                 f"{_stamp(st[i])} s: {v[i].tolist()}")
    qn = np.linalg.norm(v[:, 3:], axis=1)
    if (qn < 1e-9).any():
        i = int(np.flatnonzero(qn < 1e-9)[0])
        raise BagError(bag.path, f"pose topic {topic!r} has a zero quaternion at {_stamp(st[i])} s")
    q = v[:, 3:] / qn[:, None]
    pos = v[:, :3]
    offset = np.asarray(config.tip_offset, dtype=np.float64)
    if offset.any():
        from scipy.spatial.transform import Rotation  # noqa: PLC0415 (slow import, rarely needed)

        pos = pos + Rotation.from_quat(q).apply(offset)
    try:
        check_positions_metres(bag.path, pos, "probe position")
    except UnitsError:
        norms = np.linalg.norm(pos, axis=1)
        i = int(np.argmax(norms))
        raise UnitsError(bag.path, f"pose topic {topic!r}: the probe at {_stamp(st[i])} s is "
                                   f"{norms[i]:.6g} m from the robot origin ({pos[i].tolist()}): "
                                   f"looks like millimetres; ROS (REP 103) and the session format "
                                   f"use metres") from None
    return _Poses(st, pos, q, msgtype, dup, frame_ids)


def _force(bag: _Bag, config: BagImportConfig, st: np.ndarray, v: np.ndarray,
           pose_stamps: np.ndarray) -> tuple[np.ndarray, int]:
    """Force at the pose stamps, (K, 3) N, by linear interpolation; and the number of
    pose rows outside the force samples' span (given the nearest sample, at most two
    force periods away)."""
    topic = config.force_topic
    if st.size == 0:  # pragma: no cover (connections() refuses empty topics)
        raise BagError(bag.path, f"force topic {topic!r} has no messages")
    _zero_stamps(bag, topic, st)
    idx, _ = _first_unique(st)
    st, v = st[idx], v[idx]
    if not np.isfinite(v).all():
        i = int(np.flatnonzero(~np.isfinite(v).all(axis=1))[0])
        raise BagError(bag.path, f"force topic {topic!r} has a non-finite force at {_stamp(st[i])} s")
    if config.negate_force:
        v = -v
    base = st[0]
    ft = (st - base).astype(np.float64) / _NS
    kt = (pose_stamps - base).astype(np.float64) / _NS
    period = float(np.median(np.diff(ft))) if ft.size > 1 else 0.0
    outside = (kt < ft[0]) | (kt > ft[-1])
    if outside.any() and float(np.maximum(ft[0] - kt, kt - ft[-1]).max()) > 2 * period:
        raise BagError(bag.path, f"force topic {topic!r} spans {_stamp(st[0])}-{_stamp(st[-1])} s "
                                 f"but the poses span {_stamp(pose_stamps[0])}-"
                                 f"{_stamp(pose_stamps[-1])} s: the forces must cover the poses")
    force = np.stack([np.interp(kt, ft, v[:, j]) for j in range(3)], axis=1)
    return force, int(outside.sum())


def _intrinsics(bag: _Bag, topic: str, msg: Any) -> dict:
    """``camera.intrinsics`` from a ``CameraInfo`` (``K`` in ROS1, ``k`` in ROS2)."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(-1)
    if k.shape != (9,) or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0:
        raise BagError(bag.path, f"camera-info topic {topic!r}: K must be a 3x3 camera matrix "
                                 f"with positive focal lengths, got {k.tolist()}")
    return {"width": int(msg.width), "height": int(msg.height), "fx": float(k[0]),
            "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5])}


def _cloud(bag: _Bag, topic: str, stamp: int, msg: Any) -> tuple[np.ndarray, int]:
    try:
        return pointcloud2_xyz(msg)
    except ValueError as exc:
        raise BagError(bag.path, f"cloud topic {topic!r}, message at {_stamp(stamp)} s: {exc}") from None


def _check_cloud_units(bag: _Bag, topic: str, stamp: int, points: np.ndarray) -> None:
    try:
        check_cloud_metres(bag.path, points)
    except UnitsError as exc:
        raise UnitsError(bag.path, f"topic {topic!r}, cloud at {_stamp(stamp)} s: {exc.problem}") from None


def _reference(bag: _Bag, topic: str, stamp: int, msg: Any) -> np.ndarray:
    points, total = _cloud(bag, topic, stamp, msg)
    if points.shape[0] == 0:
        raise BagError(bag.path, f"reference topic {topic!r}: its first cloud has no finite point "
                                 f"(of {total})")
    _check_cloud_units(bag, topic, stamp, points)
    return points


def _plan_clouds(bag: _Bag, topic: str, st: np.ndarray, frame_ids: set[str]) -> _CloudPlan:
    _zero_stamps(bag, topic, st)
    idx, _ = _first_unique(st)
    keep = np.zeros(st.size, dtype=bool)
    keep[idx] = True
    # rank of each kept message in stamp order against its position in log order
    kept = np.flatnonzero(keep)
    rank = np.empty(kept.size, dtype=np.int64)
    rank[np.argsort(st[kept], kind="stable")] = np.arange(kept.size)
    lag = int(np.max(np.arange(kept.size) - rank)) if kept.size else 0
    if lag > _MAX_REORDER:
        raise BagError(bag.path, f"cloud topic {topic!r}: header stamps run up to {lag} messages "
                                 f"out of log order (at most {_MAX_REORDER} can be reordered)")
    return _CloudPlan(st, keep, lag, frame_ids)


# --------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------


@dataclass
class _BagPlan:
    path: Path
    name: str
    role: str
    scan: _Scan
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
        with _Bag(path, config.time_source) as bag:
            scan = _scan(bag, config, intrinsics=intrinsics is None,
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
        rate = float(_NS / np.median(gaps))

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
                          "pose_type": _short(p.scan.poses.msgtype)} for p in plans]}
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
            kt = (poses.stamps - plan.t0_ns).astype(np.float64) / _NS
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
            t = (stamp - plan.t0_ns) / _NS
            if not kin_t[0] <= t <= kin_t[-1]:
                stats["outside"] += 1
            try:  # the writer's millimetre check, reported against the bag and topic
                writer.write_frame(plan.name, r, t, points)
            except UnitsError as exc:
                raise UnitsError(plan.path, f"cloud topic {topic!r}, message at {_stamp(stamp)} s: "
                                            f"{exc.problem}") from None
            stats["frames"] += 1
            if r % every == 0:
                progress(r, f"{plan.name}: frame {r + 1}/{kept.size}")

    with _Bag(plan.path, config.time_source) as bag:
        conns, _ = bag.connections(topic, (CLOUD_TYPE,), "cloud")
        for i, (_, stamp, msg) in enumerate(bag.messages(conns, f"cloud topic {topic!r}")):
            if i >= cp.stamps.size or stamp != cp.stamps[i]:
                raise BagError(plan.path, f"cloud topic {topic!r} changed while it was read")
            if not cp.keep[i]:
                continue
            points, total = _cloud(bag, topic, stamp, msg)
            heapq.heappush(heap, (int(rank[i]), stamp, points, total))
            flush(cp.lag)
        flush(0)
    if stats["frames"] == 0:
        raise BagError(plan.path, f"cloud topic {topic!r}: none of its {kept.size} clouds has a "
                                  f"finite point")
    return stats
