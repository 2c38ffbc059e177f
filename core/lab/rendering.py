"""The virtual lab's depth recording: the camera placed for a seed, its clock, its clouds.

This module holds what turns the truth's deformed phantom into what the SR300-like
camera records: the camera rig of a seed (:func:`place_camera`: a random pose and jittered
intrinsics, the ray-cast window around the phantom, the table and the ring of it that is
kept; :class:`CameraRig`), the camera's jittered frame clock (:func:`frame_times`), the
reference cloud of the phantom at rest (:meth:`CameraRig.reference_points`) and one noisy
frame with the instrument (:meth:`CameraRig.frame_points`). The camera model itself
(ray casting, depth noise) is :mod:`core.lab.camera`. Scene geometry is in the phantom
frame; clouds are in the camera frame (OpenCV axes), m.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core.lab.camera import (
    DepthCamera,
    Instrument,
    Intrinsics,
    apply_depth_noise,
    cast,
    depth_to_points,
    random_camera_pose,
    roi_for_box,
    table_mesh,
    table_ring_mask,
)

if TYPE_CHECKING:
    from core.lab.config import LabConfig

__all__ = ["CameraRig", "place_camera", "frame_times"]


@dataclass(frozen=True)
class CameraRig:
    """The lab's depth camera as placed for one seed, with what every ray cast reuses.

    Attributes:
        T_phantom_camera: (4, 4) float64, maps camera points into the phantom frame.
        intrinsics: the seed's jittered pinhole intrinsics.
        roi: (u0, u1, v0, v1) pixel window that is ray cast (half-open).
        camera: the posed :class:`core.lab.camera.DepthCamera` (its ``noise`` is the
            lab's ``depth_noise``).
        rays: (R, 6) float32 rays of the window (origin, direction), phantom frame.
        table: (vertices (4, 3) m, triangles (2, 3)) of the table plane, phantom frame.
        table_keep: (R,) bool, rays whose table hits are kept (a ring around the phantom).
    """

    T_phantom_camera: np.ndarray
    intrinsics: Intrinsics
    roi: tuple[int, int, int, int]
    camera: DepthCamera
    rays: np.ndarray
    table: tuple[np.ndarray, np.ndarray]
    table_keep: np.ndarray

    def reference_points(self, rest: np.ndarray, triangles: np.ndarray, frames: int,
                         reference_rng: np.random.Generator) -> np.ndarray:
        """The reference cloud (``calibration/reference.ply``): the phantom at rest, no
        instrument, ``max(frames, 1)`` noisy frames averaged per pixel (a pixel valid in
        fewer than half of them is dropped).

        Args:
            rest: (N, 3) float64 node positions at rest, m, phantom frame.
            triangles: (T, 3) int surface triangles of the truth mesh (node indices).
            frames: noisy frames averaged.
            reference_rng: the reference's noise stream (one noise draw per frame).

        Returns:
            (P, 3) float32 points, m, camera frame.
        """
        hits = cast(self.camera, (rest, triangles), table=self.table, rays=self.rays, table_keep=self.table_keep)
        stack = np.stack([apply_depth_noise(hits, self.camera.noise, reference_rng)
                          for _ in range(max(frames, 1))])
        n_valid = np.isfinite(stack).sum(axis=0)
        mean = np.nansum(stack, axis=0) / np.maximum(n_valid, 1)
        ref_depth = np.where(n_valid * 2 >= stack.shape[0], mean, np.nan)
        return depth_to_points(self.camera, ref_depth)

    def frame_points(self, nodes: np.ndarray, triangles: np.ndarray, inst: Instrument,
                     srng: np.random.Generator) -> np.ndarray:
        """One recorded depth frame: the deformed phantom, the table ring and the
        instrument, ray cast and put through the sensor's noise.

        Args:
            nodes: (N, 3) node positions of the truth at the frame, m, phantom frame.
            triangles: (T, 3) int surface triangles of the truth mesh (node indices).
            inst: the instrument at the frame (phantom frame).
            srng: the sequence's noise stream (one noise draw).

        Returns:
            (P, 3) float32 points, m, camera frame.
        """
        hits = cast(self.camera, (nodes, triangles), table=self.table, instrument=inst, rays=self.rays,
                    table_keep=self.table_keep)
        return depth_to_points(self.camera, apply_depth_noise(hits, self.camera.noise, srng))


def place_camera(rng: np.random.Generator, cfg: LabConfig, size: np.ndarray, top_centre: np.ndarray) -> CameraRig:
    """The camera of a seed, looking at the phantom's top.

    Args:
        rng: the session's main stream: the camera pose
            (:func:`core.lab.camera.random_camera_pose`), then the intrinsics' jitter
            (:meth:`core.lab.camera.Intrinsics.jittered`) are drawn from it, in that order.
        cfg: the lab (``camera_distance_range``, ``camera_tilt_range_deg``,
            ``intrinsics``, ``roi_margin``, ``depth_noise``, ``table_margin``).
        size: (3,) float64 phantom bounding box, m.
        top_centre: (3,) float64 centre of the phantom's top, m, phantom frame.

    Returns:
        the :class:`CameraRig`.
    """
    T_phantom_camera = random_camera_pose(rng, top_centre, distance_range=cfg.camera_distance_range,
                                          tilt_range_deg=cfg.camera_tilt_range_deg)
    intrinsics = cfg.intrinsics.jittered(rng)
    m = cfg.roi_margin
    roi = roi_for_box(intrinsics, T_phantom_camera, (-m, -m, -0.001), (size[0] + m, size[1] + m, size[2] + 0.02))
    camera = DepthCamera(intrinsics, T_phantom_camera, roi, cfg.depth_noise)
    rays = camera.rays_phantom()
    tm = cfg.table_margin
    table = table_mesh(top_centre)
    table_keep = table_ring_mask(rays, (-tm, -tm), (size[0] + tm, size[1] + tm), float(table[0][0, 2]))
    return CameraRig(T_phantom_camera, intrinsics, roi, camera, rays, table, table_keep)


def frame_times(rng, duration: float, rate: float, jitter: float) -> np.ndarray:
    """(F,) float64 frame times of a camera clock, s: a uniform phase in the first period,
    one frame per period, each jittered by a normal of standard deviation ``jitter`` s
    (clipped to 0.3 periods), those in ``[0, duration]`` kept. ``rate`` in Hz. Draws one
    uniform, then the jitter normals, from ``rng``."""
    period = 1.0 / rate
    n = int(np.floor((duration - period) * rate)) + 1
    t = rng.uniform(0.0, period) + period * np.arange(n)
    t = t + np.clip(rng.normal(0.0, jitter, n), -0.3 * period, 0.3 * period)
    t = t[(t >= 0.0) & (t <= duration)]
    return t
