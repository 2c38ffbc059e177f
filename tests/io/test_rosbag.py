"""ROS bag import (core.io.rosbag, ``tissuetwin import-bag``): a generated session written
to ROS1 and ROS2 bags by rosbags' own writers and imported back must reproduce itself;
bad bags and bad topics give errors that name the bag and the topic.

The bags are written here with rosbags' writers and an independent PointCloud2 encoder
(numpy structured arrays in three different layouts), not with the importer's code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from app.cli import main
from core.errors import SessionFormatError, TissueTwinError, UnitsError
from core.io import Corners, SessionExistsError, read_session
from core.io.rosbag import BagError, BagImportConfig, import_bags, pointcloud2_xyz

NS = 1_000_000_000
EPOCH_NS = 1_700_000_000 * NS  # ROS time of t = 0 in the bags (Nov 2023)
POSE = "/PSM1/measured_cp"
CLOUD = "/camera/depth/color/points"
FORCE = "/PSM1/body/measured_cf"
INFO = "/camera/depth/camera_info"
REF = "/phantom/reference"
TIP = np.array([0.0, 0.002, -0.011])  # sphere centre in the tool frame, m (ROS2 bags)
# Stamps are integer nanoseconds: a time read back differs from the session's float64
# seconds by at most half a nanosecond (plus float rounding of the subtraction).
T_TOL = 1e-9

TS1 = get_typestore(Stores.ROS1_NOETIC)
TS2 = get_typestore(Stores.ROS2_HUMBLE)


# --------------------------------------------------------------------------------------
# Writing bags from a session
# --------------------------------------------------------------------------------------


def _header(ts, ns: int, frame: str):
    T = ts.types
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // NS, nanosec=ns % NS)
    if ts is TS1:
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


# Three PointCloud2 layouts, each (fields [(name, offset, datatype)], point_step,
# big-endian, organised in rows of this width or None, row padding bytes).
LAYOUTS = {
    # RealSense-like: x y z float32, rgb at 16, 20-byte points, one row
    "xyzrgb": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("rgb", 16, 7)], 20, False, None, 0),
    # big-endian, fields out of order, a float64 coordinate, organised with row padding
    "shuffled_be": ([("intensity", 0, 7), ("z", 4, 7), ("x", 8, 8), ("y", 16, 7)], 24, True, 64, 12),
    # plain x y z, 16-byte points, organised without padding
    "xyz16": ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 16, False, 50, 0),
}


def encode_cloud(ts, ns: int, points: np.ndarray, layout: str, rng: np.random.Generator,
                 nan_fraction: float = 0.1):
    """A PointCloud2 of ``points`` (in order) with NaN points (invalid pixels) inserted
    at random places, in the given layout."""
    fields, step, big, row, pad = LAYOUTS[layout]
    nan = rng.random(len(points) + int(len(points) * nan_fraction)) < nan_fraction
    n_total = max(len(nan), len(points) + int(nan.sum()))
    full = np.full((n_total, 3), np.nan)
    valid = np.flatnonzero(~np.r_[nan, np.zeros(n_total - len(nan), bool)])[: len(points)]
    full[valid] = points
    if row is not None:  # organised: fill the last row with NaN
        height = -(-n_total // row)
        full = np.vstack([full, np.full((height * row - n_total, 3), np.nan)])
        width = row
    else:
        height, width = 1, n_total
    e = ">" if big else "<"
    kinds = {7: "f4", 8: "f8"}
    dtype = np.dtype({"names": [f[0] for f in fields], "formats": [e + kinds[f[2]] for f in fields],
                      "offsets": [f[1] for f in fields], "itemsize": step})
    arr = np.zeros(height * width, dtype=dtype)
    for j, c in enumerate("xyz"):
        arr[c] = full[:, j]
    rows = arr.tobytes()
    row_step = width * step + pad
    if pad:
        rows = b"".join(rows[r * width * step:(r + 1) * width * step] + b"\xab" * pad for r in range(height))
    T = ts.types
    PF = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, ns, "camera_depth_optical_frame"), height=height, width=width,
        fields=[PF(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=big, point_step=step, row_step=row_step,
        data=np.frombuffer(rows, dtype=np.uint8), is_dense=False)


def pose_msg(ts, ns: int, p, q, kind: str):
    T = ts.types
    if kind == "pose":
        return T["geometry_msgs/msg/PoseStamped"](
            header=_header(ts, ns, "PSM1_base"),
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, ns, "PSM1_base"), child_frame_id="PSM1_tool",
        transform=T["geometry_msgs/msg/Transform"](translation=T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                                                   rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))


def wrench_msg(ts, ns: int, f):
    T = ts.types
    V = T["geometry_msgs/msg/Vector3"]
    return T["geometry_msgs/msg/WrenchStamped"](header=_header(ts, ns, "PSM1_base"),
                                               wrench=T["geometry_msgs/msg/Wrench"](force=V(x=f[0], y=f[1], z=f[2]), torque=V(x=0.0, y=0.0, z=0.0)))


def camera_info_msg(ts, ns: int, intr: dict):
    T = ts.types
    k = np.array([intr["fx"], 0, intr["cx"], 0, intr["fy"], intr["cy"], 0, 0, 1], dtype=np.float64)
    kw = dict(header=_header(ts, ns, "camera_depth_optical_frame"), height=intr["height"], width=intr["width"],
              distortion_model="plumb_bob", binning_x=0, binning_y=0,
              roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    arrays = dict(d=np.zeros(5), k=k, r=np.eye(3).ravel(), p=np.c_[k.reshape(3, 3), np.zeros(3)].ravel())
    if ts is TS1:
        arrays = {key.upper(): v for key, v in arrays.items()}
    return T["sensor_msgs/msg/CameraInfo"](**kw, **arrays)


def write_bag(path: Path, storage: str, items: list[tuple[str, str, int, object]]) -> Path:
    """Write ``(topic, msgtype, log time ns, message)`` items with rosbags' writers;
    ``storage``: ``ros1``, ``sqlite3`` or ``mcap``. Items are written in log-time order."""
    ts = TS1 if storage == "ros1" else TS2
    items = sorted(items, key=lambda it: it[2])
    if storage == "ros1":
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        conns = {}
        for topic, msgtype, _, _ in items:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, log_ns, msg in items:
            data = ts.serialize_ros1(msg, msgtype) if storage == "ros1" else ts.serialize_cdr(msg, msgtype)
            writer.write(conns[topic], log_ns, data)
    return path


def session_to_bag(session, name: str, path: Path, storage: str, *, pose_kind: str, layout: str,
                   rng: np.random.Generator, extras: bool = False, force: np.ndarray | None = None,
                   max_frames: int | None = None, swap_clouds: bool = False,
                   duplicate_pose: bool = False, epoch_ns: int = EPOCH_NS) -> Path:
    """One sequence of ``session`` as a bag whose stamps are ``epoch_ns + t``.

    Extras (first bag only): camera info, the reference cloud, an unrelated topic.
    ``swap_clouds`` swaps the log order of every 7th pair of clouds (late arrivals);
    ``duplicate_pose`` repeats one pose message with the same stamp."""
    ts = TS1 if storage == "ros1" else TS2
    seq = session.sequences[name]
    kin = seq.kinematics
    stamps = epoch_ns + np.round(kin.t * NS).astype(np.int64)
    latency = 300_000  # log time = stamp + 0.3 ms
    items = []
    pose_type = "geometry_msgs/msg/PoseStamped" if pose_kind == "pose" else "geometry_msgs/msg/TransformStamped"
    positions = kin.position
    if pose_kind == "transform":  # the bag holds the tool frame; the sphere centre is TIP in it
        positions = positions - Rotation.from_quat(kin.quaternion).apply(TIP)
    for k, (ns, p, q) in enumerate(zip(stamps.tolist(), positions.tolist(), kin.quaternion.tolist())):
        items.append((POSE, pose_type, ns + latency, pose_msg(ts, ns, p, q, pose_kind)))
        if duplicate_pose and k == 5:
            items.append((POSE, pose_type, ns + latency + 1, pose_msg(ts, ns, p, q, pose_kind)))
        if force is not None:
            items.append((FORCE, "geometry_msgs/msg/WrenchStamped", ns + latency, wrench_msg(ts, ns, force[k])))
    n = len(seq) if max_frames is None else min(max_frames, len(seq))
    for i in range(n):
        ns = epoch_ns + int(round(float(seq.frames.t[i]) * NS))
        log = ns + latency
        if swap_clouds and i % 7 == 1:
            log = epoch_ns + int(round(float(seq.frames.t[i - 1]) * NS)) + latency - 1000
        items.append((CLOUD, "sensor_msgs/msg/PointCloud2", log, encode_cloud(ts, ns, seq.cloud(i), layout, rng)))
    if extras:
        t0 = int(stamps[0])
        items.append((INFO, "sensor_msgs/msg/CameraInfo", t0, camera_info_msg(ts, t0, session.meta.camera.intrinsics)))
        items.append((REF, "sensor_msgs/msg/PointCloud2", t0, encode_cloud(ts, t0, session.reference_cloud(), layout, rng)))
        items.append(("/notes", "std_msgs/msg/String", t0, ts.types["std_msgs/msg/String"](data="calibrated")))
    return write_bag(path, storage, items)


# --------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def original(small_session):
    return read_session(small_session)


@pytest.fixture(scope="module")
def ros1_bags(original, tmp_path_factory):
    """One ROS1 bag per sequence (PoseStamped; late clouds and a duplicate pose in seq00)."""
    d = tmp_path_factory.mktemp("ros1")
    rng = np.random.default_rng(0)
    return [session_to_bag(original, name, d / f"{name}.bag", "ros1", pose_kind="pose", layout="xyzrgb",
                           rng=rng, extras=(k == 0), swap_clouds=(k == 0), duplicate_pose=(k == 0))
            for k, name in enumerate(original.sequences)]


@pytest.fixture(scope="module")
def force_tracks(original):
    rng = np.random.default_rng(1)
    return {name: rng.normal(0.0, 0.3, size=(len(s.kinematics), 3)) for name, s in original.sequences.items()}


@pytest.fixture(scope="module")
def ros2_bags(original, force_tracks, tmp_path_factory):
    """One ROS2 bag per sequence (TransformStamped of the tool frame, forces), sqlite3 and
    MCAP storage alternating; each bag on its own clock (an hour apart, odd nanoseconds)."""
    d = tmp_path_factory.mktemp("ros2")
    rng = np.random.default_rng(2)
    bags = []
    for k, name in enumerate(original.sequences):
        storage = ("sqlite3", "mcap")[k % 2]
        layout = ("shuffled_be", "xyz16")[k % 2]
        bags.append(session_to_bag(original, name, d / name, storage, pose_kind="transform", layout=layout,
                                   rng=rng, extras=(k == 0), force=force_tracks[name],
                                   epoch_ns=EPOCH_NS + k * 3600 * NS + 123_456_789))
    return bags


@pytest.fixture(scope="module")
def tiny_bag(original, tmp_path_factory):
    """A short ROS1 bag (seq00, 4 frames) for the error tests."""
    d = tmp_path_factory.mktemp("tiny")
    name = next(iter(original.sequences))
    return session_to_bag(original, name, d / "tiny.bag", "ros1", pose_kind="pose", layout="xyz16",
                          rng=np.random.default_rng(3), max_frames=4)


def corners_csv(session) -> Path:
    return session.path / "calibration" / "corners.csv"


def assert_same_session(imported, original, *, shift: dict[str, float] | None = None, pos_atol: float = 0.0):
    """Same sequences (names, roles, order), kinematics, frame numbers, times (shifted by
    ``shift[name]`` s) and clouds point for point; same corners and reference."""
    assert [(s.name, s.role) for s in imported.sequences.values()] == \
        [(s.name, s.role) for s in original.sequences.values()]
    assert imported.corners == original.corners
    np.testing.assert_array_equal(imported.reference_cloud(), original.reference_cloud())
    np.testing.assert_array_equal(imported.meta.phantom.size, original.meta.phantom.size)
    assert imported.meta.probe == original.meta.probe
    assert imported.meta.camera.intrinsics == original.meta.camera.intrinsics
    for name, seq in original.sequences.items():
        got = imported.sequences[name]
        d = (shift or {}).get(name, 0.0)
        np.testing.assert_allclose(got.kinematics.t, seq.kinematics.t - d, rtol=0, atol=T_TOL)
        np.testing.assert_allclose(got.kinematics.position, seq.kinematics.position, rtol=0, atol=pos_atol)
        np.testing.assert_allclose(got.kinematics.quaternion, seq.kinematics.quaternion, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(got.frames.index, seq.frames.index)
        np.testing.assert_allclose(got.frames.t, seq.frames.t - d, rtol=0, atol=T_TOL)
        for i in range(len(seq)):
            np.testing.assert_array_equal(got.cloud(i), seq.cloud(i), err_msg=f"{name} frame {i}")


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


def test_ros1_bags_reproduce_the_session(original, ros1_bags, tmp_path):
    config = BagImportConfig(camera_info_topic=INFO, reference_topic=REF, t0_ns=EPOCH_NS,
                             camera_rate_hz=original.meta.camera.rate_hz,
                             roles=tuple(s.role for s in original.sequences.values()))
    result = import_bags(ros1_bags, tmp_path / "imported", corners=corners_csv(original), config=config)
    imported = read_session(result.path, check_clouds=True)
    assert_same_session(imported, original)  # PoseStamped positions pass exactly
    assert imported.meta.camera.rate_hz == original.meta.camera.rate_hz
    assert not imported.has_force
    first = result.sequences[0]
    assert first.pose_type == "geometry_msgs/msg/PoseStamped"
    assert first.duplicate_poses == 1 and first.duplicate_clouds == 0
    assert first.empty_clouds == 0 and first.nonfinite_points > 0  # the inserted NaN points
    assert first.frame_ids == {"pose": ["PSM1_base"], "cloud": ["camera_depth_optical_frame"]}
    assert [s.frames for s in result.sequences] == [len(s) for s in original.sequences.values()]
    raw = imported.meta.raw
    assert raw["source"]["topics"]["pose"] == POSE and raw["sequences"][0]["bag"] == "seq00.bag"
    assert raw["sequences"][0]["t0_ns"] == EPOCH_NS


def test_ros2_bags_reproduce_the_session(original, ros2_bags, force_tracks, tmp_path):
    """TransformStamped of the tool frame + tip offset, sqlite3 and MCAP, forces; default
    time origin (each sequence starts at its first message) and measured camera rate."""
    config = BagImportConfig(camera_info_topic=INFO, reference_topic=REF, force_topic=FORCE,
                             tip_offset=tuple(TIP), roles=tuple(s.role for s in original.sequences.values()))
    result = import_bags(ros2_bags, tmp_path / "imported", corners=corners_csv(original), config=config)
    imported = read_session(result.path, check_clouds=True)
    shift = {name: min(s.kinematics.t[0], s.frames.t[0]) for name, s in original.sequences.items()}
    # the tip offset is applied in float64: a few ulp of 0.5 m
    assert_same_session(imported, original, shift=shift, pos_atol=1e-12)
    for name, seq in imported.sequences.items():
        assert min(seq.kinematics.t[0], seq.frames.t[0]) == 0.0
        np.testing.assert_allclose(seq.kinematics.force, force_tracks[name], rtol=0, atol=1e-15)
    assert {s.pose_type for s in result.sequences} == {"geometry_msgs/msg/TransformStamped"}
    assert all(s.force_rows_clamped == 0 and s.frames_outside_kinematics == 0 for s in result.sequences)
    # camera rate measured as 1 / median frame interval: the lab's clock is 15 Hz with 1 ms jitter
    nominal = original.meta.camera.rate_hz
    measured = 1.0 / np.median(np.concatenate([np.diff(s.frames.t) for s in original.sequences.values()]))
    assert result.camera_rate_hz == pytest.approx(measured, rel=1e-6)
    assert abs(result.camera_rate_hz - nominal) / nominal < 0.02


# --------------------------------------------------------------------------------------
# PointCloud2 decoding
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize("ts", [TS1, TS2], ids=["ros1", "ros2"])
def test_pointcloud2_layouts_decode_in_order_without_nan(layout, ts):
    rng = np.random.default_rng(4)
    points = rng.normal(0.3, 0.05, size=(237, 3)).astype(np.float32).astype(np.float64)
    msg = encode_cloud(ts, EPOCH_NS, points, layout, rng, nan_fraction=0.3)
    # through the serialiser and back, as a bag would carry it
    if ts is TS1:
        msg = ts.deserialize_ros1(ts.serialize_ros1(msg, msg.__msgtype__), msg.__msgtype__)
    else:
        msg = ts.deserialize_cdr(ts.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)
    got, total = pointcloud2_xyz(msg)
    np.testing.assert_array_equal(got, points)
    assert total == msg.height * msg.width > len(points)


def test_pointcloud2_without_float_xyz_is_refused():
    msg = encode_cloud(TS2, EPOCH_NS, np.ones((3, 3)), "xyz16", np.random.default_rng(0))
    msg.fields[2].datatype = 5  # INT32 z
    with pytest.raises(ValueError, match="field 'z' must be FLOAT32"):
        pointcloud2_xyz(msg)
    msg.fields = msg.fields[:2]
    with pytest.raises(ValueError, match=r"lacks field\(s\) \['z'\]"):
        pointcloud2_xyz(msg)


# --------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------


def _nothing_left(out: Path) -> None:
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def test_unknown_topic_names_it_and_lists_the_topics(original, tiny_bag, tmp_path):
    out = tmp_path / "s"
    with pytest.raises(BagError) as exc:
        import_bags([tiny_bag], out, corners=corners_csv(original), config=BagImportConfig(pose_topic="/PSM2/measured_cp"))
    msg = str(exc.value)
    assert str(tiny_bag) in msg and "'/PSM2/measured_cp'" in msg
    assert f"{POSE} (geometry_msgs/PoseStamped" in msg and f"{CLOUD} (sensor_msgs/PointCloud2" in msg
    _nothing_left(out)


def test_wrong_message_type_is_named(original, tiny_bag, tmp_path):
    out = tmp_path / "s"
    with pytest.raises(BagError, match=r"pose topic '/camera/depth/color/points' carries sensor_msgs/PointCloud2; "
                                       r"expected geometry_msgs/PoseStamped or geometry_msgs/TransformStamped"):
        import_bags([tiny_bag], out, corners=corners_csv(original), config=BagImportConfig(pose_topic=CLOUD))
    with pytest.raises(BagError, match=r"cloud topic '/PSM1/measured_cp' carries geometry_msgs/PoseStamped"):
        import_bags([tiny_bag], out, corners=corners_csv(original), config=BagImportConfig(cloud_topic=POSE))
    _nothing_left(out)


def test_truncated_and_non_bag_files_are_named(original, tiny_bag, tmp_path):
    data = tiny_bag.read_bytes()
    cases = {
        "truncated.bag": data[: len(data) // 2],
        "header-only.bag": data[:100],
        "notes.bag": b"this is not a bag\n" * 10,
        "empty.bag": b"",
        "ros1.mcap": data,
    }
    for fname, content in cases.items():
        bag = tmp_path / fname
        bag.write_bytes(content)
        out = tmp_path / f"out-{fname}"
        with pytest.raises(BagError) as exc:
            import_bags([bag], out, corners=corners_csv(original))
        assert str(exc.value).startswith(f"{bag}: "), (fname, str(exc.value))
        _nothing_left(out)
    for storage in ("sqlite3", "mcap"):  # ROS2 storage files cut in half
        bag = session_to_bag(original, "seq00", tmp_path / f"ros2-{storage}", storage, pose_kind="pose",
                             layout="xyz16", rng=np.random.default_rng(6), max_frames=4)
        (f,) = [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        for given in (bag, f):  # the bag folder or its storage file
            with pytest.raises(BagError, match="cannot read the bag") as exc:
                import_bags([given], tmp_path / "o", corners=corners_csv(original))
            assert str(exc.value).startswith(f"{given}: ")
    _nothing_left(tmp_path / "o")
    with pytest.raises(BagError, match="does not exist"):
        import_bags([tmp_path / "missing.bag"], tmp_path / "o", corners=corners_csv(original))
    folder = tmp_path / "not-a-ros2-bag"
    folder.mkdir()
    with pytest.raises(BagError, match="folder without metadata.yaml"):
        import_bags([folder], tmp_path / "o", corners=corners_csv(original))


def test_millimetre_poses_are_refused_naming_bag_and_topic(original, tmp_path):
    ts = TS1
    kin = original.sequences["seq00"].kinematics
    items = [(POSE, "geometry_msgs/msg/PoseStamped", EPOCH_NS + k * NS // 100,
              pose_msg(ts, EPOCH_NS + k * NS // 100, (kin.position[k] * 1000).tolist(), kin.quaternion[k].tolist(), "pose"))
             for k in range(5)]
    cloud = original.sequences["seq00"].cloud(0)
    items.append((CLOUD, "sensor_msgs/msg/PointCloud2", EPOCH_NS, encode_cloud(ts, EPOCH_NS, cloud, "xyz16", np.random.default_rng(0))))
    bag = write_bag(tmp_path / "mm.bag", "ros1", items)
    with pytest.raises(UnitsError, match=r"mm.bag: pose topic '/PSM1/measured_cp': .* looks like millimetres"):
        import_bags([bag], tmp_path / "o", corners=corners_csv(original))
    # metres for the poses, millimetres for the clouds
    items = [(POSE, "geometry_msgs/msg/PoseStamped", EPOCH_NS + k * NS // 100,
              pose_msg(ts, EPOCH_NS + k * NS // 100, kin.position[k].tolist(), kin.quaternion[k].tolist(), "pose"))
             for k in range(5)]
    items += [(CLOUD, "sensor_msgs/msg/PointCloud2", EPOCH_NS + i, encode_cloud(ts, EPOCH_NS + i, cloud * (1000 if i else 1), "xyz16",
                                                                                np.random.default_rng(i))) for i in range(2)]
    bag = write_bag(tmp_path / "mm-cloud.bag", "ros1", items)
    with pytest.raises(UnitsError, match=r"mm-cloud.bag: cloud topic '/camera/depth/color/points', message at "
                                         r"1700000000.000000001 s: median point distance .* looks like millimetres"):
        import_bags([bag], tmp_path / "o", corners=corners_csv(original), config=BagImportConfig(camera_rate_hz=30.0))
    _nothing_left(tmp_path / "o")


def test_zero_header_stamps_ask_for_log_time(original, tmp_path):
    ts = TS1
    kin = original.sequences["seq00"].kinematics
    rng = np.random.default_rng(7)
    items = [(POSE, "geometry_msgs/msg/PoseStamped", EPOCH_NS + k * NS // 100,
              pose_msg(ts, 0, kin.position[k].tolist(), kin.quaternion[k].tolist(), "pose")) for k in range(20)]
    items += [(CLOUD, "sensor_msgs/msg/PointCloud2", EPOCH_NS + i * NS // 15,
               encode_cloud(ts, 0, original.sequences["seq00"].cloud(i), "xyz16", rng)) for i in range(3)]
    bag = write_bag(tmp_path / "zero.bag", "ros1", items)
    with pytest.raises(BagError, match=r"every header.stamp of topic '/PSM1/measured_cp' is zero: .*--time-source log"):
        import_bags([bag], tmp_path / "o", corners=corners_csv(original))
    result = import_bags([bag], tmp_path / "o", corners=corners_csv(original),
                         config=BagImportConfig(time_source="log", t0_ns=EPOCH_NS))
    s = read_session(result.path)
    np.testing.assert_allclose(s.sequences["seq00"].kinematics.t, np.arange(20) / 100, rtol=0, atol=T_TOL)
    np.testing.assert_allclose(s.sequences["seq00"].frames.t, np.arange(3) / 15, rtol=0, atol=T_TOL)
    assert result.camera_rate_hz == pytest.approx(15.0, rel=1e-6)


def _short_bag(original, path: Path, storage: str, *, n_poses: int = 20, force_rows: slice | None = None,
               force: np.ndarray | None = None) -> Path:
    """Poses every 10 ms, three clouds of seq00, optional forces at some of the pose stamps."""
    ts = TS1 if storage == "ros1" else TS2
    seq = original.sequences["seq00"]
    kin = seq.kinematics
    items = [(POSE, "geometry_msgs/msg/PoseStamped", EPOCH_NS + k * NS // 100,
              pose_msg(ts, EPOCH_NS + k * NS // 100, kin.position[k].tolist(), kin.quaternion[k].tolist(), "pose"))
             for k in range(n_poses)]
    rng = np.random.default_rng(8)
    items += [(CLOUD, "sensor_msgs/msg/PointCloud2", EPOCH_NS + i * NS // 15,
               encode_cloud(ts, EPOCH_NS + i * NS // 15, seq.cloud(i), "xyzrgb", rng)) for i in range(3)]
    if force is not None:
        rows = range(n_poses)[force_rows or slice(None)]
        items += [(FORCE, "geometry_msgs/msg/WrenchStamped", EPOCH_NS + k * NS // 100,
                   wrench_msg(ts, EPOCH_NS + k * NS // 100, force[k])) for k in rows]
    return write_bag(path, storage, items)


def test_forces_must_cover_the_poses_and_can_be_negated(original, tmp_path):
    f = np.random.default_rng(9).normal(0.0, 0.5, size=(20, 3))
    config = BagImportConfig(force_topic=FORCE, negate_force=True, camera_rate_hz=15.0)
    bag = _short_bag(original, tmp_path / "force.bag", "ros1", force=f)
    s = read_session(import_bags([bag], tmp_path / "o", corners=corners_csv(original), config=config).path)
    np.testing.assert_array_equal(s.sequences["seq00"].kinematics.force, -f)
    # forces at every other pose stamp: linear interpolation in between
    bag = _short_bag(original, tmp_path / "half.bag", "ros1", force=f, force_rows=slice(0, 20, 2))
    result = import_bags([bag], tmp_path / "h", corners=corners_csv(original), config=config)
    got = read_session(result.path).sequences["seq00"].kinematics.force
    np.testing.assert_allclose(got[0:19:2], -f[0:19:2], rtol=0, atol=1e-15)
    np.testing.assert_allclose(got[1:18:2], -(f[0:17:2] + f[2:19:2]) / 2, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(got[19], -f[18])  # the last pose is 10 ms past the last force: nearest
    assert result.sequences[0].force_rows_clamped == 1
    # forces for the first half only: refused, naming the topic
    bag = _short_bag(original, tmp_path / "short.bag", "ros1", force=f, force_rows=slice(0, 10))
    with pytest.raises(BagError, match=r"short.bag: force topic '/PSM1/body/measured_cf' spans .* the forces must cover"):
        import_bags([bag], tmp_path / "x", corners=corners_csv(original), config=config)
    _nothing_left(tmp_path / "x")


def test_reference_ply_and_phantom_stl_files_are_stored(original, tmp_path):
    import trimesh

    stl = tmp_path / "phantom.stl"
    trimesh.creation.box(extents=original.meta.phantom.size).export(stl)
    bag = _short_bag(original, tmp_path / "b", "sqlite3")
    ref = original.path / "calibration" / "reference.ply"
    result = import_bags([bag], tmp_path / "o", corners=corners_csv(original), reference=ref, phantom_stl=stl,
                         config=BagImportConfig(camera_rate_hz=15.0, names=("poke",)))
    s = read_session(result.path)
    np.testing.assert_array_equal(s.reference_cloud(), original.reference_cloud())
    assert (s.path / "phantom.stl").read_bytes() == stl.read_bytes()
    assert result.reference == str(ref)
    with pytest.raises(TissueTwinError, match="not both"):
        import_bags([bag], tmp_path / "p", corners=corners_csv(original), reference=ref,
                    config=BagImportConfig(reference_topic=REF))


def test_empty_clouds_are_dropped_leaving_a_gap(original, tmp_path):
    ts = TS2
    kin = original.sequences["seq00"].kinematics
    items = [(POSE, "geometry_msgs/msg/PoseStamped", EPOCH_NS + int(kin.t[k] * NS),
              pose_msg(ts, EPOCH_NS + int(kin.t[k] * NS), kin.position[k].tolist(), kin.quaternion[k].tolist(), "pose"))
             for k in range(40)]
    rng = np.random.default_rng(5)
    cloud = original.sequences["seq00"].cloud(0)
    for i in range(3):
        ns = EPOCH_NS + (i + 1) * NS // 15
        pts = np.full((10, 3), np.nan) if i == 1 else cloud
        items.append((CLOUD, "sensor_msgs/msg/PointCloud2", ns, encode_cloud(ts, ns, pts, "xyzrgb", rng)))
    bag = write_bag(tmp_path / "gap", "mcap", items)
    result = import_bags([bag], tmp_path / "o", corners=corners_csv(original), config=BagImportConfig(camera_rate_hz=15.0))
    s = read_session(result.path)
    assert s.sequences["seq00"].frames.index.tolist() == [0, 2]
    assert result.sequences[0].empty_clouds == 1 and result.sequences[0].frames == 2
    assert s.meta.sequences[0].role == "test"  # one bag: default role


def test_bad_names_roles_and_corners_fail_before_reading(original, tiny_bag, tmp_path):
    with pytest.raises(SessionFormatError, match="role"):
        import_bags([tiny_bag], tmp_path / "o", corners=corners_csv(original), config=BagImportConfig(roles=("exam",)))
    with pytest.raises(TissueTwinError, match="2 sequence names"):
        import_bags([tiny_bag], tmp_path / "o", corners=corners_csv(original), config=BagImportConfig(names=("a", "b")))
    with pytest.raises(SessionFormatError, match="corners.csv"):
        import_bags([tiny_bag], tmp_path / "o", corners=tmp_path / "corners.csv")
    few = Corners(labels=("x0y0",), positions=original.corners.positions[:1])
    with pytest.raises(SessionFormatError, match="at least 4 corner touches"):
        import_bags([tiny_bag], tmp_path / "o", corners=few)
    _nothing_left(tmp_path / "o")


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


def test_cli_import_bag_refuses_an_existing_out_unless_overwrite(original, tiny_bag, tmp_path, capsys):
    out = tmp_path / "session"
    args = ["import-bag", str(tiny_bag), "--pose-topic", POSE, "--cloud-topic", CLOUD, "--out", str(out),
            "--corners", str(corners_csv(original)), "--roles", "train"]
    assert main(args + ["--t0", "1699999999.5"]) == 0
    s = read_session(out)
    assert [(q.name, q.role, len(q)) for q in s.sequences.values()] == [("seq00", "train", 4)]
    orig = original.sequences["seq00"]
    np.testing.assert_allclose(s.sequences["seq00"].kinematics.t, orig.kinematics.t + 0.5, rtol=0, atol=T_TOL)
    np.testing.assert_allclose(s.sequences["seq00"].frames.t, orig.frames.t[:4] + 0.5, rtol=0, atol=T_TOL)
    stamp = (out / "session.json").stat().st_mtime_ns
    capsys.readouterr()
    assert main(args) == 2
    assert "already exists" in capsys.readouterr().err
    assert (out / "session.json").stat().st_mtime_ns == stamp
    assert main(args + ["--overwrite", "--names", "poke1"]) == 0
    assert list(read_session(out).sequences) == ["poke1"]


def test_cli_reads_t0_to_the_nanosecond():
    from app.cli_bag import _seconds_to_ns

    assert _seconds_to_ns("1700000000.123456789") == 1_700_000_000_123_456_789  # float64 would be 1e-7 off
    assert _seconds_to_ns("-2.5") == -2_500_000_000


def test_cli_reports_a_missing_topic_in_one_line(original, tiny_bag, tmp_path, capsys):
    rc = main(["import-bag", str(tiny_bag), "--cloud-topic", "/camera/points", "--out", str(tmp_path / "s"),
               "--corners", str(corners_csv(original))])
    err = capsys.readouterr().err
    assert rc == 2
    # progress lines (stderr is not a terminal here) may come before it; the error is one line
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: ") and "'/camera/points'" in last and CLOUD in last
    assert sum(line.startswith("error") for line in err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "s").exists()
    with pytest.raises(SessionExistsError):
        import_bags([tiny_bag], tmp_path, corners=corners_csv(original))
