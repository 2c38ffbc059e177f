"""Young's modulus you can compare with a rheometer: its model-form range.

With force data, the force at a given dent is proportional to E in every model here
(every stiffness, the contact's included, scales with it), so E follows from the force
once the rest of the model is fixed. But the rest is not known: the phantom's material
law, its Poisson's ratio and the discretisation of whatever produced the data. Measured on
randomised-lab sessions (13x5x5 / 19x7x7 / 25x9x9, corotational / neo-Hookean / Yeoh,
nu 0.42-0.48), the E that a least-squares force fit returns moves by 25-35 % with the law,
by 15-25 % with each refinement of the grid and by 10-20 % with Poisson's ratio; linear
tetrahedra at nu ~ 0.44 lock, and a Richardson extrapolation over the 13x5x5, 19x7x7 and
25x9x9 grids does not converge (the successive differences shrink slower than any power of
the element size), so a mesh-converged E is out of reach of these grids.

:func:`youngs_model_form` therefore refits E to the measured force under each variant of
:data:`VARIANTS` (three laws, the ends of the plausible Poisson's ratio range) on the
coarse grid and, through the reference model's ratio of its fine to its coarse E, on the
fine grid,
by least squares along the force: the variant replayed at the model's E gives a force
``f``, and ``E f.m / f.f`` (noise-weighted, ``m`` the measured force) is its E, the
causes that set a scale of their own (gravity, a foundation) understood as scaled with
it, so that the shape stays the fitted one. The range of these is reported. The range is stated, not tuned: a phantom stiffer in its law than
a Yeoh solid with k = 2, or with nu outside 0.42-0.48, can fall outside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.identification.execution import Executor, SerialExecutor
from core.preparation import PreparedSession
from core.simulation import SimulationConfig

__all__ = ["ModelFormVariant", "VARIANTS", "REFERENCE", "youngs_model_form", "force_youngs", "variant_element_sizes"]


@dataclass(frozen=True)
class ModelFormVariant:
    """A model the force is refitted with: grid (nodes per axis), law, Poisson's ratio and
    the Yeoh stiffening of ``stable_yeoh``."""

    grid: tuple[int, int, int]
    law: str
    poisson_ratio: float
    stiffening: float = 0.0

    @property
    def label(self) -> str:
        law = self.law if self.law != "stable_yeoh" else f"yeoh k={self.stiffening:g}"
        return f"{law}, nu {self.poisson_ratio:g}, {'x'.join(str(v) for v in self.grid)}"


COARSE, FINE = (13, 5, 5), (25, 9, 9)
"""The grids of the variants: every variant on the coarse grid, and the reference on both,
whose ratio carries every variant to the fine grid (one fine replay per sequence instead
of one per variant; the ratio is that of the reference law and nu)."""

REFERENCE = ModelFormVariant(COARSE, "corotational", 0.44)

VARIANTS: tuple[ModelFormVariant, ...] = tuple(
    [ModelFormVariant(COARSE, law, nu) for law in ("corotational", "stable_neo_hookean") for nu in (0.42, 0.48)]
    + [ModelFormVariant(COARSE, "stable_yeoh", 0.44, k) for k in (1.0, 2.0)])
"""The model-form variants of the modulus on the coarse grid (see the module docstring)."""

def _variant_mesh(prepared: PreparedSession, v: ModelFormVariant, element_size: float | None):
    """The mesh a variant is replayed on: the box grid ``v.grid`` of the session's size, or
    for a phantom given by ``phantom.stl`` its own mesh at ``element_size`` (m)."""
    from core.simulation import box_mesh
    from core.simulation.meshing import phantom_mesh

    if prepared.stl_path is None:
        return box_mesh(prepared.size, v.grid)
    return phantom_mesh(prepared.size, prepared.stl_path, grid=v.grid, element_size=element_size)


def _force_trial(prepared: PreparedSession, name: str, effects, E: float, v: ModelFormVariant, dt: float,
                 element_size: float | None = None):
    from core.simulation import Material, build_model, effect_from_dict, simulate

    seq = prepared.sequences[name]
    model = build_model(_variant_mesh(prepared, v, element_size), prepared.mass,
                        Material(E, v.poisson_ratio, v.law, stiffening=v.stiffening), SimulationConfig(dt=dt),
                        [effect_from_dict(dict(e)) for e in effects])
    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times)
    return sim.contact_force if sim.ok else None


def _run(prepared: PreparedSession, item) -> np.ndarray | None:
    name, effects, E, v, dt, h = item
    return _force_trial(prepared, name, effects, E, v, dt, h)


def variant_element_sizes(prepared: PreparedSession, element_size: float | None) -> dict | None:
    """{COARSE: h, FINE: h_fine} (m) of a phantom given by ``phantom.stl``: the replay's
    element size (None: the mesher's default) and half the mean edge of that mesh, as the
    diagnosis's fine reference and the E fit's refinement take it; None for the box, whose
    variants are the grids :data:`COARSE` and :data:`FINE`."""
    if prepared.stl_path is None:
        return None
    from core.simulation.meshing import refined_element_size
    from core.simulation.replay import replay_mesh

    return {COARSE: element_size, FINE: refined_element_size(replay_mesh(prepared, COARSE, element_size), element_size)}


def _label(v: ModelFormVariant, sizes: dict | None, mesh: tuple[int, int, int] | None = None) -> str:
    """A variant's label; on a phantom's own mesh its element size instead of the grid
    (the coarse one "the replay's mesh" when the mesher chose it)."""
    grid = mesh or v.grid
    if sizes is None:
        return ModelFormVariant(grid, v.law, v.poisson_ratio, v.stiffening).label
    law = v.law if v.law != "stable_yeoh" else f"yeoh k={v.stiffening:g}"
    h = sizes[grid]
    return f"{law}, nu {v.poisson_ratio:g}, " + ("the replay's mesh" if h is None else f"elements {1e3 * h:.1f} mm")


def youngs_model_form(prepared: PreparedSession, effects: Sequence[dict], youngs_modulus: float, *,
                      names: Sequence[str] | None = None, executor: Executor | None = None,
                      variants: Sequence[ModelFormVariant] = VARIANTS,
                      dt: float = 1.0 / 60.0, element_size: float | None = None) -> dict:
    """E refitted to the measured force under each model-form variant.

    Args:
        prepared: the session (its ``names`` sequences need force columns).
        effects: the model's effect dicts (SESSION_FORMAT.md) at ``youngs_modulus``.
        youngs_modulus: the model's E, Pa. names: sequences (default: the train ones).
        dt: the variants' time step, s.
        element_size: the replay's element size (m) of a phantom given by ``phantom.stl``
            (None: the mesher's default): its variants run on its own mesh at this size
            and, for the fine one, at half its mean edge (:func:`variant_element_sizes`);
            the box's on the grids.

    Returns:
        ``{"variants": [{"model": label, "youngs_modulus": Pa or None}], "low": Pa,
        "high": Pa, "fine_over_coarse": the reference's ratio}`` (a variant whose replay
        diverged gets None and is left out).
    """
    executor = executor or SerialExecutor()
    names = _force_names(prepared, names)
    sigma = _force_sigma(prepared, names)
    fine_ref = ModelFormVariant(FINE, REFERENCE.law, REFERENCE.poisson_ratio)
    runs = [REFERENCE, fine_ref, *variants]
    sizes = variant_element_sizes(prepared, element_size)
    items = [(n, tuple(effects), float(youngs_modulus), v, dt, None if sizes is None else sizes[v.grid])
             for v in runs for n in names]
    forces = executor.map(_run, prepared, items)
    fitted = [_least_squares_youngs(prepared, names, forces[i * len(names):(i + 1) * len(names)], youngs_modulus, sigma)
              for i in range(len(runs))]
    ref, ref_fine = fitted[0], fitted[1]
    ratio = ref_fine / ref if ref and ref_fine else None
    out = [{"model": _label(REFERENCE, sizes), "youngs_modulus": ref},
           {"model": _label(fine_ref, sizes), "youngs_modulus": ref_fine}]
    for v, E_v in zip(variants, fitted[2:]):
        out.append({"model": _label(v, sizes), "youngs_modulus": E_v})
        if ratio is not None and v.grid == COARSE:
            out.append({"model": _label(v, sizes, FINE) + " (the reference's fine/coarse ratio)",
                        "youngs_modulus": None if E_v is None else E_v * ratio})
    vals = [o["youngs_modulus"] for o in out if o["youngs_modulus"] is not None]
    return {"variants": out, "low": min(vals) if vals else None, "high": max(vals) if vals else None,
            "fine_over_coarse": ratio}


def force_youngs(prepared: PreparedSession, models: Sequence[Sequence[dict]], youngs_modulus: float, *,
                 names: Sequence[str] | None = None, executor: Executor | None = None,
                 variant: ModelFormVariant = REFERENCE, dt: float = 1.0 / 60.0,
                 element_size: float | None = None) -> list[float | None]:
    """E refitted to the measured force for each of several models under one variant, by the
    least squares of :func:`youngs_model_form` (one replay per model and sequence: the
    force scales with E, the causes that set a scale of their own understood as scaled with it).

    Smooth in the models' parameters wherever their force is, which the joint fit of E to
    force and residual field is not on a coarse mesh where the replay jumps between two
    equilibria (a compliant base's press on 13x5x5: see
    :mod:`core.simulation.contact`).

    Args:
        prepared: the session (its ``names`` sequences need force columns).
        models: lists of effect dicts (SESSION_FORMAT.md), each replayed at ``youngs_modulus`` (Pa).
        names: sequences (default: the train ones). variant: the law, Poisson's ratio and
            grid (default: the replay's). dt: time step, s. element_size: as
            :func:`youngs_model_form`'s.

    Returns:
        One E (Pa) per model, None where a replay diverged or the force gave no scale.
    """
    executor = executor or SerialExecutor()
    names = _force_names(prepared, names)
    sigma = _force_sigma(prepared, names)
    sizes = variant_element_sizes(prepared, element_size)
    h = None if sizes is None else sizes[variant.grid]
    items = [(n, tuple(effects), float(youngs_modulus), variant, dt, h) for effects in models for n in names]
    forces = executor.map(_run, prepared, items)
    k = len(names)
    return [_least_squares_youngs(prepared, names, forces[i * k:(i + 1) * k], youngs_modulus, sigma)
            for i in range(len(models))]


def _force_names(prepared: PreparedSession, names: Sequence[str] | None) -> list[str]:
    return list(names) if names is not None else [n for n, s in prepared.sequences.items() if s.role == "train"]


def _force_sigma(prepared: PreparedSession, names: Sequence[str]) -> np.ndarray:
    """(3,) N: the force's noise per axis from the rest frames of ``names`` (ones when fewer than 10)."""
    rest = [prepared.sequences[m].force_at(prepared.sequences[m].frame_times)[prepared.rest_frames(m)] for m in names
            if prepared.sequences[m].force is not None]
    rest = np.concatenate(rest) if rest else np.zeros((0, 3))
    return np.maximum(np.sqrt(np.mean(rest**2, axis=0)), 1e-3) if rest.shape[0] >= 10 else np.ones(3)


def _least_squares_youngs(prepared: PreparedSession, names: Sequence[str], forces, youngs_modulus: float,
                          sigma: np.ndarray) -> float | None:
    """``E f.m / f.f`` (noise-weighted) over the sequences ``names`` from the replayed forces
    ``f`` (one (F, 3) array or None per sequence) at ``youngs_modulus`` and the measured ``m``."""
    num = den = 0.0
    for n, f in zip(names, forces):
        seq = prepared.sequences[n]
        if f is None or seq.force is None:
            return None
        fm = seq.force_at(seq.frame_times)  # the replay's force is on the robot's clock
        num += float(np.sum(f * fm / sigma**2))
        den += float(np.sum(f * f / sigma**2))
    return float(youngs_modulus) * num / den if den > 0 and num > 0 else None
