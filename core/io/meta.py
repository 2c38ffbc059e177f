"""``session.json``: the typed metadata of a session, its validation and serialisation.

:class:`SessionMeta` holds the phantom, probe, camera and sequence entries, the optional
named ``landmarks`` (plus every unknown key, kept verbatim); :func:`parse_meta`
validates a parsed ``session.json`` object and :func:`read_meta` reads the file. Errors
name the file and the key.
"""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import MissingFileError, SessionFormatError, UnitsError
from core.io.checks import FORMAT, MAX_SIZE_M, ROLES, ArrayEq, frozen_array

__all__ = [
    "PhantomSpec",
    "ProbeSpec",
    "CameraSpec",
    "SequenceSpec",
    "SessionMeta",
    "Landmarks",
    "parse_meta",
    "read_meta",
]

# --------------------------------------------------------------------------------------
# Typed metadata
# --------------------------------------------------------------------------------------


class Landmarks(Mapping):
    """Immutable mapping landmark name -> (3,) read-only float64 point, m, phantom frame.

    The value of :attr:`SessionMeta.landmarks`, in ``session.json`` order. Picklable;
    ``==`` compares names, order-insensitively, and points exactly.
    """

    __slots__ = ("_points",)
    __hash__ = None  # holds arrays

    def __init__(self, points: Mapping[str, Any] | None = None):
        """
        Args:
            points: name -> [x, y, z] (m, phantom frame); None or empty for none.

        Raises:
            ValueError: a point is not (3,).
        """
        out: dict[str, np.ndarray] = {}
        for name, xyz in dict(points or {}).items():
            a = frozen_array(xyz, np.float64)
            if a.shape != (3,):
                raise ValueError(f"landmark {name!r} must be (3,) [x, y, z], got {a.shape}")
            out[str(name)] = a
        object.__setattr__(self, "_points", out)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Landmarks is immutable")

    def __getitem__(self, name: str) -> np.ndarray:
        return self._points[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._points)

    def __len__(self) -> int:
        return len(self._points)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Mapping):
            return NotImplemented
        return self.keys() == other.keys() and all(
            np.array_equal(self[k], np.asarray(other[k], dtype=np.float64)) for k in self
        )

    def __repr__(self) -> str:
        items = ", ".join(f"{k!r}: {v.tolist()}" for k, v in self._points.items())
        return f"Landmarks({{{items}}})"

    def __reduce__(self):
        return (type(self), (self._points,))

    def to_json(self) -> dict[str, list[float]]:
        """``{"<name>": [x, y, z], ...}`` as written in ``session.json``."""
        return {k: [float(v) for v in p] for k, p in self._points.items()}


