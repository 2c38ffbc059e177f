"""Reading ROS bags for :mod:`core.io.rosbag`: the bag layer under the import.

This module holds what touches a bag file and its messages: the message types the import
accepts, :class:`BagError`, the check that a path is a bag rosbags can read, the
translation of rosbags' many exceptions into :class:`BagError`, :class:`Bag` (one open bag:
its topics and its deserialised messages with their stamps), and the decoding of
``sensor_msgs/PointCloud2`` (:func:`pointcloud2_xyz`, :func:`decode_cloud`) and of stamps
and header frame ids. It knows nothing of sessions; :mod:`core.io.rosbag_scan` plans the
import from the messages and :mod:`core.io.rosbag` writes the session.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import TissueTwinError

__all__ = [
    "BagError",
    "Bag",
    "POSE_TYPES",
    "CLOUD_TYPE",
    "FORCE_TYPE",
    "CAMERA_INFO_TYPE",
    "NS_PER_S",
    "decode_cloud",
    "header_frame_id",
    "pointcloud2_xyz",
    "short_type",
    "stamp_text",
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

NS_PER_S = 1_000_000_000
"""Nanoseconds per second: ROS time is integer ns (``sec * NS_PER_S + nanosec``), and a
time in s is ``(stamp - t0) / NS_PER_S``."""
_FLOAT_FIELDS = {7: "f4", 8: "f8"}  # sensor_msgs/PointField FLOAT32, FLOAT64


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


def decode_cloud(bag: Bag, topic: str, stamp: int, msg: Any) -> tuple[np.ndarray, int]:
    """:func:`pointcloud2_xyz` of a message read from ``bag``, with errors naming the bag.

    Args:
        bag: the open bag the message came from (only its path is used, for errors).
        topic: the message's topic, for errors.
        stamp: the message's stamp, integer ns of ROS time, for errors.
        msg: a deserialised ``PointCloud2``.

    Returns:
        ``(points, total)`` as :func:`pointcloud2_xyz`: (N, 3) float64 finite points in
        the cloud's frame and unit (m for ROS), and the message's point count.

    Raises:
        BagError: the cloud cannot be decoded (the :class:`ValueError` of
            :func:`pointcloud2_xyz`, with the topic and the stamp in s).
    """
    try:
        return pointcloud2_xyz(msg)
    except ValueError as exc:
        raise BagError(bag.path, f"cloud topic {topic!r}, message at {stamp_text(stamp)} s: {exc}") from None


# --------------------------------------------------------------------------------------
# Reading one bag
# --------------------------------------------------------------------------------------


def stamp_text(ns: int) -> str:
    """Integer ns of ROS time as exact seconds (``1700000000.000000001``); a float would
    round at 1.7e9 s to about 0.2 us.

    Args:
        ns: a stamp, integer ns (anything ``int()`` accepts, e.g. a numpy int64; may be
            negative).

    Returns:
        The stamp in s as text with nine decimals, for messages. Raises nothing for an
        integer.
    """
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    return f"{sign}{abs(ns) // NS_PER_S}.{abs(ns) % NS_PER_S:09d}"


def short_type(msgtype: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs/PoseStamped``.

    Args:
        msgtype: a message type name as rosbags spells it (ROS2 style, with ``/msg/``).

    Returns:
        The name as ROS1 spells it (unchanged if it has no ``/msg/``), for messages and
        ``session.json``'s ``pose_type``. Raises nothing.
    """
    return msgtype.replace("/msg/", "/")


def header_frame_id(msg: Any) -> str:
    """The ``header.frame_id`` of a deserialised stamped message as text, ``""`` if the
    header has none.

    Raises:
        AttributeError: ``msg`` has no ``header`` (not a stamped message).
    """
    return str(getattr(msg.header, "frame_id", ""))


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


class Bag:
    """One open bag: its topics and deserialised messages (errors name the bag).

    Args:
        path: a ROS1 ``.bag`` file, a ROS2 bag folder (with ``metadata.yaml``), or a ROS2
            ``.db3`` / ``.mcap`` file.
        time_source: ``"header"`` (stamps are the messages' ``header.stamp``) or
            ``"log"`` (the times the bag recorded them); stamps are integer ns.

    Attributes:
        path: the bag, as given.
        time_source: as given.
        reader: the open ``rosbags.highlevel.AnyReader``.
        topics: ``{topic: (msgtype, message count, connections)}``.

    Raises:
        BagError: the path is missing, not a bag or misnamed (the suffix does not match
            the content), or rosbags cannot open it, list its topics, read a message or
            close it (the message says which, with a repair hint for truncated bags).

    Use as a context manager (``with Bag(path, "header") as bag:``); it closes the bag.
    """

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

    def __enter__(self) -> Bag:
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
        return ", ".join(f"{n} ({short_type(t or '?')}, {c} messages)"
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
            got = " and ".join(sorted(short_type(t) for t in types))
            want = " or ".join(short_type(t) for t in accepted)
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
                stamp = int(st.sec) * NS_PER_S + int(st.nanosec)
            yield conn.topic, stamp, msg
