"""Camera calibration from picked point pairs: preview (Kabsch + ICP) and accept.

Wu et al. 2020, Sec. 3.3 initialise ICP by hand because the phantom's top is flat and
featureless. The user picks K >= 3 points on the reference cloud (camera frame) and
the matching points on the phantom's rest surface (phantom frame); the initial
``T_phantom_camera`` is their Kabsch fit (Kabsch 1976) and point-to-plane ICP refines it
(``core.registration.calibrate_camera(picked=...)``).

Accepted picks are stored in the session folder as ``calibration/picked.json``::

    {"format": "tissuetwin-picked/1",
     "points_camera": [[x, y, z], ...],     # K >= 3, m, camera frame
     "points_phantom": [[x, y, z], ...],    # the same K points, m, phantom frame
     "T_phantom_camera": [[...4x4...]],     # the ICP result when accepted (informative)
     "T_init": [[...]], "rms_init": m, "rms": m, "fitness": f, "accepted_at": ISO time}

Jobs of the workbench pass the pairs (read with ``core.io.read_picked``) to
``prepare_session(picked=...)``, which re-runs the same deterministic ICP; the CLI's
calibration reads the same file when no pairs are given.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np

from app.server.errors import Invalid
from core.io.session import PICKED_FILE

__all__ = ["PICKED_FILE", "load_calibration", "reference_and_surface", "preview", "accept", "clear"]



def _pairs(points_camera, points_phantom) -> tuple[np.ndarray, np.ndarray]:
    pc = np.asarray(points_camera, dtype=np.float64)
    pp = np.asarray(points_phantom, dtype=np.float64)
    if pc.ndim != 2 or pc.shape[1:] != (3,) or pp.shape != pc.shape:
        raise Invalid(f"points_camera and points_phantom must both be (K, 3), got {pc.shape} and {pp.shape}")
    if pc.shape[0] < 3:
        raise Invalid(f"pick at least 3 point pairs, got {pc.shape[0]}")
    if not (np.isfinite(pc).all() and np.isfinite(pp).all()):
        raise Invalid("picked points must be finite")
    return pc, pp


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def load_calibration(session_path: str | Path) -> dict | None:
    """The stored ``picked.json`` as a dict, or None (automatic initialisation).

    Raises:
        SessionFormatError: not UTF-8 JSON, not an object, or holding NaN/Infinity.
    """
    from core.errors import SessionFormatError

    f = Path(session_path) / PICKED_FILE
    if not f.exists():
        return None
    try:
        obj = json.loads(f.read_text(encoding="utf-8"), parse_constant=_no_constant)
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise SessionFormatError(f, f"not valid JSON ({exc})") from exc
    if not isinstance(obj, dict):
        raise SessionFormatError(f, f"top level must be a JSON object, got {type(obj).__name__}")
    return obj


def reference_and_surface(session_path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the user picks on.

    Returns:
        reference_camera (N, 3) float64 m (``calibration/reference.ply``, else the first
        frame of the first sequence), rest surface samples (P, 3) float64 m phantom frame,
        and the phantom size (3,) m.
    """
    from core.io import read_session
    from core.registration import phantom_rest_surface

    s = read_session(session_path)
    ref = s.reference_cloud()
    if ref is None:
        ref = next(iter(s.sequences.values())).cloud(0)
    surface, _ = phantom_rest_surface(s.meta.phantom.size, s.phantom_stl, spacing=0.002)
    return ref, surface, np.asarray(s.meta.phantom.size, float)


def preview(session_path: str | Path, points_camera, points_phantom) -> dict:
    """Kabsch initial transform, then ICP; nothing is saved.

    Returns:
        dict with ``T_init`` and ``T_phantom_camera`` (4x4 lists), ``rms_init`` (Kabsch
        residual of the picks, m), ``rms`` (ICP point-to-plane inlier rms, m),
        ``fitness``, ``coverage``, and the pick residuals after ICP (m).

    Raises:
        Invalid: malformed picks, or degenerate ones (coincident or collinear).
        RegistrationError: the picks do not match rigidly (> 10 mm) or ICP does not fit.
    """
    from core.io import read_session
    from core.registration import apply_transform, calibrate_camera, kabsch

    pc, pp = _pairs(points_camera, points_phantom)
    s = read_session(session_path)
    ref = s.reference_cloud()
    if ref is None:
        ref = next(iter(s.sequences.values())).cloud(0)
    try:
        init = kabsch(pc, pp)
        fit = calibrate_camera(ref, s.meta.phantom.size, probe_radius=s.meta.probe.radius, picked=(pc, pp),
                               stl_path=s.phantom_stl)
    except ValueError as exc:  # kabsch: coincident or collinear picks leave the rotation undetermined
        raise Invalid(f"picked points: {exc}") from exc
    after = np.linalg.norm(apply_transform(fit.T, pc) - pp, axis=1)
    return {
        "T_init": np.asarray(fit.T_init).tolist(),
        "T_phantom_camera": np.asarray(fit.T).tolist(),
        "rms_init": float(init.rms),
        "rms": float(fit.rms),
        "fitness": float(fit.fitness),
        "coverage": float(fit.coverage),
        "pick_residuals_after": after.tolist(),
    }


def accept(session_path: str | Path, points_camera, points_phantom) -> dict:
    """Run :func:`preview` and store the picks as ``calibration/picked.json``.

    Returns the stored dict. Raises as :func:`preview` (nothing is written then).
    """
    pc, pp = _pairs(points_camera, points_phantom)
    res = preview(session_path, pc, pp)
    obj = {
        "format": "tissuetwin-picked/1",
        "points_camera": pc.tolist(),
        "points_phantom": pp.tolist(),
        **{k: res[k] for k in ("T_phantom_camera", "T_init", "rms_init", "rms", "fitness", "coverage")},
        "accepted_at": dt.datetime.now(dt.timezone.utc).isoformat(),
    }
    f = Path(session_path) / PICKED_FILE
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(obj, indent=2))
    tmp.replace(f)
    return obj


def clear(session_path: str | Path) -> bool:
    """Remove the stored picks (back to automatic initialisation). True if one existed."""
    f = Path(session_path) / PICKED_FILE
    existed = f.exists()
    f.unlink(missing_ok=True)
    return existed
