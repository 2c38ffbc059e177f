"""What a Dask worker runs for the diagnosis: one replay of a model variant, measured as a field.

A :class:`FieldTrial` is one replay (a trial, the field layout and optionally the
:class:`Directions` to differentiate it along); :func:`run_field` replays it on a fresh
model and returns its :class:`FieldRun`: the residual field of :mod:`core.diagnosis.fields`,
the probe force and, with directions, their derivatives (:mod:`core.simulation.sensitivity`).
Each worker process keeps the binned points of the sequences it replays
(:func:`drop_binned_points` empties them). This is apart from
:class:`core.diagnosis.evidence.Evidence`, which plans the trials, caches their runs and
weighs them on the driver: what is here is what the workers execute, and it holds no
driver state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from core.diagnosis.caching import LruCache
from core.diagnosis.fields import FieldLayout, frame_bins, residual_field, residual_field_tangent
from core.identification.trials import Trial
from core.simulation import SimulationConfig
from core.preparation import PreparedSession, release_pages
from core.simulation.fem import inverted_elements
from core.simulation.replay import build_replay_model, frame_errors, replay_mesh
from core.simulation.effects import FitSpace
from core.simulation.sensitivity import simulate_sensitivities
from core.simulation.solver import simulate

__all__ = ["Directions", "FieldTrial", "FieldRun", "run_field", "drop_binned_points"]


@dataclass(frozen=True)
class Directions:
    """The parameters a field run is differentiated along: a candidate's fit variables
    (at ``x``) and, with ``fit_youngs``, log10 of Young's modulus as the last one.

    Attributes:
        fixed: effect dicts of the model besides the candidate.
        space: the candidate's fit space (None: E alone).
        x: (n,) the candidate's fit variables.
        youngs_modulus: E of the model, Pa (the start of log10 E when fitted).
        fit_youngs: differentiate along log10 E too.
    """

    fixed: tuple
    space: FitSpace | None
    x: np.ndarray
    youngs_modulus: float
    fit_youngs: bool = False
    simulation: tuple = ()
    """``SimulationConfig`` fields changed from the run's default (as :class:`core.diagnosis.evidence.Spec`'s)."""
    law: str | None = None
    """Material law (None: the configured one), as :class:`core.diagnosis.evidence.Spec`'s; so are the next two."""
    poisson_ratio: float | None = None
    stiffening: float = 0.0

    @property
    def theta(self) -> np.ndarray:
        """(p,) the parameters: x, then log10 E when fitted."""
        tail = [math.log10(self.youngs_modulus)] if self.fit_youngs else []
        return np.concatenate([np.asarray(self.x, dtype=np.float64).reshape(-1), tail])

    @property
    def scales(self) -> np.ndarray:
        """(p,) each parameter's scale (the fit's steps; log10 E: :data:`E_SCALE`)."""
        head = self.space.steps if self.space is not None else np.zeros(0)
        return np.concatenate([head, [E_SCALE] if self.fit_youngs else []])

    def effects(self, theta: np.ndarray) -> tuple:
        n = 0 if self.space is None else len(self.space.names)
        cand = () if self.space is None else (self.space.to_effect(np.asarray(theta[:n])),)
        return tuple(self.fixed) + cand

    def youngs(self, theta: np.ndarray) -> float:
        return float(10.0 ** theta[-1]) if self.fit_youngs else float(self.youngs_modulus)


E_SCALE = 0.02
"""Scale of log10 E in the sensitivities (their model differences take 1e-4 of it)."""


@dataclass(frozen=True)
class FieldTrial:
    """One replay for the diagnosis: a trial, the field layout, whether to compute the
    paper's point-to-mesh error too (slower: a KD-tree per frame), and optionally the
    directions to differentiate the run along (:mod:`core.simulation.sensitivity`; the
    trial's effects and E are then those of the directions at their ``theta``)."""

    trial: Trial
    layout: FieldLayout
    paper_error: bool = False
    directions: Directions | None = None
    count_inverted: bool = False
    """Count the replayed mesh's inverted elements (:attr:`FieldRun.inverted`)."""


