"""Export a twin as VTK unstructured grids (``.vtu``, written with meshio) for ParaView.

What is written into ``out``:

- ``rest.vtu``: the rest mesh (linear tetrahedra, phantom frame, m) with cell data
  ``youngs_modulus`` (Pa, per element: an inclusion's elements are stiffer) and point data
  ``fixed`` (1 on held nodes), ``node_mass`` (kg), ``support_stiffness`` (N/m) and
  ``static_displacement`` (m, the sag under the model's body forces; zero without gravity);
- per sequence with trajectories (a replay), ``<sequence>/frame_NNNNNN.vtu``: the mesh at
  that frame (points = the simulated node positions, m) with point data ``displacement``
  (m, from rest) and field data ``time`` (s), ``frame_error`` (m, the frame's mean
  cloud-to-mesh distance: the replay stores no per-vertex residual), ``probe_centre`` (m)
  and ``contact_force`` (N); and ``<sequence>.pvd``, the ParaView collection listing the
  frames with their times. Frames after a divergence (NaN positions) are left out.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

__all__ = ["write_vtu", "write_pvd"]


def _mesh(points: np.ndarray, tets: np.ndarray, **data):
    import meshio

    return meshio.Mesh(np.ascontiguousarray(points, dtype=np.float64),
                       [("tetra", np.ascontiguousarray(tets, dtype=np.int64))], **data)


def _field_xml(fields: dict[str, np.ndarray]) -> str:
    """A VTK ``<FieldData>`` block of ASCII float arrays (one tuple each), exact to the bit."""
    parts = ["<FieldData>"]
    for name, value in fields.items():
        v = np.asarray(value, dtype=np.float64).reshape(-1)
        text = " ".join(repr(float(x)) for x in v)
        parts.append(f'<DataArray type="Float64" Name="{name}" NumberOfTuples="1" '
                     f'NumberOfComponents="{v.size}" format="ascii">{text}</DataArray>')
    parts.append("</FieldData>")
    return "\n".join(parts)


def _write(path: Path, mesh, fields: dict | None = None) -> None:
    """meshio's VTU writer drops field data; add it as the grid's ``<FieldData>``, which
    ParaView and meshio's reader both read."""
    import meshio

    meshio.write(path, mesh, file_format="vtu")
    if fields:
        text = path.read_text()
        text = text.replace("<UnstructuredGrid>", "<UnstructuredGrid>\n" + _field_xml(fields), 1)
        path.write_text(text)


def write_pvd(path: Path, entries: list[tuple[float, str]]) -> Path:
    """Write a ParaView collection: ``entries`` of (time s, file relative to ``path``'s folder)."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, f in entries:
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0", file=f)
    ET.indent(root)
    path.write_text('<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n")
    return path


def write_vtu(twin, out, *, stride: int = 1) -> list[Path]:
    """Write ``rest.vtu`` and, for every sequence with trajectories, its frames and ``.pvd``.

    Args:
        twin: an :class:`app.export.run.Twin`.
        out: folder (created).
        stride: write every ``stride``-th frame (1: all).

    Returns:
        The files written (rest.vtu, then per sequence its .pvd; frames not listed).

    Raises:
        TissueTwinError: stride < 1; SimulationError: the twin collapses under its own weight.
    """
    from core.errors import TissueTwinError

    if int(stride) < 1:
        raise TissueTwinError(f"stride must be >= 1, got {stride}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = twin.mesh
    rest = np.asarray(mesh.nodes, dtype=np.float64)
    static = twin.static_positions()
    written = [out / "rest.vtu"]
    _write(written[0], _mesh(
        rest, mesh.tets,
        point_data={"fixed": twin.fixed.astype(np.int32), "node_mass": twin.node_mass,
                    "support_stiffness": twin.support_stiffness, "static_displacement": static - rest},
        cell_data={"youngs_modulus": [np.asarray(twin.element_youngs, dtype=np.float64)]},
    ), {"youngs_modulus_bulk": [twin.youngs_modulus], "poisson_ratio": [twin.poisson_ratio],
        "density": [twin.density], "gravity": twin.gravity})
    for name, seq in twin.sequences.items():
        if seq.positions is None:
            continue
        folder = out / name
        folder.mkdir(exist_ok=True)
        for old in folder.glob("frame_*.vtu"):  # a previous export's frames
            old.unlink()
        entries = []
        for f in range(0, seq.times.size, int(stride)):
            x = seq.positions[f]
            if not np.all(np.isfinite(x)):
                continue
            fname = f"frame_{f:06d}.vtu"
            fields = {"time": [seq.times[f]], "probe_centre": seq.probe_centres[f]}
            if seq.frame_errors is not None:
                fields["frame_error"] = [seq.frame_errors[f]]
            if seq.contact_force is not None:
                fields["contact_force"] = seq.contact_force[f]
            _write(folder / fname, _mesh(x, mesh.tets, point_data={"displacement": x - rest}), fields)
            entries.append((float(seq.times[f]), f"{name}/{fname}"))
        written.append(write_pvd(out / f"{name}.pvd", entries))
    return written