@dataclass(frozen=True, eq=False)
class PhantomSpec(ArrayEq):
    """The phantom at rest, from ``session.json["phantom"]``.

    The phantom frame has the box spanning ``[0, size[0]] x [0, size[1]] x [0, size[2]]``,
    z up, bottom face at z = 0.
    """

    size: np.ndarray
    """(3,) float64, m: x length, y width, z height (read-only array)."""
    mass: float
    """kg."""
    fixed: str = "bottom"
    """Boundary condition; ``"bottom"``: every node on the z = 0 face is held."""
    shape: str = "box"
    """Rest shape kind; ``phantom.stl`` overrides ``size`` when present."""

    def __post_init__(self) -> None:
        size = frozen_array(self.size, np.float64)
        if size.shape != (3,):
            raise ValueError(f"phantom size must be (3,), got {size.shape}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "mass", float(self.mass))


@dataclass(frozen=True)
class ProbeSpec:
    """The instrument tip, from ``session.json["probe"]``."""

    radius: float
    """Sphere radius, m. Kinematics give the sphere's centre."""
    shape: str = "sphere"
    """Tip shape; the format defines ``"sphere"``."""


@dataclass(frozen=True)
class CameraSpec:
    """The depth camera, from ``session.json["camera"]``."""

    rate_hz: float
    """Frame rate, Hz."""
    depth_accuracy: float
    """Depth noise scale, m (standard deviation as stated by the recorder)."""
    intrinsics: dict | None = None
    """Optional pinhole intrinsics as written (e.g. width, height, fx, fy, cx, cy), or None."""


@dataclass(frozen=True)
class SequenceSpec:
    """One entry of ``session.json["sequences"]``."""

    name: str
    """Folder name under ``sequences/``."""
    role: str
    """One of ``"train"``, ``"validation"``, ``"test"``."""

    def __post_init__(self) -> None:
        n = self.name
        if not isinstance(n, str) or not n or n in (".", "..") or "/" in n or "\\" in n:
            raise ValueError(f"sequence name must be a plain folder name, got {n!r}")
        if self.role not in ROLES:
            raise ValueError(f"sequence role must be one of {ROLES}, got {self.role!r}")


@dataclass(frozen=True, eq=False)
class SessionMeta(ArrayEq):
    """The content of ``session.json``: typed fields plus everything else, kept verbatim."""

    phantom: PhantomSpec
    probe: ProbeSpec
    camera: CameraSpec
    sequences: tuple[SequenceSpec, ...]
    """In file order; names are unique."""
    raw: dict = field(default_factory=dict)
    """The whole ``session.json`` as read (unknown keys at any level are kept and written
    back by :meth:`to_json`); empty for metadata built in code."""
    landmarks: Mapping[str, np.ndarray] = field(default_factory=Landmarks)
    """Top-level ``landmarks`` of ``session.json`` (optional, any phantom shape): name ->
    (3,) float64 point, m, phantom frame, of the rest surface, touched by
    ``calibration/landmarks.csv``. A :class:`Landmarks` (immutable), empty when absent.
    Names are non-empty, without surrounding spaces, commas, quotes or line breaks (they
    are CSV cells of ``landmarks.csv``)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "sequences", tuple(self.sequences))
        object.__setattr__(self, "landmarks", Landmarks(self.landmarks))
        names = [s.name for s in self.sequences]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"sequence names must be unique, got duplicates {dup}")

    def sequence(self, name: str) -> SequenceSpec:
        """The :class:`SequenceSpec` called ``name`` (KeyError if absent)."""
        for s in self.sequences:
            if s.name == name:
                return s
        raise KeyError(f"no sequence {name!r}; have {[s.name for s in self.sequences]}")

    def to_json(self) -> dict:
        """The ``session.json`` object: :attr:`raw` with the typed fields written over it.

        Unknown keys of :attr:`raw` (top level, inside ``phantom``/``probe``/``camera``
        and inside each sequence entry, matched by name) are preserved; ``"format"`` is
        set to ``"tissue-session/1"``; ``"landmarks"`` is written from :attr:`landmarks`,
        only when there are any. Returns a new dict (JSON-serialisable).
        """
        raw = copy.deepcopy(self.raw)
        out: dict[str, Any] = {"format": FORMAT}
        out.update((k, v) for k, v in raw.items() if k != "format")

        def _sub(key: str) -> dict:
            v = raw.get(key)
            return dict(v) if isinstance(v, dict) else {}

        phantom = _sub("phantom")
        phantom.update(
            shape=self.phantom.shape,
            size=[float(v) for v in self.phantom.size],
            mass=float(self.phantom.mass),
            fixed=self.phantom.fixed,
        )
        probe = _sub("probe")
        probe.update(shape=self.probe.shape, radius=float(self.probe.radius))
        camera = _sub("camera")
        camera.update(rate_hz=float(self.camera.rate_hz),
                      depth_accuracy=float(self.camera.depth_accuracy))
        if self.camera.intrinsics is None:
            camera.pop("intrinsics", None)
        else:
            camera["intrinsics"] = copy.deepcopy(self.camera.intrinsics)
        raw_seqs = {
            s["name"]: s
            for s in (raw.get("sequences") if isinstance(raw.get("sequences"), list) else [])
            if isinstance(s, dict) and isinstance(s.get("name"), str)
        }
        sequences = []
        for s in self.sequences:
            entry = dict(raw_seqs.get(s.name, {}))
            entry.update(name=s.name, role=s.role)
            sequences.append(entry)
        out.update(phantom=phantom, probe=probe, camera=camera, sequences=sequences)
        if self.landmarks:
            out["landmarks"] = self.landmarks.to_json()
        else:
            out.pop("landmarks", None)
        return out

    @classmethod
    def from_json(cls, obj: Any, path: str | os.PathLike = "session.json") -> SessionMeta:
        """Validate a parsed ``session.json`` object and build the metadata.

        Args:
            obj: the parsed JSON value.
            path: the file it came from (named in error messages).

        Raises:
            SessionFormatError: wrong ``format``, missing ``phantom``/``probe``/``camera``/
                ``sequences``, wrong types, non-positive size/mass/radius/rate, bad role,
                bad or duplicate sequence names, ``landmarks`` not an object of
                ``"<name>": [x, y, z]`` with finite numbers and valid names.
            UnitsError: a phantom dimension or the probe radius > 1 m, a landmark
                coordinate beyond +-1 m (millimetres).
        """
        return parse_meta(Path(path), obj)


# --------------------------------------------------------------------------------------
# session.json
# --------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _get_obj(path: Path, parent: dict, key: str, where: str = "") -> dict:
    if key not in parent:
        raise SessionFormatError(path, f"missing required key '{where}{key}'")
    v = parent[key]
    if not isinstance(v, dict):
        raise SessionFormatError(path, f"'{where}{key}' must be an object, got {v!r}")
    return v


def _get_str(path: Path, obj: dict, key: str, where: str, default: str | None) -> str:
    if key not in obj:
        if default is None:
            raise SessionFormatError(path, f"missing required key '{where}{key}'")
        return default
    v = obj[key]
    if not isinstance(v, str) or not v:
        raise SessionFormatError(path, f"'{where}{key}' must be a non-empty string, got {v!r}")
    return v


def _get_num(path: Path, obj: dict, key: str, where: str, *, positive: bool = True,
             default: float | None = None) -> float:
    name = f"{where}{key}"
    if key not in obj:
        if default is not None:
            return default
        raise SessionFormatError(path, f"missing required key '{name}'")
    v = obj[key]
    if not _is_number(v) or not math.isfinite(v):
        raise SessionFormatError(path, f"'{name}' must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise SessionFormatError(path, f"'{name}' must be positive, got {v!r}")
    if not positive and v < 0:
        raise SessionFormatError(path, f"'{name}' must be non-negative, got {v!r}")
    return float(v)


def parse_meta(path: Path, obj: Any) -> SessionMeta:
    if not isinstance(obj, dict):
        raise SessionFormatError(path, f"top level must be a JSON object, got {type(obj).__name__}")
    fmt = obj.get("format")
    if fmt != FORMAT:
        raise SessionFormatError(path, f"'format' must be {FORMAT!r}, got {fmt!r}")

    ph = _get_obj(path, obj, "phantom")
    size = ph.get("size")
    if (not isinstance(size, list) or len(size) != 3
            or not all(_is_number(v) and math.isfinite(v) for v in size)):
        raise SessionFormatError(path, f"'phantom.size' must be 3 finite numbers, got {size!r}")
    if any(v <= 0 for v in size):
        raise SessionFormatError(path, f"'phantom.size' must be positive, got {size!r}")
    if any(v > MAX_SIZE_M for v in size):
        raise UnitsError(
            path,
            f"'phantom.size' = {size!r} looks like millimetres: the format uses metres "
            f"(every dimension must be <= {MAX_SIZE_M} m)",
        )
    phantom = PhantomSpec(
        size=np.array(size, dtype=np.float64),
        mass=_get_num(path, ph, "mass", "phantom."),
        fixed=_get_str(path, ph, "fixed", "phantom.", "bottom"),
        shape=_get_str(path, ph, "shape", "phantom.", "box"),
    )

    pr = _get_obj(path, obj, "probe")
    radius = _get_num(path, pr, "radius", "probe.")
    if radius > MAX_SIZE_M:
        raise UnitsError(
            path,
            f"'probe.radius' = {radius!r} looks like millimetres: the format uses metres "
            f"(must be <= {MAX_SIZE_M} m)",
        )
    probe = ProbeSpec(radius=radius, shape=_get_str(path, pr, "shape", "probe.", "sphere"))

    cam = _get_obj(path, obj, "camera")
    intrinsics = cam.get("intrinsics")
    if intrinsics is not None and not isinstance(intrinsics, dict):
        raise SessionFormatError(
            path, f"'camera.intrinsics' must be an object or absent, got {intrinsics!r}"
        )
    camera = CameraSpec(
        rate_hz=_get_num(path, cam, "rate_hz", "camera."),
        depth_accuracy=_get_num(path, cam, "depth_accuracy", "camera.", positive=False),
        intrinsics=copy.deepcopy(intrinsics),
    )

    if "sequences" not in obj:
        raise SessionFormatError(path, "missing required key 'sequences'")
    seqs = obj["sequences"]
    if not isinstance(seqs, list):
        raise SessionFormatError(path, f"'sequences' must be a list, got {seqs!r}")
    specs: list[SequenceSpec] = []
    seen: set[str] = set()
    for i, s in enumerate(seqs):
        where = f"sequences[{i}]."
        if not isinstance(s, dict):
            raise SessionFormatError(path, f"'sequences[{i}]' must be an object, got {s!r}")
        name = _get_str(path, s, "name", where, None)
        if name in (".", "..") or "/" in name or "\\" in name or name.strip() != name:
            raise SessionFormatError(path, f"'{where}name' = {name!r} is not a valid folder name")
        role = s.get("role")
        if role not in ROLES:
            raise SessionFormatError(
                path, f"'{where}role' of sequence {name!r} must be one of {list(ROLES)}, got {role!r}"
            )
        if name in seen:
            raise SessionFormatError(path, f"duplicate sequence name {name!r}")
        seen.add(name)
        specs.append(SequenceSpec(name=name, role=role))

    return SessionMeta(phantom=phantom, probe=probe, camera=camera, sequences=tuple(specs),
                       raw=copy.deepcopy(obj), landmarks=_parse_landmarks(path, obj))


def _parse_landmarks(path: Path, obj: dict) -> dict[str, np.ndarray]:
    """The optional top-level ``landmarks`` object: name -> (3,) float64, m, phantom frame.

    A phantom is at most 1 m in every dimension (``phantom.size``), so a point of its
    surface has every coordinate within +-1 m; anything beyond is taken for millimetres.
    """
    if "landmarks" not in obj:
        return {}
    lm = obj["landmarks"]
    if not isinstance(lm, dict):
        raise SessionFormatError(
            path, f"'landmarks' must be an object {{\"<name>\": [x, y, z], ...}}, got {lm!r}"
        )
    out: dict[str, np.ndarray] = {}
    for name, xyz in lm.items():
        if (not isinstance(name, str) or not name or name.strip() != name
                or any(c in name for c in ',"\r\n')):
            raise SessionFormatError(
                path,
                f"landmark name {name!r} in 'landmarks' must be a non-empty string without "
                f"surrounding spaces, commas, quotes or line breaks",
            )
        key = f"landmarks.{name}"
        if (not isinstance(xyz, list) or len(xyz) != 3
                or not all(_is_number(v) and math.isfinite(v) for v in xyz)):
            raise SessionFormatError(
                path, f"'{key}' must be 3 finite numbers [x, y, z] (m, phantom frame), got {xyz!r}"
            )
        if any(abs(v) > MAX_SIZE_M for v in xyz):
            raise UnitsError(
                path,
                f"'{key}' = {xyz!r} looks like millimetres: the format uses metres "
                f"(a phantom-frame point of the surface is within {MAX_SIZE_M} m of the origin "
                f"on every axis)",
            )
        out[name] = np.array(xyz, dtype=np.float64)
    return out


def read_meta(path: Path) -> SessionMeta:
    if not path.is_file():
        raise MissingFileError(path, "session.json does not exist")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise SessionFormatError(path, f"not UTF-8 text ({exc})") from exc
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SessionFormatError(
            path, f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from exc
    return parse_meta(path, obj)