@dataclass(frozen=True)
class FieldRun:
    """Evidence of one :class:`FieldTrial`.

    Attributes:
        sequence: name. ok: the simulation did not diverge.
        field: (F, B) float64 mean signed normal residual per bin and frame, m.
        ss, dof: per face of ``fields.FACES``, within-bin sums of squares (5,) m^2 and
            their degrees of freedom (5,).
        frame_sums: (F,) sum of point-to-mesh distances per frame, m, or None.
        frame_counts: (F,) measured points per frame.
        probe_centres: (F, 3) probe sphere centres at frame times, m, phantom frame.
        force: (F, 3) simulated force of the probe on the phantom at the robot's samples
            of the frame times (:class:`core.simulation.SimulationResult`), N, phantom
            frame: it compares with the measured rows at the frame times.
        youngs_modulus: E of the replay, Pa.
        clock_offset: the replay's ``time_offset`` effect, s (0 without one): the robot's
            clock, which stamps kinematics and force alike, runs this far ahead of the
            camera's.
    """

    sequence: str
    ok: bool
    field: np.ndarray
    ss: np.ndarray
    dof: np.ndarray
    frame_sums: np.ndarray | None
    frame_counts: np.ndarray
    probe_centres: np.ndarray
    force: np.ndarray
    youngs_modulus: float
    clock_offset: float = 0.0
    inverted: int | None = None
    """The most tetrahedra of the replayed mesh inverted at once (:func:`inverted_elements`)
    where the trial asked for it (``FieldTrial.count_inverted``: the base model's runs on the
    replay's own mesh, whose inversion the diagnosis reports), else None: counting every run
    took 2.8 s of a 60 s diagnosis."""
    jac_field: np.ndarray | None = None
    """(p, F, B) d field / d theta along the trial's directions (None without them), m per unit."""
    jac_force: np.ndarray | None = None
    """(p, F, 3) d force / d theta, N per unit."""
    d_youngs: np.ndarray | None = None
    """(p,) d E / d theta, Pa per unit."""
    d_offset: np.ndarray | None = None
    """(p,) d clock_offset / d theta, s per unit."""


BINS_CACHE_BYTES = 1 << 30
"""Most bytes of binned points a process keeps (:func:`_binned`): a paper-size sequence's
indices and bins are ~0.16 GB by its point count (:func:`fields.frame_bins`), a 12 s
one's a few MB."""


def _bins_bytes(hit) -> int:
    """Bytes of a :func:`_binned` entry ``(clouds, (points, bins, counts))`` (the clouds are the caller's)."""
    pts, idx, counts = hit[1]
    return int(pts.nbytes + idx.nbytes + counts.nbytes)


_BINS = LruCache(BINS_CACHE_BYTES, _bins_bytes, max_items=16)


def drop_binned_points() -> None:
    """Empty this process's cache of binned points (:func:`_binned`): the diagnosis calls
    it on every worker (:meth:`core.identification.execution.Executor.run_everywhere`)
    before its test stage, which bins only the test sequences (a paper-size diagnosis's
    workers held ~0.9 GiB of train and validation bins through it)."""
    _BINS.clear()


def _binned(prepared: PreparedSession, name: str, layout: FieldLayout):
    """:func:`frame_bins` of a sequence's clouds, computed once per worker process (at most
    16 sequences and :data:`BINS_CACHE_BYTES` kept)."""
    clouds = prepared.sequences[name].clouds
    key = (str(prepared.path), id(clouds), name, layout)
    hit = _BINS.get_recent(key)
    # the entry holds the clouds themselves: an id is reused once its object is freed (the
    # planner's virtual sequences share names and come and go)
    if hit is None or hit[0] is not clouds:
        hit = (clouds, frame_bins(clouds, layout))
        _BINS.put(key, hit)
    return hit[1]


