"""Export the calibrated twin of a replay or diagnosis (issue 19, item 5).

``export_run(RUN, fmt, OUT)`` reads RUN (:func:`app.export.run.load_run`) and writes
one of :data:`FORMATS`:

- ``vtu``: VTK unstructured grids for ParaView (:mod:`app.export.vtu`);
- ``sofa``: a SOFA Python3 scene (:mod:`app.export.sofa`);
- ``mjcf``: a MuJoCo model with a 3D flex (:mod:`app.export.mjcf`).

Every export also writes ``twin.json``, the twin's parameters (:meth:`Twin.describe`).
meshio and mujoco are imported by the writers only: ``core`` never imports them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from app.export.run import Trajectory, Twin, build_twin, load_run
from core.errors import TissueTwinError

__all__ = ["FORMATS", "ExportResult", "Trajectory", "Twin", "build_twin", "export_run", "export_twin", "load_run"]

FORMATS = ("vtu", "sofa", "mjcf")


@dataclass(frozen=True)
class ExportResult:
    """What an export wrote: ``files`` (paths, twin.json last), the ``twin``, and its ``notes``
    (what the format cannot represent)."""

    files: list
    twin: Twin

    @property
    def notes(self) -> tuple:
        return self.twin.notes


def export_twin(twin: Twin, fmt: str, out, *, sequence: str | None = None, stride: int = 1) -> ExportResult:
    """Write ``twin`` as ``fmt`` into the folder ``out`` (created).

    Args:
        sequence: the sequence whose probe path a sofa or mjcf export carries (default:
            the first test sequence); vtu writes every sequence of the twin.
        stride: vtu only, write every ``stride``-th frame.

    Raises:
        TissueTwinError: an unknown format or sequence.
    """
    if fmt not in FORMATS:
        raise TissueTwinError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    out = Path(out)
    if fmt == "vtu":
        from app.export.vtu import write_vtu

        if sequence is not None and sequence not in twin.sequences:
            raise TissueTwinError(f"no sequence {sequence!r} in {twin.source}; it has {list(twin.sequences)}")
        files = write_vtu(twin, out, stride=stride)
    elif fmt == "sofa":
        from app.export.sofa import write_sofa

        files = write_sofa(twin, out, sequence=sequence)
    else:
        from app.export.mjcf import write_mjcf

        files = write_mjcf(twin, out, sequence=sequence)
    meta = out / "twin.json"
    meta.write_text(json.dumps({**twin.describe(), "export": {"format": fmt, "files": [str(f.relative_to(out)) for f in files]}},
                               indent=2))
    return ExportResult(files=[*files, meta], twin=twin)


def export_run(run, fmt: str, out, *, sequences=None, sequence: str | None = None, stride: int = 1,
               youngs: float | None = None, poisson: float | None = None, grid=None, session=None) -> ExportResult:
    """Read RUN (a replay or diagnosis folder) and write its calibrated twin as ``fmt``.

    Args:
        run: the folder (see :func:`app.export.run.load_run`).
        fmt: one of :data:`FORMATS`.
        out: the output folder (created; files of the same name are replaced).
        sequences: names to keep (vtu: the sequences written; default all).
        sequence: the probe path of a sofa or mjcf export (default: the first test sequence).
        stride, youngs, poisson, grid, session: see :func:`export_twin` and :func:`load_run`.

    Raises:
        TissueTwinError: an unknown format, or bad input (the file is named).
    """
    if fmt not in FORMATS:
        raise TissueTwinError(f"unknown export format {fmt!r}; expected one of {', '.join(FORMATS)}")
    twin = load_run(run, youngs=youngs, poisson=poisson, grid=grid, session=session, sequences=sequences)
    return export_twin(twin, fmt, out, sequence=sequence, stride=stride)
