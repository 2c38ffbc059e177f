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

import time
import warnings

import numpy as np
from numba.core.errors import NumbaPerformanceWarning

__all__ = ["compile_kernels"]


def compile_kernels() -> float:
    """Step tiny models through every compiled path so numba writes its cache.

    Returns:
        The wall time it took, s (a few seconds when the cache is already there).

    Raises:
        core.errors.SimulationError: if a tiny replay fails (a broken install).
    """
    from core.simulation import ProbePath, box_mesh

    t0 = time.perf_counter()
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