def _clock_offset(effects) -> float:
    return sum(float(e["offset"]) for e in effects if e["kind"] == "time_offset")


def _inverted(mesh, positions: np.ndarray) -> int:
    """The most elements of the replayed ``mesh`` inverted at once over ``positions``."""
    counts = inverted_elements(mesh.nodes, mesh.tets, positions)
    return int(counts.max()) if counts.size else 0


def run_field(prepared: PreparedSession, item: FieldTrial) -> FieldRun:
    """Replay ``item.trial`` (a fresh model) and measure its residual field (worker
    function); with ``item.directions``, differentiate it along them too."""
    t = item.trial
    seq = prepared.sequences[t.sequence]
    jac = None
    default_dt = SimulationConfig().dt
    for _ in range(2):
        if item.directions is None:
            model = build_replay_model(prepared, t.replay_config())
            sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times)
        else:
            d = item.directions
            theta, scales = d.theta, d.scales

            def build(th, factorize, t=t):
                tr = replace(t, effects=d.effects(th), youngs_modulus=d.youngs(th))
                return build_replay_model(prepared, tr.replay_config(), factorize=factorize)

            sens = simulate_sensitivities(build, theta, seq.probe, prepared.probe_radius, seq.frame_times, scales=scales)
            sim = sens.result
        if sim.ok or t.simulation.dt <= default_dt:
            break
        # the coarse runs' longer step (``coarse_dt``) can lose stability where the replay's
        # own step does not (measured: a dome's 1003-node mesh pressed near its apex
        # diverged at 1/60 s and replayed at 1/80 s): such a run is repeated at the default
        # step, as the replay itself would run it, rather than reported as a divergence
        t = replace(t, simulation=replace(t.simulation, dt=default_dt))
    if item.directions is not None:
        h = 1e-4 * np.where(scales > 0, scales, 1.0)
        d_E = np.array([(d.youngs(theta + hj * e) - d.youngs(theta - hj * e)) / (2 * hj)
                        for hj, e in zip(h, np.eye(theta.size))])
        d_off = np.array([(_clock_offset(d.effects(theta + hj * e)) - _clock_offset(d.effects(theta - hj * e))) / (2 * hj)
                          for hj, e in zip(h, np.eye(theta.size))])
        jac = (sens.positions, sens.contact_force, d_E, d_off)
    pts, bins, counts = _binned(prepared, t.sequence, item.layout)
    # the mesh the fields are measured on: the box's grid, or any phantom's replayed mesh
    shape = item.layout.measured_on(prepared, t.grid, t.element_size)
    fld, ss, dof = residual_field(sim.positions, shape, item.layout, pts, bins, counts)
    n = np.array([c.shape[0] for c in seq.clouds], dtype=np.int64)
    sums = None
    if item.paper_error:
        means, _ = frame_errors(sim.positions, shape, seq.clouds, distances=False)
        sums = means * n  # NaN where the frame diverged
    run = FieldRun(t.sequence, bool(sim.ok), fld, ss, dof, sums, n, np.asarray(sim.probe_centres),
                   np.asarray(sim.contact_force, dtype=np.float64), float(t.youngs_modulus), _clock_offset(t.effects),
                   inverted=(_inverted(model.mesh if item.directions is None else replay_mesh(prepared, t.grid, t.element_size),
                                       sim.positions) if item.count_inverted else None))
    if jac is not None:
        dpos, dforce, d_E, d_off = jac
        dfield = residual_field_tangent(sim.positions, dpos, shape, item.layout, pts, bins, counts)
        run = replace(run, jac_field=dfield, jac_force=np.asarray(dforce, dtype=np.float64), d_youngs=d_E,
                      d_offset=d_off)
    release_pages(seq.clouds)  # done with this sequence's clouds (mapped ones leave the resident set)
    return run
