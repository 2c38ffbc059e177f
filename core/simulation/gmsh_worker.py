"""Fill a watertight STL with tetrahedra using Gmsh, in a process of its own.

Run as ``python -m core.simulation.gmsh_worker STL ELEMENT_SIZE OUT.npz``; used by
:func:`core.simulation.meshing.tetrahedralise`, which checks the STL first and reads
``OUT.npz`` (``nodes`` (N, 3) float64 m, ``tets`` (E, 4) int64). Gmsh keeps global state,
installs signal handlers and can abort the process on a bad surface: in a child process
none of that touches the replay, the job service or its workers.

The recipe is Gmsh's own for remeshing an STL (tutorial t13, as the paper did with its
CAD surface, Wu et al. 2020, Sec. 4.2): classify the triangles into patches split at
sharp edges (40 degrees), rebuild a parametrised geometry from them, close it into a
volume and mesh it with the 3D Delaunay algorithm at the target element size, then
optimise the tetrahedra (Gmsh's and Netgen's optimisers). On failure the worker prints
Gmsh's last messages to stderr and exits with status 2.
"""

from __future__ import annotations

import math
import sys

import numpy as np


def mesh_stl(stl: str, element_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(nodes (N, 3) float64 m, tets (E, 4) int64 0-based) of the volume inside ``stl``.

    Raises:
        RuntimeError: Gmsh's error (the message holds its log's last lines)."""
    import gmsh  # noqa: PLC0415 (only the worker loads Gmsh)

    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.logger.start()
        try:
            gmsh.model.add("phantom")
            gmsh.merge(stl)
            gmsh.model.mesh.classifySurfaces(40.0 * math.pi / 180.0, True, True, math.pi)
            gmsh.model.mesh.createGeometry()
            surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
            if not surfaces:
                raise RuntimeError("no surface in the STL")
            loop = gmsh.model.geo.addSurfaceLoop(surfaces)
            gmsh.model.geo.addVolume([loop])
            gmsh.model.geo.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", element_size)
            gmsh.option.setNumber("Mesh.MeshSizeMin", 0.3 * element_size)
            gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 12)
            gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
            gmsh.option.setNumber("Mesh.Algorithm3D", 1)
            gmsh.option.setNumber("Mesh.Optimize", 1)
            gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)
            gmsh.model.mesh.generate(3)
            types, _, node_tags = gmsh.model.mesh.getElements(3)
            if 4 not in list(types):
                raise RuntimeError("Gmsh made no tetrahedra")
            conn = np.asarray(node_tags[list(types).index(4)], dtype=np.int64).reshape(-1, 4)
            tags, coords, _ = gmsh.model.mesh.getNodes()
        except Exception as exc:
            log = [m for m in gmsh.logger.get() if "Error" in m or "Warning" in m]
            raise RuntimeError(f"{exc}; " + " | ".join(log[-4:])) from exc
    finally:
        gmsh.finalize()
    tags = np.asarray(tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    used = np.unique(conn)
    lookup = np.full(int(max(tags.max(), used.max())) + 1, -1, dtype=np.int64)
    lookup[tags] = np.arange(tags.size)
    nodes = coords[lookup[used]]
    compact = np.full(lookup.size, -1, dtype=np.int64)
    compact[used] = np.arange(used.size)
    return nodes, compact[conn]


def main(argv: list[str]) -> int:
    stl, size, out = argv[0], float(argv[1]), argv[2]
    try:
        nodes, tets = mesh_stl(stl, size)
    except Exception as exc:  # the parent turns this into a MeshingError naming the STL
        print(str(exc), file=sys.stderr)
        return 2
    np.savez(out, nodes=nodes, tets=tets)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
