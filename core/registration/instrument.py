"""The instrument's pose in the phantom frame, and how well raw camera frames support it.

The robot's kinematics put the probe in the phantom frame (through ``T_phantom_robot``);
raw camera frames show it. Camera calibration (:mod:`core.registration.icp`) uses the two
to tell apart the poses a symmetric phantom leaves open (Wu et al. 2020 initialise by
hand instead):

* :func:`probe_pose_phantom` -- probe sphere centres and tool z-axes at given times,
  phantom frame: positions interpolated linearly, orientations by Slerp (Shoemake 1985).
* :func:`instrument_hints` -- ``hints`` for :func:`core.registration.icp.calibrate_camera`:
  raw camera frames of one sequence with the probe's phantom-frame pose at their times
  (type :data:`Hint`).
* :func:`instrument_support` -- under a candidate ``T_phantom_camera``, the number of raw
  hint points that lie on the instrument's sphere and shaft but outside the phantom's
  box and above the table. Under the right candidate the instrument's points land on
  it; under the wrong one (for a box, the twin 180 deg about the vertical axis) they do
  not. Any shape's counterpart, against the rest surface rather than the box, is
  :func:`core.registration.symmetry.surface_instrument_support`.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from core.registration.cleaning import as_points, as_size, instrument_mask
from core.registration.rigid import apply_transform

__all__ = ["Hint", "probe_pose_phantom", "instrument_hints", "instrument_support"]

#: One hint: ``(points_camera (N, 3) float64 m, probe_centre_phantom (3,) m,
#: shaft_axis_phantom (3,) unit, shaft -> tip)`` -- a raw camera frame with the probe's
#: pose at its time, phantom frame.
Hint = tuple[np.ndarray, np.ndarray, np.ndarray]


def probe_pose_phantom(kinematics, t: np.ndarray, T_phantom_robot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Probe sphere centres and tool z-axes at times ``t``, phantom frame.

    Positions are linearly interpolated, orientations spherically (Slerp); times outside
    the kinematics' range are clamped to its ends.

    Args:
        kinematics: object with ``t`` (K,) s, ``position`` (K, 3) robot frame m and
            ``quaternion`` (K, 4) xyzw (``core.io`` ``Kinematics``).
        t: (M,) query times, s, same clock.
        T_phantom_robot: (4, 4) robot calibration
            (:func:`core.registration.rigid.calibrate_robot`).

    Returns:
        centres (M, 3) float64 m and unit tool z-axes (M, 3) float64 (shaft -> tip),
        phantom frame.
    """
    from scipy.spatial.transform import Rotation, Slerp

    kt = np.asarray(kinematics.t, dtype=np.float64).reshape(-1)
    pos = np.asarray(kinematics.position, dtype=np.float64).reshape(-1, 3)
    quat = np.asarray(kinematics.quaternion, dtype=np.float64).reshape(-1, 4)
    tq = np.clip(np.atleast_1d(np.asarray(t, dtype=np.float64)), kt[0], kt[-1])
    centre_robot = np.stack([np.interp(tq, kt, pos[:, k]) for k in range(3)], axis=1)
    if kt.size >= 2:
        rot = Slerp(kt, Rotation.from_quat(quat))(tq)
    else:
        rot = Rotation.from_quat(np.repeat(quat[:1], tq.size, axis=0))
    z_robot = rot.as_matrix()[:, :, 2]
    T = np.asarray(T_phantom_robot, dtype=np.float64)
    return apply_transform(T, centre_robot), z_robot @ T[:3, :3].T


def instrument_hints(sequence, T_phantom_robot: np.ndarray, frames: Iterable[int] = (0, 1, 2)) -> list[Hint]:
    """Build ``hints`` for :func:`core.registration.icp.calibrate_camera` from raw frames of one sequence.

    Args:
        sequence: object with ``kinematics`` (see :func:`probe_pose_phantom`), ``frames.t``
            (M,) s and ``cloud(i)`` -> (N, 3) camera-frame points (``core.io`` ``Sequence``).
        T_phantom_robot: (4, 4) robot calibration.
        frames: frame indices to use. The instrument must be in view; frames where the
            probe is low (touching the phantom) discriminate best: high above the
            phantom's centre, the shaft of the symmetric twin can cross the real one.

    Returns:
        list of ``(points_camera (N, 3), probe_centre_phantom (3,), shaft_axis_phantom (3,))``.
    """
    idx = [int(i) for i in frames]
    t = np.asarray(sequence.frames.t, dtype=np.float64)[idx]
    centres, axes = probe_pose_phantom(sequence.kinematics, t, T_phantom_robot)
    return [(np.asarray(sequence.cloud(i), dtype=np.float64), centres[k], axes[k]) for k, i in enumerate(idx)]


def instrument_support(
    T_phantom_camera: np.ndarray,
    hints: Sequence[Hint],
    phantom_size,
    *,
    probe_radius: float = 0.005,
    shaft_radius: float = 0.0045,
    tolerance: float = 0.003,
) -> int:
    """How many raw hint points a candidate calibration puts on the instrument.

    Counts the points that, mapped by ``T_phantom_camera``, lie inside the instrument
    (sphere + shaft grown by ``tolerance``) but outside the rest box grown by
    ``tolerance`` and above the table (z > 5 mm) -- points the phantom or the table
    cannot explain. Under a wrong candidate the instrument's points land elsewhere.

    Args:
        T_phantom_camera: (4, 4) float candidate camera calibration (camera -> phantom).
        hints: :data:`Hint` tuples (see :func:`instrument_hints`); non-finite hint points
            are dropped.
        phantom_size: (3,) box size, m.
        probe_radius, shaft_radius: instrument radii, m.
        tolerance: grows the instrument's radii and the box, m.

    Returns:
        the number of supporting points, summed over the hints.

    Raises:
        ValueError: a bad ``phantom_size`` or hint points that are not (N, 3).
    """
    size = as_size(phantom_size)
    T = np.asarray(T_phantom_camera, dtype=np.float64)
    total = 0
    for points_camera, centre, axis in hints:
        pts = as_points("hint points_camera", points_camera)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        q = apply_transform(T, pts)
        g = tolerance
        in_box = ((q[:, 0] > -g) & (q[:, 0] < size[0] + g) & (q[:, 1] > -g) & (q[:, 1] < size[1] + g)
                  & (q[:, 2] < size[2] + g))
        free = ~in_box & (q[:, 2] > 0.005)
        on_tool = instrument_mask(q[free], centre, axis, probe_radius=probe_radius,
                                  shaft_radius=shaft_radius, margin=tolerance)
        total += int(np.count_nonzero(on_tool))
    return total

