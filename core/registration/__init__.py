"""Registration and cloud cleaning: robot and camera calibration, per-frame cleaning.

Public surface:

* :func:`kabsch` / :class:`RigidFit` -- paired-point rigid/similarity fit (Kabsch 1976,
  Umeyama 1991).
* :func:`calibrate_robot` -- ``T_phantom_robot`` from corner touches (Wu et al. 2020, Sec. 3.2).
* :func:`calibrate_robot_landmarks` -- ``T_phantom_robot`` from touches of named landmarks of
  any shape (Kabsch 1976), with :func:`landmark_normals` (outward normals of the rest surface).
* :func:`calibrate_camera` / :class:`CameraFit` -- ``T_phantom_camera`` by point-to-plane
  ICP of the reference cloud (Wu et al. 2020, Sec. 3.3), initialised from picked points
  or automatically (table RANSAC + footprint rectangle, symmetry resolved by ``hints``).
* :func:`phantom_rest_surface` -- rest-surface samples used as the ICP target.
* :func:`clean_cloud` / :class:`CleanResult` -- per-frame removal of table, instrument and
  outliers (Wu et al. 2020, Sec. 3.1).
* Helpers: :func:`instrument_hints`, :func:`probe_pose_phantom`, :func:`instrument_support`,
  :func:`find_table_plane`, :func:`corner_points_phantom`, :func:`landmark_points_phantom`,
  :func:`apply_transform`.

Modules: ``rigid`` (Kabsch, corner touches), ``landmarks`` (landmark touches),
``cleaning`` (table, instrument and outlier removal; point and size checks),
``icp`` (camera calibration by ICP), ``initial_pose`` (its automatic initial pose from the
table and the footprint, and the table anchoring), ``instrument`` (the instrument's pose
in the phantom frame and its support in raw frames), ``symmetry`` (the yaw a phantom of
any shape leaves open).

open3d is imported inside the functions that use it, so importing this package is cheap.
"""

from core.registration.cleaning import CleanResult, TablePlane, clean_cloud, find_table_plane
from core.registration.icp import CameraFit, calibrate_camera, phantom_rest_surface
from core.registration.instrument import instrument_hints, instrument_support, probe_pose_phantom
from core.registration.landmarks import calibrate_robot_landmarks, landmark_normals, landmark_points_phantom
from core.registration.rigid import RigidFit, apply_transform, calibrate_robot, corner_points_phantom, kabsch

__all__ = [
    "RigidFit",
    "kabsch",
    "calibrate_robot",
    "corner_points_phantom",
    "calibrate_robot_landmarks",
    "landmark_normals",
    "landmark_points_phantom",
    "apply_transform",
    "CameraFit",
    "calibrate_camera",
    "phantom_rest_surface",
    "instrument_hints",
    "instrument_support",
    "probe_pose_phantom",
    "CleanResult",
    "TablePlane",
    "clean_cloud",
    "find_table_plane",
]
