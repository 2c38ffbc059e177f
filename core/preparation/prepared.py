"""A prepared session: calibration, calibrated probe paths, measured forces and cleaned
clouds in the phantom frame, ready for any number of replays.

Cleaned clouds are held as one (P, 3) float32 array of points and (F + 1,) offsets per
sequence (:class:`Clouds`), in memory or memory-mapped from the preparation cache
(:mod:`core.preparation.prepare`): a paper-size session (25k frames) then costs the
pages a computation touches, not its gigabytes, and a pickled session (a Dask scatter)
carries the file's path instead of the points.
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import mmap

import numpy as np

from core.preparation.calibration import Calibration
from core.preparation.probe import ProbePath
from core.preparation.shape import RestShape, rest_shape

__all__ = ["Clouds", "PrepareConfig", "PreparedSequence", "PreparedSession", "release_pages"]


def _mapping_of(array: np.ndarray) -> "mmap.mmap | None":
    """The ``mmap.mmap`` an array's memory comes from (a ``np.load(mmap_mode=...)`` array
    and its views, even converted to plain ndarrays), or None."""
    base = array
    while base is not None:
        if isinstance(base, mmap.mmap):
            return base
        base = getattr(base, "base", None)
    return None


class Clouds(SequenceABC):
    """Per-frame point clouds: F arrays (M_f, 3) float32, m, phantom frame, stored as
    one (P, 3) array and (F + 1,) int64 offsets (frame f is ``points[off[f]:off[f + 1]]``).

    Indexing gives a frame's (M_f, 3) view (an int) or a tuple of them (a slice);
    iterating gives the frames in order.
    """

    def __init__(self, points: np.ndarray, offsets: np.ndarray, *, files: tuple | None = None):
        points = np.asarray(points)
        offsets = np.asarray(offsets, dtype=np.int64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"clouds' points must be (P, 3), got {points.shape}")
        if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or offsets[-1] != points.shape[0] \
                or np.any(np.diff(offsets) < 0):
            raise ValueError(f"clouds' offsets must rise from 0 to {points.shape[0]}, got {offsets[:3]}...{offsets[-3:]}")
        self.points = points
        self.offsets = offsets
        self.files = files

    @classmethod
    def from_arrays(cls, clouds: Sequence[np.ndarray]) -> "Clouds":
        """Clouds in memory from F arrays (M_f, 3) (stored as float32)."""
        counts = np.array([np.asarray(c).shape[0] for c in clouds], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)])
        pts = np.concatenate([np.asarray(c, dtype=np.float32).reshape(-1, 3) for c in clouds]) if len(clouds) \
            else np.zeros((0, 3), dtype=np.float32)
        return cls(pts, offsets)

    @classmethod
    def open(cls, points_file: str, offsets_file: str, start: int = 0, stop: int | None = None) -> "Clouds":
        """Clouds memory-mapped from ``.npy`` files (read-only), frames ``[start, stop)``."""
        off = np.load(offsets_file)
        stop = off.size - 1 if stop is None else int(stop)
        pts = np.load(points_file, mmap_mode="r")[off[start]:off[stop]]
        return cls(pts, off[start:stop + 1] - off[start], files=(points_file, offsets_file, int(start), stop))

    def window(self, start: int, stop: int) -> "Clouds":
        """Frames ``[start, stop)`` as clouds of their own (views; mapped from the same file)."""
        off = self.offsets
        files = None
        if self.files is not None:
            base = self.files[2]
            files = (self.files[0], self.files[1], base + int(start), base + int(stop))
        return Clouds(self.points[off[start]:off[stop]], off[start:stop + 1] - off[start], files=files)

    def __len__(self) -> int:
        return int(self.offsets.size - 1)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return tuple(self[k] for k in range(*i.indices(len(self))))
        n = len(self)
        i = int(i)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {n} clouds")
        i %= n
        return self.points[self.offsets[i]:self.offsets[i + 1]]

    @property
    def counts(self) -> np.ndarray:
        """(F,) int64 points per frame."""
        return np.diff(self.offsets)

    def release(self) -> bool:
        """Drop the pages of memory-mapped clouds from this process's resident set
        (``madvise(MADV_DONTNEED)`` on the read-only mapping: the next access reads them
        back from the kernel's page cache, or the file). A stage that is done with a
        sequence calls it, so a process holds the clouds of the sequence it works on, not
        of every sequence it has touched (on a paper-size session, 3.9 GB of cleaned
        clouds per process). The whole file's mapping is released (a window's too: they
        share it). Clouds in memory are left as they are.

        Returns:
            True when pages were released.
        """
        mm = _mapping_of(self.points)
        if mm is None or not hasattr(mmap, "MADV_DONTNEED") or mm.closed:
            return False
        try:
            mm.madvise(mmap.MADV_DONTNEED)
        except (OSError, ValueError):
            return False
        return True

    def __reduce__(self):
        if self.files is not None:  # a worker maps the file itself
            return (Clouds.open, self.files)
        return (Clouds, (np.asarray(self.points), self.offsets))

    def __repr__(self) -> str:
        return f"Clouds({len(self)} frames, {self.points.shape[0]} points{', ' + self.files[0] if self.files else ''})"


def release_pages(clouds) -> bool:
    """:meth:`Clouds.release` for any sequence of clouds (a list of arrays: nothing to do)."""
    return clouds.release() if isinstance(clouds, Clouds) else False


@dataclass(frozen=True)
class PrepareConfig:
    """How a session is prepared.

    Attributes:
        sequences: names to prepare; None prepares all.
        voxel_size: voxel downsampling of cleaned clouds, m (0 disables).
        max_points: random subsample of each cleaned cloud (None keeps all).
        path_smoothing: the calibrated probe path is low-passed by a Gaussian kernel of
            this many seconds (:meth:`ProbePath.smoothed`; 0 keeps the raw kinematics).
    """

    sequences: tuple[str, ...] | None = None
    voxel_size: float = 0.001
    max_points: int | None = None
    path_smoothing: float = 0.01

    @classmethod
    def of(cls, config) -> "PrepareConfig":
        """The preparation settings of any config that carries them (a ``ReplayConfig``)."""
        if config is None:
            return cls()
        if isinstance(config, cls):
            return config
        return cls(sequences=None if getattr(config, "sequences", None) is None else tuple(config.sequences),
                   voxel_size=float(getattr(config, "voxel_size", 0.001)), max_points=getattr(config, "max_points", None),
                   path_smoothing=float(getattr(config, "path_smoothing", 0.01)))


@dataclass(frozen=True)
class PreparedSequence:
    """A sequence ready to simulate, everything in the phantom frame.

    Attributes:
        name, role: from session.json.
        frame_times: (F,) camera frame times, s.
        probe: the calibrated probe path (sphere centres, phantom frame).
        clouds: F arrays (M_f, 3) of cleaned measured points, m, phantom frame (a
            :class:`Clouds`, or any sequence of arrays).
        force: (K, 3) measured probe force in the phantom frame (N) at ``probe.t``, or None.
    """

    name: str
    role: str
    frame_times: np.ndarray
    probe: ProbePath
    clouds: Sequence[np.ndarray]
    force: np.ndarray | None = None

    @property
    def n_points(self) -> int:
        return int(sum(c.shape[0] for c in self.clouds))

    def force_at(self, times) -> np.ndarray | None:
        """(M, 3) measured probe force (N, phantom frame) interpolated at ``times`` (s), or None."""
        if self.force is None:
            return None
        times = np.asarray(times, dtype=np.float64)
        return np.stack([np.interp(times, self.probe.t, self.force[:, i]) for i in range(3)], axis=1)


@dataclass(frozen=True)
class PreparedSession:
    """Calibration plus prepared sequences of one session (reused across many simulations).

    Attributes:
        path: the session folder. size: (3,) box size, m. mass: kg. probe_radius: m.
        calibration: :class:`Calibration`. sequences: name -> :class:`PreparedSequence`.
        timings: stage timings, s (``load``, ``calibrate``, ``clean``; ``cache`` when
            read from the preparation cache). reference: (M, 3) the cleaned reference
            cloud, phantom frame, or None.
        cache_key: the preparation cache's key of this preparation ("" when not cached).
        stl_path: the session's ``phantom.stl`` (the rest shape, phantom frame, m), or
            None for the box of ``size``.
    """

    path: Path
    size: np.ndarray
    mass: float
    probe_radius: float
    calibration: Calibration
    sequences: dict[str, PreparedSequence]
    timings: dict[str, float]
    reference: np.ndarray | None = None
    cache_key: str = ""
    stl_path: Path | None = None

    @property
    def shape(self) -> RestShape:
        """The rest phantom's geometry (:func:`core.preparation.shape.rest_shape`): the
        ``phantom.stl`` surface when the session has one, else the box of ``size``.

        Raises:
            ValueError: the STL is not a watertight surface."""
        return rest_shape(self.size, self.stl_path)

    def rest_frames(self, name: str, *, settle: float = 1.0, clearance: float = 0.002) -> np.ndarray:
        """Indices of frames of sequence ``name`` where the phantom is at rest: the probe
        has been at least ``clearance`` (m) clear of the box for the last ``settle`` s."""
        seq = self.sequences[name]
        lag = np.linspace(0.0, settle, 11)
        times = (seq.frame_times[:, None] - lag[None, :]).ravel()
        c = seq.probe.at(times)
        outside = np.maximum(np.maximum(-c, c - self.size), 0.0)
        clear = np.linalg.norm(outside, axis=1) > self.probe_radius + clearance
        return np.flatnonzero(clear.reshape(-1, lag.size).all(axis=1))
