"""Any phantom shape (issue 18): replay speed, E-fit and diagnosis wall time on a dome and
a kidney-like phantom beside a box of the same volume, each given as ``phantom.stl`` and
meshed by Gmsh at one element size (so the three hold comparable element counts).

For each shape it generates a ``small``-preset session of ``--duration`` s sequences
(seed ``--seed``, hidden gravity, force columns) with ``tissuetwin generate --phantom-stl``'s
code, then measures on an idle machine:

- Gmsh meshing time, nodes, tetrahedra, minimum dihedral angle and bandwidth;
- the replay's steps per second (simulation only, all four sequences, truth E);
- ``fit_youngs_modulus`` wall time and replays (serial);
- ``diagnose`` wall time and simulations (serial; skipped with ``--no-diagnosis``).

Prints one table; asserts nothing.

    .venv/bin/python -m benchmarks.bench_shapes [--duration 6] [--seed 3] [--no-diagnosis]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh


def _box_surface(volume: float, height: float) -> trimesh.Trimesh:
    """A box ``height`` high with a square footprint of the given volume, corner at 0."""
    side = float(np.sqrt(volume / height))
    box = trimesh.creation.box(extents=[side, side, height])
    box.apply_translation([side / 2, side / 2, height / 2])
    return box


def main(argv=None) -> int:
    from core.identification import fit_youngs_modulus
    from core.identification.trials import Trial
    from core.lab.generate import PRESETS, generate_session
    from core.lab.shapes import dome_surface, kidney_surface
    from core.preparation import prepare_session
    from core.simulation.meshing import default_element_size, mesh_quality, tetrahedralise
    from core.simulation.replay import ReplayConfig, replay

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--no-diagnosis", action="store_true")
    ap.add_argument("--workdir", default=None, help="keep sessions here (default: a temporary folder)")
    args = ap.parse_args(argv)

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench-shapes-"))
    work.mkdir(parents=True, exist_ok=True)
    dome = trimesh.Trimesh(*dome_surface())
    kidney = trimesh.Trimesh(*kidney_surface())
    box = _box_surface(float(dome.volume), float(dome.bounds[1, 2]))
    h = default_element_size(float(dome.volume))
    rows = []
    for name, surface in (("box", box), ("dome", dome), ("kidney", kidney)):
        stl = work / f"{name}.stl"
        surface.export(str(stl))
        t0 = time.perf_counter()
        mesh = tetrahedralise(stl, h, cache=False)
        t_mesh = time.perf_counter() - t0
        q = mesh_quality(mesh)
        session = work / f"{name}-s{args.seed}"
        if not session.exists():
            generate_session(session, preset=PRESETS["small"].with_duration(args.duration), seed=args.seed,
                             phantom_stl=stl, with_force=True, effects=[{"kind": "gravity", "g": [0.0, 0.0, -9.81]}])
        truth = json.loads((session / "truth.json").read_text())
        prepared = prepare_session(session)
        r = replay(session, ReplayConfig(youngs_modulus=truth["youngs_modulus"], element_size=h), prepared=prepared)
        sim_time = r.timings["simulate"]
        seconds = sum(float(s.frame_times[-1]) for s in r.sequences.values())
        t0 = time.perf_counter()
        fit = fit_youngs_modulus(prepared, base=Trial(sequence="", youngs_modulus=1.0, element_size=h,
                                                      effects=({"kind": "gravity", "g": [0.0, 0.0, -9.81]},)))
        t_fit = time.perf_counter() - t0
        row = dict(shape=name, volume_cm3=float(surface.volume) * 1e6, nodes=mesh.n_nodes, tets=mesh.n_tets,
                   min_dihedral=q.min_dihedral_deg, bandwidth=q.bandwidth, mesh_s=t_mesh,
                   replay_s_per_min=sim_time / seconds * 60.0,
                   fit_s=t_fit, fit_replays=fit.evaluations, fit_E=fit.youngs_modulus, truth_E=truth["youngs_modulus"])
        if not args.no_diagnosis:
            from core.diagnosis import DiagnosisConfig, diagnose_prepared

            t0 = time.perf_counter()
            d = diagnose_prepared(prepared, DiagnosisConfig(element_size=h))
            row.update(diagnose_s=time.perf_counter() - t0, simulations=d.simulations,
                       claimed=[c.kind for c in d.causes])
        rows.append(row)
        print(json.dumps(row), flush=True)
    print()
    print(f"{'shape':8} {'cm3':>6} {'nodes':>6} {'tets':>6} {'dih':>5} {'band':>5} {'mesh s':>7} {'s/min':>6} "
          f"{'fit s':>6} {'E fit':>8} {'E true':>7} {'diag s':>7} claimed")
    for r in rows:
        e = "n/a" if r["fit_E"] is None else f"{r['fit_E']:.0f}"
        print(f"{r['shape']:8} {r['volume_cm3']:6.1f} {r['nodes']:6d} {r['tets']:6d} {r['min_dihedral']:5.1f} "
              f"{r['bandwidth']:5d} {r['mesh_s']:7.2f} {r['replay_s_per_min']:6.2f} {r['fit_s']:6.1f} {e:>8} "
              f"{r['truth_E']:7.0f} {r.get('diagnose_s', float('nan')):7.1f} {r.get('claimed', '')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
