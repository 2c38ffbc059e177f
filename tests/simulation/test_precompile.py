"""``tissuetwin precompile`` (scripts/setup.sh runs it): after it, replays and their
sensitivities on another mesh, with effects, compile nothing new."""

import numpy as np
from numba.core.registry import CPUDispatcher

from app.cli import main
from core.simulation import Material, ProbePath, SimulationConfig, box_mesh, build_model, effect_from_dict, simulate
from core.simulation import kernels, lowrank, stepper, tangent, tangent_step
from core.simulation.sensitivity import simulate_sensitivities


def _signatures() -> dict[str, int]:
    return {f"{m.__name__}.{name}": len(obj.signatures)
            for m in (kernels, lowrank, stepper, tangent, tangent_step)
            for name, obj in vars(m).items() if isinstance(obj, CPUDispatcher)}


def test_after_precompile_a_replay_and_its_sensitivities_compile_nothing(capsys):
    assert main(["precompile"]) == 0
    assert "simulation kernels compiled and cached" in capsys.readouterr().out
    before = _signatures()
    assert before["core.simulation.stepper.advance"] >= 1
    size = (0.05, 0.03, 0.03)
    mesh = box_mesh(size, (6, 4, 4))
    t = np.arange(0.0, 0.5, 0.01)
    depth = np.interp(t, [0.0, 0.2, 0.5], [0.003, -0.004, -0.004])
    centres = np.stack([np.full_like(t, 0.02), np.full_like(t, 0.015), size[2] + 0.005 + depth], axis=1)
    path = ProbePath(t, centres)
    frames = np.arange(0.0, 0.5, 0.1) + 0.001

    def build(theta, factorize):
        effects = [effect_from_dict({"kind": "gravity", "g": [0.0, 0.0, theta[1]]}),
                   effect_from_dict({"kind": "friction", "mu": 0.3})]
        return build_model(mesh, 0.05, Material(10 ** theta[0], 0.45), SimulationConfig(), effects,
                           factorize=factorize)

    theta = np.array([np.log10(4000.0), -9.81])
    assert simulate(build(theta, True), path, 0.005, frames).ok
    assert simulate_sensitivities(build, theta, path, 0.005, frames, scales=[0.02, 1.0]).result.ok
    after = _signatures()
    assert {k: v for k, v in after.items() if v != before[k]} == {}


def test_a_changed_kernel_source_clears_the_whole_numba_cache(tmp_path):
    """numba keys a cache by its own file only: a caller's cached kernel kept a changed
    callee's old code. The digest of every cached module's source decides instead."""
    from core.simulation.precompile import clear_stale_cache

    pkg = tmp_path / "pkg"
    (pkg / "__pycache__").mkdir(parents=True)
    callee, caller = pkg / "callee.py", pkg / "caller.py"
    callee.write_text("@njit(cache=True)\ndef f(x):\n    return x + 1\n")
    caller.write_text("@njit(cache=True)\ndef g(x):\n    return f(x)\n")
    stamp = tmp_path / "stamp"
    compiled = [pkg / "__pycache__" / "caller.g-3.py311.1.nbc", pkg / "__pycache__" / "caller.g-3.py311.nbi"]

    def cache():
        for f in compiled:
            f.write_bytes(b"x")

    cache()
    assert clear_stale_cache(pkg, stamp) and not any(f.exists() for f in compiled)  # no record yet
    cache()
    assert not clear_stale_cache(pkg, stamp) and all(f.exists() for f in compiled)  # unchanged: kept
    callee.write_text("@njit(cache=True)\ndef f(x):\n    return x + 2\n")  # the callee alone changes
    assert clear_stale_cache(pkg, stamp) and not any(f.exists() for f in compiled)
