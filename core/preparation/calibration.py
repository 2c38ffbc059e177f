"""Calibration of a session: robot -> phantom (Kabsch on corner or landmark touches) and
camera -> phantom (ICP of the reference cloud), with their residuals (Wu et al. 2020,
Sec. 3.1)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import SessionFormatError
from core.io import Session, read_picked
from core.registration import (
    RigidFit,
    calibrate_camera,
    calibrate_robot,
    calibrate_robot_landmarks,
    instrument_hints,
    landmark_normals,
)

__all__ = ["Calibration", "calibrate", "calibrate_robot_on_landmarks"]


@dataclass(frozen=True)
class Calibration:
    """Registration results with their residuals.

    Attributes:
        T_phantom_robot: (4, 4) robot base -> phantom (Kabsch on corner touches, or on
            landmark touches when the session has ``calibration/landmarks.csv``).
        T_phantom_camera: (4, 4) camera -> phantom (point-to-plane ICP).
        robot_rms: corner- (or landmark-) touch residual RMS, m.
        camera_rms: ICP inlier RMS, m.
        camera_fitness: ICP inlier fraction.
        probe_sigma: standard error of the calibrated probe's vertical position over the
            top face, m, from the corner- (or landmark-) touch residuals: per-axis touch noise
            ``sigma^2 = sum(r^2) / (3 N - 6)`` (6 rigid degrees of freedom), propagated
            through the Kabsch fit as ``sigma^2 / N`` at the touches' centroid plus the
            tilt term, 1/3 of that averaged over the face. NaN when unknown.
    """

    T_phantom_robot: np.ndarray
    T_phantom_camera: np.ndarray
    robot_rms: float
    camera_rms: float
    camera_fitness: float
    probe_sigma: float = float("nan")

    @classmethod
    def from_json(cls, d: dict) -> "Calibration":
        """The inverse of :meth:`to_json`."""
        return cls(np.asarray(d["T_phantom_robot"], dtype=np.float64), np.asarray(d["T_phantom_camera"], dtype=np.float64),
                   float(d["robot_rms"]), float(d["camera_rms"]), float(d["camera_fitness"]),
                   float(d.get("probe_sigma", float("nan"))))

    def to_json(self) -> dict:
        return {
            "T_phantom_robot": self.T_phantom_robot.tolist(),
            "T_phantom_camera": self.T_phantom_camera.tolist(),
            "robot_rms": float(self.robot_rms),
            "camera_rms": float(self.camera_rms),
            "camera_fitness": float(self.camera_fitness),
            "probe_sigma": float(self.probe_sigma),
        }


def calibrate(session: Session, *, picked=None) -> Calibration:
    """Register robot and camera to the phantom frame.

    The robot is registered on ``calibration/landmarks.csv`` when the session has it
    (:func:`calibrate_robot_on_landmarks`), otherwise on ``calibration/corners.csv``
    (:func:`core.registration.calibrate_robot`).

    Args:
        session: a read session.
        picked: optional (points_camera (K, 3), points_phantom (K, 3)), K >= 3, to
            initialise ICP from picked point pairs instead of automatically. When None,
            pairs accepted in the workbench (``calibration/picked.json``) are used if
            the session has them.

    Raises:
        RegistrationError: a registration that does not fit.
        SessionFormatError: a malformed ``calibration/picked.json``; (landmark
            calibration) a ``phantom.stl`` that cannot be read or is not watertight.
    """
    meta = session.meta
    if picked is None:
        picked = read_picked(session.path)
    if session.landmark_touches is not None:
        robot = calibrate_robot_on_landmarks(session)
    else:
        robot = calibrate_robot(session.corners, meta.phantom.size, meta.probe.radius)
    reference = session.reference_cloud()
    hints = []
    for seq in list(session.sequences.values())[:2]:
        n = len(seq)
        frames = sorted({0, n // 4, n // 2}) if session.phantom_stl is None else \
            _frames_off_axis(seq, robot.T, meta.phantom.size)
        hints += instrument_hints(seq, robot.T, frames)
    if reference is None:
        first = next(iter(session.sequences.values()))
        reference = first.cloud(0)
    camera = calibrate_camera(
        reference,
        meta.phantom.size,
        probe_radius=meta.probe.radius,
        picked=picked,
        hints=hints,
        stl_path=session.phantom_stl,
    )
    return Calibration(
        T_phantom_robot=robot.T,
        T_phantom_camera=camera.T,
        robot_rms=float(robot.rms),
        camera_rms=float(camera.rms),
        camera_fitness=float(camera.fitness),
        probe_sigma=_probe_sigma(robot.residuals),
    )


def _frames_off_axis(seq, T_phantom_robot: np.ndarray, size, count: int = 3) -> list[int]:
    """``count`` frames of ``seq`` whose probe is furthest (horizontally) from the
    phantom's vertical axis while over or beside it and less than 3 cm above its top:
    a phantom of revolution leaves the camera's yaw to the instrument
    (:func:`core.registration.symmetry.resolve_yaw`), and an instrument near the axis
    cannot tell yaws apart. Frames at least 0.5 s apart."""
    from core.registration.instrument import probe_pose_phantom

    t = np.asarray(seq.frames.t, dtype=np.float64)
    centres, _ = probe_pose_phantom(seq.kinematics, t, T_phantom_robot)
    size = np.asarray(size, dtype=np.float64)
    axis_xy = size[:2] / 2
    reach = np.linalg.norm(centres[:, :2] - axis_xy, axis=1)
    ok = (np.all(np.abs(centres[:, :2] - axis_xy) <= size[:2] / 2 + 0.01, axis=1) & (centres[:, 2] < size[2] + 0.03))
    chosen: list[int] = []
    for i in np.argsort(-np.where(ok, reach, -1.0)):
        if not ok[i] or len(chosen) == count:
            break
        if all(abs(t[i] - t[j]) >= 0.5 for j in chosen):
            chosen.append(int(i))
    n = len(seq)
    return sorted(chosen) if chosen else sorted({0, n // 4, n // 2})


def calibrate_robot_on_landmarks(session: Session) -> RigidFit:
    """``T_phantom_robot`` from ``calibration/landmarks.csv`` (Kabsch 1976).

    Each touch's phantom-frame sphere centre is its landmark (``session.json``) plus the
    probe radius along the outward normal of the rest surface there: ``phantom.stl``
    when present, else the box ``[0, size]`` (:func:`core.registration.landmark_normals`).

    Raises:
        RegistrationError: as :func:`core.registration.calibrate_robot_landmarks`.
        SessionFormatError: ``phantom.stl`` cannot be read, or has no outward normal at a
            landmark (not watertight).
    """
    import trimesh  # noqa: PLC0415 (heavy, only needed here)

    meta = session.meta
    surface = session.phantom_mesh()
    if surface is None:
        size = np.asarray(meta.phantom.size, dtype=np.float64)
        surface = trimesh.creation.box(extents=size)
        surface.apply_translation(size / 2.0)  # centred -> spans [0, size], the phantom frame
    names = list(meta.landmarks)
    try:
        normals = landmark_normals(surface, np.stack([meta.landmarks[n] for n in names]))
    except ValueError as exc:
        where = session.phantom_stl if session.phantom_stl is not None else session.path / "session.json"
        raise SessionFormatError(where, f"no outward normal at the landmarks: {exc}") from exc
    return calibrate_robot_landmarks(session.landmark_touches, meta.landmarks,
                                     dict(zip(names, normals)), meta.probe.radius)


def _probe_sigma(residuals: np.ndarray) -> float:
    """Standard error (m) of the calibrated probe height (see ``Calibration.probe_sigma``)."""
    n = int(np.asarray(residuals).size)
    if n < 3:
        return float("nan")
    sigma2 = float(np.sum(np.asarray(residuals) ** 2)) / max(3 * n - 6, 1)
    return float(np.sqrt(sigma2 / n * 4.0 / 3.0))
