"""``tissuetwin export``: write the calibrated twin of a replay or diagnosis as VTU
(ParaView), a SOFA scene or a MuJoCo MJCF model (:mod:`app.export`)."""

from __future__ import annotations

from pathlib import Path

from core.errors import TissueTwinError

FORMATS = ("vtu", "sofa", "mjcf")
"""As :data:`app.export.FORMATS` (repeated here so that ``--help`` does not import the writers)."""


def cmd_export(args) -> int:
    from app.export import export_run
    from app.run_mesh import mesh_label

    names = args.sequence or None
    sequence = None
    if args.format in ("sofa", "mjcf") and names:
        if len(names) > 1:
            raise TissueTwinError(f"--format {args.format} carries one probe path: give one --sequence, got {names}")
        sequence, names = names[0], None
    result = export_run(args.run, args.format, args.out, sequences=names, sequence=sequence, stride=args.stride,
                        youngs=args.youngs, poisson=args.poisson, grid=tuple(args.grid) if args.grid else None,
                        session=args.session)
    twin = result.twin
    print(f"{twin.kind} {twin.source}: {mesh_label(twin.mesh)}, {twin.mesh.n_nodes} nodes, "
          f"{twin.mesh.n_tets} tetrahedra, E {twin.youngs_modulus:.4g} Pa ({twin.youngs_source}), "
          f"nu {twin.poisson_ratio:g}, effects: {', '.join(e['kind'] for e in twin.effects) or 'none'}")
    for note in result.notes:
        print(f"note: {note}")
    out = Path(args.out)
    frames = sum(len(list((out / n).glob("frame_*.vtu"))) for n, s in twin.sequences.items()
                 if args.format == "vtu" and s.positions is not None)
    for f in result.files:
        print(f"wrote {f}")
    if frames:
        print(f"wrote {frames} frame files under {out}/<sequence>/")
    return 0


def register(sub) -> None:
    """Add the ``export`` subcommand to the ``tissuetwin`` parser's subparsers."""
    p = sub.add_parser(
        "export",
        help="export the calibrated twin of a replay or diagnosis as VTU, a SOFA scene or MuJoCo MJCF",
        description="RUN is a folder of `tissuetwin replay` (replay.json and <sequence>.npz: the mesh, its "
                    "trajectories and the model) or of `tissuetwin diagnose` (diagnosis.json: the base model "
                    "plus the claimed causes at the reported Young's modulus). vtu: the rest mesh with "
                    "per-element E and, for a replay, one .vtu per frame and a .pvd per sequence; sofa: "
                    "scene.py (createScene) and probe_path.csv; mjcf: twin.xml (a 3D flex) and "
                    "probe_path.csv. twin.json lists the parameters.",
    )
    p.add_argument("run", metavar="RUN", help="a replay or diagnosis output folder")
    p.add_argument("--format", required=True, choices=FORMATS, help="vtu (ParaView), sofa (Python3 scene) or mjcf (MuJoCo)")
    p.add_argument("--out", required=True, help="output folder (created; files of the same name are replaced)")
    p.add_argument("--sequence", action="append", default=None, metavar="NAME",
                   help="vtu: sequences to write (repeatable; default all); sofa/mjcf: the probe path to carry "
                        "(default the first test sequence)")
    p.add_argument("--stride", type=int, default=1, help="vtu: write every N-th frame (default 1)")
    p.add_argument("--youngs", type=float, default=None, help="override Young's modulus, Pa")
    p.add_argument("--poisson", type=float, default=None, help="override Poisson's ratio (a diagnosis: default 0.44)")
    p.add_argument("--grid", type=int, nargs=3, default=None, metavar=("NX", "NY", "NZ"),
                   help="node grid of a diagnosis's twin of a box (default 13 5 5; a replay keeps its own; "
                        "an STL phantom has its own mesh)")
    p.add_argument("--session", default=None, help="the session folder, if it moved since the run")
    p.set_defaults(func=cmd_export)
