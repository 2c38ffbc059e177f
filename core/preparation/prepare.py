"""Prepare a session once: calibrate, clean every frame, cache the result.

Cleaning (:func:`core.registration.clean_cloud`: table, instrument, outliers, voxel
downsampling) is independent per frame, so the frames of a long session are cleaned in
chunks by worker processes. The result is stored once per session content and
preparation settings in the preparation cache (:func:`cache_root`): per sequence the
cleaned points as one float32 ``.npy`` and their per-frame offsets, beside the frame
times, the calibrated probe path and the measured force. Every later command and job of
the same session (a replay, a fit, a diagnosis, the workbench's jobs) maps the clouds
from there instead of cleaning again, and holds only the pages it touches.

The cache key hashes ``session.json``, the calibration files, each prepared sequence's
``kinematics.csv`` and ``frames.csv`` in full, and each cloud file's name, size and
modification time (reading 13 GB of paper-size clouds to hash them would cost more than
a cleaning), with the preparation settings and picked ICP pairs. A session rewritten in
place gets a new key. Entries are written to a temporary folder and renamed, so a
crashed preparation never leaves a half-written one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Callable

import numpy as np

from core.errors import SessionFormatError
from core.io import Session, read_cloud, read_picked, read_session
from core.preparation.calibration import Calibration, calibrate
from core.preparation.prepared import Clouds, PrepareConfig, PreparedSequence, PreparedSession
from core.preparation.probe import ProbePath
from core.registration import clean_cloud, probe_pose_phantom

__all__ = ["prepare_session", "cache_root", "preparation_key", "CACHE_VERSION"]

Callback = Callable[[float, str], None]

CACHE_VERSION = "prepared/1"
"""Bumped whenever what a preparation computes changes (cleaning, calibration)."""

PARALLEL_MIN_FRAMES = 400
"""Sessions with fewer frames are cleaned in this process (a worker's start costs ~2 s)."""

CHUNK = 64
"""Frames per cleaning job."""


def cache_root() -> Path:
    """The preparation cache's folder: ``$TISSUETWIN_CACHE_DIR/prepared``, else
    ``$XDG_CACHE_HOME/tissuetwin/prepared`` (``~/.cache`` by default)."""
    base = os.environ.get("TISSUETWIN_CACHE_DIR")
    if base:
        return Path(base) / "prepared"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "tissuetwin" / "prepared"


def _transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def preparation_key(session: Session, config: PrepareConfig, names: list[str], picked,
                    calibration: Calibration | None) -> str:
    """The cache key of a preparation (see the module docstring), 32 hex digits."""
    h = hashlib.blake2b(digest_size=16)
    h.update(CACHE_VERSION.encode())
    root = Path(session.path)

    def content(p: Path) -> None:
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes() if p.exists() else b"<absent>")

    def stat(p: Path) -> None:
        h.update(str(p.relative_to(root)).encode())
        if p.exists():
            st = p.stat()
            h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
        else:
            h.update(b"<absent>")

    content(root / "session.json")
    for name in ("corners.csv", "landmarks.csv", "picked.json"):
        content(root / "calibration" / name)
    stat(root / "calibration" / "reference.ply")
    stat(root / "phantom.stl")
    for n in names:
        seq = session.sequences[n]
        content(seq.path / "kinematics.csv")
        content(seq.path / "frames.csv")
        for i in range(len(seq)):
            stat(seq.cloud_path(i))
    h.update(json.dumps([config.voxel_size, config.max_points, config.path_smoothing, names]).encode())
    if picked is not None:
        h.update(np.ascontiguousarray(np.asarray(picked[0], dtype=np.float64)).tobytes())
        h.update(np.ascontiguousarray(np.asarray(picked[1], dtype=np.float64)).tobytes())
    if calibration is not None:
        h.update(json.dumps(calibration.to_json(), sort_keys=True).encode())
    return h.hexdigest()


