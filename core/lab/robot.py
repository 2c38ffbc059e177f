"""The virtual lab's robot: its base pose, its calibration touches and the kinematics it reports.

This module holds the random robot base pose of a seed (:func:`random_robot_pose`,
``T_phantom_robot``), the calibration touches the robot records before the sequences
(:func:`write_calibration`: the four top corners of the box, or the named landmarks of a
surface) and one sequence's ``kinematics.csv`` as the robot reports it
(:func:`recorded_kinematics`: encoder noise, the input effects ``time_offset`` and
``kinematic_offset``, and the optional force columns with their noise). Points and forces
are written in the robot frame; ``T_robot_phantom`` maps phantom points into it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from core.io import Kinematics, SessionWriter
    from core.lab.config import LabConfig
    from core.lab.phantom import Phantom
    from core.lab.probing import ProbePlan

__all__ = ["random_robot_pose", "quat_xyzw", "write_calibration", "recorded_kinematics"]

# --------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (Shoemake 1992, from a uniform unit quaternion)."""
    from scipy.spatial.transform import Rotation

    q = rng.standard_normal(4)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def random_robot_pose(rng: np.random.Generator, distance_range) -> np.ndarray:
    """(4, 4) T_phantom_robot: a random rotation and a robot base ``distance_range`` m away.

    float64; maps robot-frame points into the phantom frame (m). Draws from ``rng``: four
    normals (the rotation), three normals (the direction), one uniform (the distance in
    ``distance_range = (low, high)``, m), in that order.
    """
    R = _random_rotation(rng)
    d = rng.standard_normal(3)
    origin_phantom = d / np.linalg.norm(d) * rng.uniform(*distance_range)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = origin_phantom
    return T


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def quat_xyzw(R: np.ndarray) -> np.ndarray:
    """(4,) float64 unit quaternion ``x, y, z, w`` (scalar last, ``w >= 0``) of a (3, 3)
    rotation matrix, in the frame the matrix maps into."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    return q if q[3] >= 0 else -q


def write_calibration(writer: SessionWriter, phantom: Phantom, cfg: LabConfig, r_true: float,
                      T_robot_phantom: np.ndarray, corner_rng: np.random.Generator) -> None:
    """Write the calibration touches: the box's four top corners
    (``calibration/corners.csv``), or a surface's landmarks (``calibration/landmarks.csv``,
    with ``phantom.stl``).

    Args:
        writer: the open session writer.
        phantom: the lab's phantom (phantom frame, m).
        cfg: the lab: ``corner_touches`` per corner or landmark, ``corner_noise`` (m,
            standard deviation per axis of a touch).
        r_true: true probe radius, m (the sphere's lowest point touches a corner; a
            landmark is touched along its normal).
        T_robot_phantom: (4, 4) float64, maps phantom points into the robot frame.
        corner_rng: the calibration's noise stream (3 normals per touch, corner by corner).

    Raises:
        SessionFormatError, ColumnError, UnitsError: the writer's checks of the touches
            (:meth:`core.io.SessionWriter.write_corners`, ``write_landmark_touches``) or of
            the STL (``write_phantom_stl``).
    """
    from core.io import Corners, LandmarkTouches

    size = phantom.size
    if phantom.landmarks is None:
        # ---- corner-touch calibration (true radius: the sphere's lowest point touches)
        labels, touches = [], []
        for label, (cx, cy) in (("x0y0", (0, 0)), ("x1y0", (1, 0)), ("x0y1", (0, 1)), ("x1y1", (1, 1))):
            corner = np.array([cx * size[0], cy * size[1], size[2] + r_true])
            for _ in range(cfg.corner_touches):
                labels.append(label)
                touches.append(corner + corner_rng.normal(0.0, cfg.corner_noise, 3))
        writer.write_corners(Corners(labels=tuple(labels),
                                     positions=_transform(T_robot_phantom, np.asarray(touches))))
    else:
        # ---- landmark touches: the sphere touches each landmark along its normal
        labels, touches = [], []
        for (label, point), normal in zip(phantom.landmarks.items(), phantom.normals):
            centre = np.asarray(point) + r_true * normal
            for _ in range(cfg.corner_touches):
                labels.append(label)
                touches.append(centre + corner_rng.normal(0.0, cfg.corner_noise, 3))
        writer.write_landmark_touches(LandmarkTouches(
            labels=tuple(labels), positions=_transform(T_robot_phantom, np.asarray(touches))))
        import trimesh

        writer.write_phantom_stl(trimesh.Trimesh(*phantom.surface, process=False))


def recorded_kinematics(plan: ProbePlan, kin_t: np.ndarray, frame_times: np.ndarray, force: np.ndarray,
                        cfg: LabConfig, *, with_force: bool, time_offset: float, kin_offset: np.ndarray,
                        T_robot_phantom: np.ndarray, srng: np.random.Generator) -> Kinematics:
    """One sequence's kinematics as the robot reports them (``kinematics.csv``).

    Args:
        plan: the sequence's true probe plan (phantom frame).
        kin_t: (K,) float64 kinematic times, s.
        frame_times: (F,) float64 camera frame times, s (the times of ``force``).
        force: (F, 3) contact force of the truth simulation, N, phantom frame.
        cfg: the lab: ``encoder_noise`` (m) and ``force_noise`` (N), standard deviations per axis.
        with_force: add the force columns (interpolated to ``kin_t - time_offset``,
            turned into the robot frame, plus noise).
        time_offset: the ``time_offset`` effect, s (0 without it): the row written at
            time t holds the true position at t - time_offset.
        kin_offset: (3,) the ``kinematic_offset`` effect, m, phantom frame (zeros without it).
        T_robot_phantom: (4, 4) float64, maps phantom points into the robot frame.
        srng: the sequence's noise stream: (K, 3) encoder normals, then (K, 3) force
            normals if ``with_force``.

    Returns:
        the :class:`core.io.Kinematics` (robot frame, m, N).

    Raises:
        ValueError: arrays of inconsistent shapes (:class:`core.io.Kinematics`).
    """
    from core.io import Kinematics

    p_true_at_kin = plan.trajectory(kin_t - time_offset)
    p_written = _transform(T_robot_phantom, p_true_at_kin - kin_offset)
    p_written = p_written + srng.normal(0.0, cfg.encoder_noise, p_written.shape)
    q = quat_xyzw(T_robot_phantom[:3, :3] @ plan.R_phantom_tool)
    f_written = None
    if with_force:
        f_ph = np.stack([np.interp(kin_t - time_offset, frame_times, force[:, j])
                         for j in range(3)], axis=1)
        f_written = f_ph @ T_robot_phantom[:3, :3].T
        f_written = f_written + srng.normal(0.0, cfg.force_noise, f_written.shape)
    return Kinematics(
        t=kin_t, position=p_written, quaternion=np.tile(q, (len(kin_t), 1)), force=f_written)
