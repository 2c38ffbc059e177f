"""Planning a ROS bag import for :mod:`core.io.rosbag`: pass 1 over one bag.

This module holds the scan of one bag (:func:`scan_bag`): every topic the import reads
but the clouds' points, in one pass, turned into checked, sorted, deduplicated poses
(:class:`Poses`, moved to the probe sphere centre), forces interpolated to the pose
stamps, the camera intrinsics, the reference cloud, and the plan that puts the clouds in
stamp order in pass 2 (:class:`CloudPlan`); :class:`Scan` gathers them. The bag itself
is read through :mod:`core.io.rosbag_reader`; :mod:`core.io.rosbag` writes the session.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from core.errors import UnitsError
from core.io.checks import check_cloud_metres, check_positions_metres
from core.io.rosbag_reader import (
    CAMERA_INFO_TYPE,
    CLOUD_TYPE,
    FORCE_TYPE,
    NS_PER_S,
    POSE_TYPES,
    Bag,
    BagError,
    decode_cloud,
    header_frame_id,
    stamp_text,
)

if TYPE_CHECKING:  # the config lives with the import, which imports this module
    from core.io.rosbag import BagImportConfig

__all__ = ["CloudPlan", "Poses", "Scan", "scan_bag"]

_MAX_REORDER = 64
"""Most messages a cloud may arrive late (log order vs header stamps) and still be
ordered; clouds are buffered in memory for that many messages at most."""


def _zero_stamps(bag: Bag, topic: str, stamps: np.ndarray) -> None:
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
class Poses:
    """The pose topic of one bag, sorted by stamp and deduplicated (the first message per
    stamp kept), checked finite, in metres, and moved to the probe sphere centre.

    Attributes:
        stamps: (K,) int64 ns of ROS time, strictly increasing.
        position: (K, 3) float64 m, sphere centre, robot frame.
        quaternion: (K, 4) float64 x, y, z, w, unit norm (tool in robot frame).
        msgtype: the topic's message type (rosbags' name, one of ``POSE_TYPES``).
        duplicates: messages dropped because an earlier one had the same stamp.
        frame_ids: the ``header.frame_id`` values seen.
    """

    stamps: np.ndarray  # (K,) int64 ns, strictly increasing
    position: np.ndarray  # (K, 3) m, sphere centre, robot frame
    quaternion: np.ndarray  # (K, 4) x, y, z, w, unit norm
    msgtype: str
    duplicates: int
    frame_ids: set[str]


@dataclass
class CloudPlan:
    """Cloud stamps in log order and how to put them in stamp order.

    Attributes:
        stamps: (M,) int64 ns of ROS time, one per cloud message, in the bag's log order.
        keep: (M,) bool, true for the first message (log order) with its stamp.
        lag: the most messages a kept cloud arrives (log order) after its place in stamp
            order, at most 64: pass 2 holds back that many clouds to reorder them.
        frame_ids: the ``header.frame_id`` values seen.
    """

    stamps: np.ndarray  # (M,) int64 ns, log order
    keep: np.ndarray  # (M,) bool: the first message with its stamp
    lag: int  # most messages one arrives (in log order) after its place in stamp order
    frame_ids: set[str]


@dataclass
class Scan:
    """Pass 1 over one bag.

    Attributes:
        poses: the pose topic (:class:`Poses`, K rows).
        clouds: the cloud topic's stamps and order (:class:`CloudPlan`).
        force: (K, 3) float64 N at the pose stamps (sign flipped if the config says so),
            or None without a force topic.
        force_clamped: pose rows outside the force samples' span (given the nearest).
        intrinsics: ``camera.intrinsics`` (``width``, ``height`` px; ``fx``, ``fy``,
            ``cx``, ``cy`` px) from the first camera-info message, or None.
        reference: (N, 3) float64 m, camera frame: the first reference cloud's finite
            points, or None.
    """

    poses: Poses
    clouds: CloudPlan
    force: np.ndarray | None  # (K, 3) N at the pose stamps
    force_clamped: int
    intrinsics: dict | None
    reference: np.ndarray | None  # (N, 3) m, camera frame


def scan_bag(bag: Bag, config: BagImportConfig, *, intrinsics: bool, reference: bool) -> Scan:
    """Read every topic but the clouds' points in one pass over the bag (a ROS1 bag
    interleaves all topics in its chunks, so one pass reads the file once).

    Args:
        bag: the open bag.
        config: the import's topics, clock, tip offset and force sign
            (:class:`core.io.rosbag.BagImportConfig`).
        intrinsics: read the camera-info topic (if configured and in this bag).
        reference: read the reference topic (if configured and in this bag).

    Returns:
        :class:`Scan`: poses (sorted, deduplicated, sphere centre, m), the cloud plan,
        forces at the pose stamps (N), intrinsics and reference cloud (m), as asked.

    Raises:
        BagError: a missing topic, one of the wrong type or without messages; every
            header stamp zero; a non-finite or zero-norm pose; a non-finite force or
            forces not covering the poses; a bad camera matrix; a reference cloud
            without a finite point or that cannot be decoded; clouds more than 64
            messages out of stamp order; or a damaged bag.
        UnitsError: positions > 5 m from the robot origin, or a reference cloud with
            median distance > 5 m (millimetres).
    """
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
            pose_ids.add(header_frame_id(msg))
        if topic == config.cloud_topic:
            cloud_st.append(stamp)
            cloud_ids.add(header_frame_id(msg))
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
    return Scan(poses, clouds, force, clamped, info, ref)


def _poses(bag: Bag, config: BagImportConfig, st: np.ndarray, v: np.ndarray, msgtype: str,
           frame_ids: set[str]) -> Poses:
    """Sort, deduplicate and check the pose messages; move to the sphere centre."""
    topic = config.pose_topic
    _zero_stamps(bag, topic, st)
    idx, dup = _first_unique(st)
    st, v = st[idx], v[idx]
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise BagError(bag.path, f"pose topic {topic!r} has a non-finite pose at "
                                 f"{stamp_text(st[i])} s: {v[i].tolist()}")
    qn = np.linalg.norm(v[:, 3:], axis=1)
    if (qn < 1e-9).any():
        i = int(np.flatnonzero(qn < 1e-9)[0])
        raise BagError(bag.path, f"pose topic {topic!r} has a zero quaternion at {stamp_text(st[i])} s")
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
        raise UnitsError(bag.path, f"pose topic {topic!r}: the probe at {stamp_text(st[i])} s is "
                                   f"{norms[i]:.6g} m from the robot origin ({pos[i].tolist()}): "
                                   f"looks like millimetres; ROS (REP 103) and the session format "
                                   f"use metres") from None
    return Poses(st, pos, q, msgtype, dup, frame_ids)


def _force(bag: Bag, config: BagImportConfig, st: np.ndarray, v: np.ndarray,
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
        raise BagError(bag.path, f"force topic {topic!r} has a non-finite force at {stamp_text(st[i])} s")
    if config.negate_force:
        v = -v
    base = st[0]
    ft = (st - base).astype(np.float64) / NS_PER_S
    kt = (pose_stamps - base).astype(np.float64) / NS_PER_S
    period = float(np.median(np.diff(ft))) if ft.size > 1 else 0.0
    outside = (kt < ft[0]) | (kt > ft[-1])
    if outside.any() and float(np.maximum(ft[0] - kt, kt - ft[-1]).max()) > 2 * period:
        raise BagError(bag.path, f"force topic {topic!r} spans {stamp_text(st[0])}-{stamp_text(st[-1])} s "
                                 f"but the poses span {stamp_text(pose_stamps[0])}-"
                                 f"{stamp_text(pose_stamps[-1])} s: the forces must cover the poses")
    force = np.stack([np.interp(kt, ft, v[:, j]) for j in range(3)], axis=1)
    return force, int(outside.sum())


def _intrinsics(bag: Bag, topic: str, msg: Any) -> dict:
    """``camera.intrinsics`` from a ``CameraInfo`` (``K`` in ROS1, ``k`` in ROS2)."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(-1)
    if k.shape != (9,) or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0:
        raise BagError(bag.path, f"camera-info topic {topic!r}: K must be a 3x3 camera matrix "
                                 f"with positive focal lengths, got {k.tolist()}")
    return {"width": int(msg.width), "height": int(msg.height), "fx": float(k[0]),
            "fy": float(k[4]), "cx": float(k[2]), "cy": float(k[5])}


def _check_cloud_units(bag: Bag, topic: str, stamp: int, points: np.ndarray) -> None:
    try:
        check_cloud_metres(bag.path, points)
    except UnitsError as exc:
        raise UnitsError(bag.path, f"topic {topic!r}, cloud at {stamp_text(stamp)} s: "
                                   f"{exc.problem}") from None


def _reference(bag: Bag, topic: str, stamp: int, msg: Any) -> np.ndarray:
    points, total = decode_cloud(bag, topic, stamp, msg)
    if points.shape[0] == 0:
        raise BagError(bag.path, f"reference topic {topic!r}: its first cloud has no finite point "
                                 f"(of {total})")
    _check_cloud_units(bag, topic, stamp, points)
    return points


def _plan_clouds(bag: Bag, topic: str, st: np.ndarray, frame_ids: set[str]) -> CloudPlan:
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
    return CloudPlan(st, keep, lag, frame_ids)