def _clean_frames(job: tuple) -> list[np.ndarray]:
    """Clean a chunk of frames (worker function): ``job = (files, centres (k, 3), axes
    (k, 3), T_phantom_camera, size, probe radius, voxel size, max points, seeds)``;
    returns their cleaned points, (M_f, 3) float32, m, phantom frame."""
    files, centres, axes, T, size, radius, voxel, max_points, seeds = job
    out = []
    for f, c, a, seed in zip(files, centres, axes, seeds):
        res = clean_cloud(read_cloud(f), T, size, probe_centre_phantom=c, shaft_axis_phantom=a, probe_radius=radius,
                          voxel_size=voxel, max_points=max_points, seed=int(seed))
        out.append(res.points_phantom.astype(np.float32))
    return out


def _clean_sequence(session: Session, name: str, cal: Calibration, config: PrepareConfig, pool,
                    progress: Callable[[int], None]) -> tuple[np.ndarray, np.ndarray, ProbePath, np.ndarray | None]:
    """(points (P, 3) float32, offsets (F + 1,), probe path, force (K, 3) or None) of one sequence."""
    seq = session.sequences[name]
    kin = seq.kinematics
    Tpr = cal.T_phantom_robot
    path = ProbePath(kin.t, _transform(Tpr, kin.position)).smoothed(config.path_smoothing)
    centres_f, axes_f = probe_pose_phantom(kin, seq.frames.t, Tpr)  # axes: tool z, shaft -> tip
    size = np.asarray(session.meta.phantom.size, dtype=np.float64)
    radius = float(session.meta.probe.radius)
    n = len(seq)
    jobs = [([str(seq.cloud_path(i)) for i in range(a, min(a + CHUNK, n))], centres_f[a:a + CHUNK], axes_f[a:a + CHUNK],
             cal.T_phantom_camera, size, radius, config.voxel_size, config.max_points, np.arange(a, min(a + CHUNK, n)))
            for a in range(0, n, CHUNK)]
    clouds: list[np.ndarray] = []
    results = pool.map(_clean_frames, jobs) if pool is not None else map(_clean_frames, jobs)
    for chunk in results:
        clouds.extend(chunk)
        progress(len(chunk))
    counts = np.array([c.shape[0] for c in clouds], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    points = np.concatenate(clouds).astype(np.float32, copy=False) if clouds else np.zeros((0, 3), np.float32)
    del clouds
    force = None if kin.force is None else kin.force @ Tpr[:3, :3].T
    return points, offsets, path, force


class _EntryWriter:
    """A cache entry written sequence by sequence into a temporary folder and renamed into
    place by :meth:`finish`, so a paper-size preparation never holds more than one
    sequence's cleaned points (a crashed preparation leaves no half-written entry).

    Raises:
        OSError: the folder cannot be written (a read-only or full cache).
    """

    def __init__(self, folder: Path, session: Session, cal: Calibration):
        self.folder = folder
        self.tmp = folder.parent / f"{folder.name}.tmp-{os.getpid()}-{time.time_ns()}"
        self.tmp.mkdir(parents=True)
        self.meta = {"version": CACHE_VERSION, "session": str(session.path), "calibration": cal.to_json(),
                     "sequences": {}}

    def add(self, name: str, role: str, frame_times, points, offsets, path: ProbePath, force) -> None:
        stem = f"s{len(self.meta['sequences']):03d}"
        np.save(self.tmp / f"{stem}.points.npy", points)
        np.save(self.tmp / f"{stem}.offsets.npy", offsets)
        arrays = {"frame_times": frame_times, "probe_t": path.t, "probe_centres": path.centres}
        if force is not None:
            arrays["force"] = force
        np.savez(self.tmp / f"{stem}.arrays.npz", **arrays)
        self.meta["sequences"][name] = {"role": role, "stem": stem}

    def read_back(self) -> dict:
        """{name: (role, frame_times, points, offsets, path, force)} of the sequences
        written so far, in memory (the fallback when the cache cannot be finished)."""
        return {name: _read_sequence(self.tmp, info, mapped=False) for name, info in self.meta["sequences"].items()}

    def finish(self, reference) -> None:
        if reference is not None:
            np.save(self.tmp / "reference.npy", reference)
        (self.tmp / "meta.json").write_text(json.dumps(self.meta, indent=1))
        try:
            self.tmp.rename(self.folder)
        except OSError:
            if not (self.folder / "meta.json").exists():
                raise  # not a race: the caller reads back what was written
            self.abort()  # another process wrote the same entry meanwhile

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def _read_sequence(folder: Path, info: dict, *, mapped: bool) -> tuple:
    """One sequence of an entry: (role, frame_times, clouds, path, force) with its clouds
    memory-mapped as :class:`Clouds` (``mapped``), else (role, frame_times, points,
    offsets, path, force) in memory."""
    stem = info["stem"]
    points, offsets = folder / f"{stem}.points.npy", folder / f"{stem}.offsets.npy"
    with np.load(folder / f"{stem}.arrays.npz") as z:
        force = z["force"] if "force" in z.files else None
        ft, path = z["frame_times"], ProbePath(z["probe_t"], z["probe_centres"])
    if mapped:
        return info["role"], ft, Clouds.open(str(points), str(offsets)), path, force
    return info["role"], ft, np.load(points), np.load(offsets), path, force


def _read_entry(folder: Path) -> tuple[Calibration, dict, np.ndarray | None]:
    meta = json.loads((folder / "meta.json").read_text())
    if meta.get("version") != CACHE_VERSION:
        raise ValueError("stale cache entry")
    seqs = {name: _read_sequence(folder, info, mapped=True) for name, info in meta["sequences"].items()}
    ref = folder / "reference.npy"
    return Calibration.from_json(meta["calibration"]), seqs, (np.load(ref) if ref.exists() else None)


def prepare_session(
    session: Session | str | Path,
    config=None,
    *,
    calibration: Calibration | None = None,
    picked=None,
    callback: Callback | None = None,
    cache: bool = True,
    workers: int | None = 2,
) -> PreparedSession:
    """Read (if a path), calibrate (unless given) and clean every selected sequence, or
    map an earlier preparation of the same content from the cache.

    Args:
        session: a session folder or a read :class:`core.io.Session`.
        config: a :class:`PrepareConfig` (or any config carrying its fields, such as a
            ``ReplayConfig``); default settings when None.
        calibration: use this calibration instead of computing one.
        picked: (points_camera (K, 3), points_phantom (K, 3)) ICP start pairs (default:
            ``calibration/picked.json`` when present).
        callback: ``callback(fraction, message)``.
        cache: read and write the preparation cache (:func:`cache_root`).
        workers: processes cleaning frames for sessions of at least
            :data:`PARALLEL_MIN_FRAMES` frames (0 or None: in this process).

    Returns:
        A :class:`PreparedSession` whose clouds are float32, memory-mapped from the cache
        when ``cache``.

    Raises:
        SessionFormatError: bad input files, or unknown sequence names.
        RegistrationError: a registration that does not fit.
        CleaningError: a frame with nothing of the phantom left.
    """
    cfg = PrepareConfig.of(config)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if not isinstance(session, Session):
        session = read_session(session)
    timings["load"] = time.perf_counter() - t0
    names = list(session.sequences) if cfg.sequences is None else list(cfg.sequences)
    unknown = [n for n in names if n not in session.sequences]
    if unknown:
        raise SessionFormatError(session.path / "session.json", f"no sequence(s) named {unknown}; it has {list(session.sequences)}")
    if picked is None:
        picked = read_picked(session.path)
    meta = session.meta
    size = np.asarray(meta.phantom.size, dtype=np.float64)

    def result(cal, seqs, reference, key) -> PreparedSession:
        return PreparedSession(path=Path(session.path), size=size, mass=float(meta.phantom.mass),
                               probe_radius=float(meta.probe.radius), calibration=cal,
                               sequences={n: PreparedSequence(n, role, np.asarray(ft), pth, clouds, force)
                                          for n, (role, ft, clouds, pth, force) in seqs.items()},
                               timings=timings, reference=reference, cache_key=key,
                               stl_path=None if session.phantom_stl is None else Path(session.phantom_stl))

    key, folder = "", None
    if cache:
        t0 = time.perf_counter()
        key = preparation_key(session, cfg, names, picked, calibration)
        folder = cache_root() / key
        if (folder / "meta.json").exists():
            try:
                cal, seqs, reference = _read_entry(folder)
                timings["cache"] = time.perf_counter() - t0
                if callback:
                    callback(1.0, "prepared (from the cache)")
                return result(cal, seqs, reference, key)
            except (OSError, ValueError, KeyError):
                shutil.rmtree(folder, ignore_errors=True)  # unreadable: prepare again
        timings["cache"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if callback:
        callback(0.0, "calibrating")
    cal = calibration or calibrate(session, picked=picked)
    timings["calibrate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    total = sum(len(session.sequences[n]) for n in names)
    done = [0]

    def progress(k: int) -> None:
        done[0] += k
        if callback:
            callback(done[0] / max(total, 1), f"cleaning ({done[0]}/{total} frames)")

    writer = None
    if folder is not None:
        try:
            folder.parent.mkdir(parents=True, exist_ok=True)
            writer = _EntryWriter(folder, session, cal)
        except OSError:  # a read-only or full cache: keep the preparation in memory
            key = ""
    kept: dict = {}  # sequences held in memory: only when they cannot be written

    def keep(n: str, entry: tuple) -> None:
        """Write a cleaned sequence to the cache entry (and let it go), or keep it in memory."""
        nonlocal writer, key
        if writer is not None:
            try:
                writer.add(n, *entry)
                return
            except OSError:
                kept.update(writer.read_back())
                writer.abort()
                writer, key = None, ""
        kept[n] = entry

    pool = None
    if workers and total >= PARALLEL_MIN_FRAMES:
        import multiprocessing

        # "spawn": the parent holds Open3D/TBB threads, which fork() does not copy safely
        pool = ProcessPoolExecutor(max_workers=int(workers), mp_context=multiprocessing.get_context("spawn"))
    try:
        for n in names:
            try:
                points, offsets, pth, force = _clean_sequence(session, n, cal, cfg, pool, progress)
            except BrokenProcessPool:
                # e.g. a script without an ``if __name__ == "__main__"`` guard: the spawned
                # workers cannot start. Same results, cleaned in this process.
                pool.shutdown(wait=False, cancel_futures=True)
                pool = None
                points, offsets, pth, force = _clean_sequence(session, n, cal, cfg, None, progress)
            keep(n, (session.sequences[n].role, np.asarray(session.sequences[n].frames.t), points, offsets, pth, force))
            del points, offsets
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    reference = session.reference_cloud()
    reference_phantom = None
    if reference is not None:
        reference_phantom = clean_cloud(reference, cal.T_phantom_camera, size, voxel_size=cfg.voxel_size).points_phantom
    timings["clean"] = time.perf_counter() - t0
    if writer is not None:
        try:
            writer.finish(reference_phantom)
        except OSError:  # a full cache: keep the preparation in memory
            kept.update(writer.read_back())
            writer.abort()
            key = ""
        else:
            _, seqs, reference_phantom = _read_entry(folder)
            return result(cal, seqs, reference_phantom, key)
    seqs = {n: (role, ft, Clouds(points, offsets), pth, force) for n, (role, ft, points, offsets, pth, force) in kept.items()}
    return result(cal, seqs, reference_phantom, key)
