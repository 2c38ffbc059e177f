"""``tissuetwin import-bag``: turn ROS bags of a dVRK recording into a session folder.

The reading and conversion live in :mod:`core.io.rosbag`; this module only maps options
to a :class:`core.io.rosbag.BagImportConfig` and prints what each bag became.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.errors import TissueTwinError


def _seconds_to_ns(text: str) -> int:
    """``"1700000000.123456789"`` -> 1700000000123456789 (exact: no float rounding)."""
    from decimal import Decimal, InvalidOperation

    try:
        value = Decimal(text) * 1_000_000_000
    except InvalidOperation:
        raise argparse.ArgumentTypeError(f"expected seconds of ROS time, got {text!r}") from None
    if not value.is_finite():
        raise argparse.ArgumentTypeError(f"expected finite seconds, got {text!r}")
    return int(value.to_integral_value())


def cmd_import_bag(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from app.cli import _progress
    from core.io.rosbag import BagImportConfig, import_bags

    # metadata options left unset keep BagImportConfig's defaults (the paper's phantom and probe)
    metadata = {
        "phantom_size": tuple(args.size) if args.size else None,
        "phantom_mass": args.mass,
        "probe_radius": args.probe_radius,
        "depth_accuracy": args.depth_accuracy,
    }
    try:
        config = BagImportConfig(
            pose_topic=args.pose_topic,
            cloud_topic=args.cloud_topic,
            force_topic=args.force_topic,
            negate_force=args.negate_force,
            camera_info_topic=args.camera_info_topic,
            reference_topic=args.reference_topic,
            time_source=args.time_source,
            t0_ns=args.t0,
            tip_offset=tuple(args.tip_offset),
            camera_rate_hz=args.camera_rate,
            names=tuple(args.names) if args.names else None,
            roles=tuple(args.roles) if args.roles else None,
            **{k: v for k, v in metadata.items() if v is not None},
        )
    except ValueError as exc:  # e.g. a non-finite --tip-offset or --camera-rate 0
        raise TissueTwinError(f"import-bag: {exc}") from None
    with _progress(f"importing {len(args.bags)} bag(s)") as cb:
        result = import_bags(args.bags, args.out, corners=args.corners, config=config,
                             reference=args.reference, phantom_stl=args.phantom_stl,
                             overwrite=args.overwrite, callback=cb)
    table = Table(title=f"{result.path} (camera {result.camera_rate_hz:.3f} Hz)")
    for col in ("sequence", "role", "bag", "kinematics", "frames", "dropped"):
        table.add_column(col, justify="right" if col in ("kinematics", "frames") else "left")
    for s in result.sequences:
        dropped = [f"{n} {what}" for n, what in (
            (s.duplicate_poses, "repeated poses"), (s.duplicate_clouds, "repeated clouds"),
            (s.empty_clouds, "empty clouds"), (s.nonfinite_points, "NaN points")) if n]
        table.add_row(s.name, s.role, s.bag.name, str(s.kinematics_rows), str(s.frames), ", ".join(dropped))
    console = Console()
    console.print(table)
    types = sorted({s.pose_type.split("/")[-1] for s in result.sequences})
    console.print(f"poses: {', '.join(types)} on {args.pose_topic}"
                  + (f" (tip offset {list(args.tip_offset)} m)" if any(args.tip_offset) else ""))
    outside = {s.name: s.frames_outside_kinematics for s in result.sequences if s.frames_outside_kinematics}
    if outside:
        console.print(f"[yellow]warning:[/yellow] frames outside the kinematics' time span {outside}: "
                      "do the robot and the camera share a clock (--time-source)?")
    clamped = {s.name: s.force_rows_clamped for s in result.sequences if s.force_rows_clamped}
    if clamped:
        console.print(f"forces: kinematics rows beyond the first or last force sample took the nearest one {clamped}")
    console.print(f"reference cloud: {result.reference or 'none'}; intrinsics: "
                  f"{'from ' + args.camera_info_topic if result.intrinsics else 'none'}")
    print(f"session written to {result.path}")
    return 0


def register(sub) -> None:
    """Add the ``import-bag`` subcommand to the ``tissuetwin`` parser's subparsers."""
    p = sub.add_parser(
        "import-bag",
        help="turn ROS1/ROS2 bags of a dVRK recording into a session folder (one bag per sequence)",
        description="Each BAG (a ROS1 .bag file, a ROS2 bag folder, or a ROS2 .db3/.mcap file) becomes one "
                    "sequence: the pose topic its kinematics.csv, the cloud topic its frames. The phantom's "
                    "corner touches (calibration/corners.csv, robot frame) are not in a bag: give them with "
                    "--corners.",
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="ROS bags, one per sequence, in order")
    p.add_argument("--out", required=True, help="session folder to create")
    p.add_argument("--corners", required=True, type=Path,
                   help="corners.csv in the session format (corner,x,y,z: probe sphere centre touching each "
                        "top corner, robot frame, m)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing session folder")
    g = p.add_argument_group("topics")
    g.add_argument("--pose-topic", default="/PSM1/measured_cp",
                   help="geometry_msgs/PoseStamped or TransformStamped, robot base frame (default /PSM1/measured_cp)")
    g.add_argument("--cloud-topic", default="/camera/depth/color/points",
                   help="sensor_msgs/PointCloud2, camera frame (default /camera/depth/color/points)")
    g.add_argument("--force-topic", default=None,
                   help="optional geometry_msgs/WrenchStamped: force of the probe on the phantom, robot base "
                        "frame, N (kinematics columns fx, fy, fz)")
    g.add_argument("--negate-force", action="store_true", help="the force topic reports the phantom's force on the probe")
    g.add_argument("--camera-info-topic", default=None, help="optional sensor_msgs/CameraInfo (camera.intrinsics)")
    g.add_argument("--reference-topic", default=None,
                   help="optional PointCloud2 of the phantom at rest, no instrument: its first message is "
                        "calibration/reference.ply")
    g = p.add_argument_group("clock and probe")
    g.add_argument("--time-source", choices=("header", "log"), default="header",
                   help="header.stamp (default) or the bag's log time (for zero stamps)")
    g.add_argument("--t0", type=_seconds_to_ns, default=None, metavar="SECONDS",
                   help="time origin in s of ROS time for every bag, e.g. 1700000000.25 (read to the "
                        "nanosecond; default: each bag's first pose or cloud)")
    g.add_argument("--tip-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("DX", "DY", "DZ"),
                   help="probe sphere centre in the pose's tool frame, m (default 0 0 0)")
    g = p.add_argument_group("metadata a bag does not carry")
    g.add_argument("--names", nargs="+", default=None, help="sequence name per bag (default seq00, seq01, ...)")
    g.add_argument("--roles", nargs="+", default=None, choices=("train", "validation", "test"),
                   help="role per bag (default: test for one bag; train, test for two; validation, test, "
                        "train... for more)")
    g.add_argument("--size", type=float, nargs=3, default=None, metavar=("LX", "LY", "LZ"),
                   help="phantom box, m (default: the paper's, Wu et al. 2020)")
    g.add_argument("--mass", type=float, default=None, help="phantom mass, kg (default: the paper's)")
    g.add_argument("--probe-radius", type=float, default=None, help="probe sphere radius, m (default 0.005)")
    g.add_argument("--depth-accuracy", type=float, default=None, help="camera depth accuracy, m (default 0.002)")
    g.add_argument("--camera-rate", type=float, default=None,
                   help="frame rate, Hz (default: 1 / median frame interval)")
    g.add_argument("--reference", default=None, help="a PLY file to store as calibration/reference.ply instead")
    g.add_argument("--phantom-stl", default=None, help="an STL of the phantom's rest surface, phantom frame, m")
    p.set_defaults(func=cmd_import_bag)
