"""Compile the simulation's numba kernels once, at install time, instead of in a user's
first command.

The compiled loop (:mod:`core.simulation.stepper` and the kernels it calls) takes about
100 s of compilation on a 2-core machine the first time a process steps a model, and
numba keys its on-disk cache by each source file's modification time, so every fresh
install (a clone, a container build) pays it once. :func:`compile_kernels` pays it
during ``scripts/setup.sh`` by stepping a tiny model through every path the compiled
loop has: both material laws, no effect and every effect kind at once, a replay and its
sensitivities, and a static equilibrium under a body force. The results are discarded.
"""

from __future__ import annotations

import hashlib
import time
import warnings
from pathlib import Path

import numpy as np
from numba.core.errors import NumbaPerformanceWarning

__all__ = ["compile_kernels", "clear_stale_cache"]

STAMP = Path(__file__).resolve().parents[1] / "__pycache__" / "numba-sources.sha256"
"""Digest of the compiled modules' sources at the last :func:`compile_kernels` (beside
Python's own caches, ignored by git)."""


def _sources(root: Path) -> list[bytes]:
    """The sources of the modules under ``root`` with numba kernels cached on disk (this one
    aside), in path order, each read once."""
    here = Path(__file__).resolve()
    texts = (p.read_bytes() for p in sorted(root.rglob("*.py")) if p.resolve() != here)
    return [text for text in texts if b"cache=True" in text]


def clear_stale_cache(root: Path | None = None, stamp: Path | None = None) -> bool:
    """Delete numba's on-disk cache of ``core`` when any compiled module's source changed
    since the last :func:`compile_kernels`.

    numba keys a kernel's cache by its own file's modification time, not by the kernels it
    calls from other files: after a change to :func:`core.simulation.kernels.sphere_contacts`
    alone, the compiled time loop (:func:`core.simulation.stepper.advance`, which calls it)
    kept running the old contact geometry from its cache (measured 2026-11-29: a dome
    replay's forces unchanged until the cache was deleted).

    Args:
        root: the package whose modules and caches are checked (default ``core``).
        stamp: where the digest is kept (default :data:`STAMP`).

    Returns:
        True when the cache was deleted (or there was no record of it).
    """
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    stamp = Path(stamp) if stamp is not None else STAMP
    digest = hashlib.sha256(b"".join(_sources(root))).hexdigest()
    if stamp.exists() and stamp.read_text().strip() == digest:
        return False
    for f in list(root.rglob("__pycache__/*.nbi")) + list(root.rglob("__pycache__/*.nbc")):
        f.unlink(missing_ok=True)
    stamp.parent.mkdir(parents=True, exist_ok=True)
    stamp.write_text(digest + "\n")
    return True


def compile_kernels() -> float:
    """Step tiny models through every compiled path so numba writes its cache.

    The cache of kernels whose sources (or their callees') changed is deleted first
    (:func:`clear_stale_cache`).

    Returns:
        The wall time it took, s (a few seconds when the cache is already there).

    Raises:
        core.errors.SimulationError: if a tiny replay fails (a broken install).
    """
    from core.simulation import ProbePath, box_mesh

    t0 = time.perf_counter()
    clear_stale_cache()
    size = (0.03, 0.02, 0.02)
    mesh = box_mesh(size, (4, 3, 3))
    # a press, a slide and a release over the middle of the top: contact on and off, sliding
    keys_t = [0.0, 0.1, 0.2, 0.3, 0.4]
    top = size[2] + 0.004
    keys = np.array([[0.015, 0.01, top + 0.002], [0.015, 0.01, top - 0.006], [0.018, 0.011, top - 0.006],
                     [0.018, 0.011, top + 0.002], [0.018, 0.011, top + 0.002]])
    t = np.arange(0.0, 0.4, 0.005)
    path = ProbePath(t, np.stack([np.interp(t, keys_t, keys[:, i]) for i in range(3)], axis=1))
    frames = np.arange(0.0, 0.4, 0.05) + 0.002
    every_kind = [
        {"kind": "gravity", "g": [0.0, 0.0, -9.81]},
        {"kind": "inclusion", "center": [0.015, 0.01, 0.01], "radius": 0.005, "stiffness_ratio": 4.0},
        {"kind": "viscoelasticity", "relaxation_time": 0.5, "stiffness_ratio": 1.0},
        {"kind": "friction", "mu": 0.4},
        {"kind": "base_compliance", "stiffness": 1e7},
        {"kind": "probe_radius", "radius": 0.004},
        {"kind": "time_offset", "offset": 0.01},
        {"kind": "kinematic_offset", "offset": [0.0002, 0.0, -0.0001]},
    ]
    with warnings.catch_warnings():  # compile-time notes on small dot products, not for an install log
        warnings.simplefilter("ignore", NumbaPerformanceWarning)
        _replay_all(mesh, path, frames, every_kind)
    return time.perf_counter() - t0


def _replay_all(mesh, path, frames, every_kind) -> None:
    from core.errors import SimulationError
    from core.simulation import Material, SimulationConfig, build_model, effect_from_dict, simulate
    from core.simulation.sensitivity import simulate_sensitivities

    for law, options in (("corotational", {}), ("stable_neo_hookean", {"newton_iterations": 2})):
        for effects in ([], every_kind):
            def build(theta, factorize, effects=effects, law=law, options=options):
                return build_model(mesh, 0.01, Material(10 ** theta[0], 0.44, law), SimulationConfig(**options),
                                   [effect_from_dict(e) for e in effects], factorize=factorize)

            result = simulate(build(np.array([np.log10(5000.0)]), True), path, 0.004, frames)
            s = simulate_sensitivities(build, np.array([np.log10(5000.0)]), path, 0.004, frames, scales=[0.02])
            if not (result.ok and s.result.ok):
                raise SimulationError(f"precompile: the tiny {law} replay with {len(effects)} effects failed")
