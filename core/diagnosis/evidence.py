"""Evidence of the diagnosis: replays of model variants, their residual fields and forces.

A :class:`Spec` names a model (effects, Young's modulus, model-form variants); an
:class:`Evidence` runs it on the sequences of a role through an executor (serially or on
Dask), caches the runs, and turns them into weighted residual vectors whose squared norm
is a chi-square: the field of :mod:`core.diagnosis.fields` weighted by its bin counts over
the point noise, and with force data the probe force residual in units of the force noise
measured on rest frames. Coarse-grid runs are shifted onto the fine grid's by the base
model's discrepancy (multi-fidelity, an additive model-discrepancy correction in the
spirit of Kennedy & O'Hagan 2001).

What a worker runs for one trial (and its cache of binned points) is
:mod:`core.diagnosis.trials`.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, fields as dataclass_fields, replace
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from core.diagnosis.caching import LruCache
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.fields import FieldLayout, frame_bins
from core.diagnosis.trials import Directions, FieldRun, FieldTrial, run_field
from core.errors import TissueTwinError
from core.identification.execution import Executor
from core.identification.trials import Trial
from core.simulation import SimulationConfig
from core.preparation import PreparedSession, release_pages
from core.simulation.meshing import refined_element_size
from core.simulation.replay import replay_mesh

__all__ = ["Spec", "Request", "Evidence", "Discrepancy"]

Discrepancy = Mapping[str, np.ndarray]
"""``{sequence: (F, B) fine - coarse residual field}`` of one model (:meth:`Evidence.discrepancy_at`)."""


RUNS_CACHE_BYTES = 1 << 29
"""Most bytes of field runs an :class:`Evidence` keeps (:class:`LruCache`): a paper-size
diagnosis made ~3700 runs whose fields and derivatives, all kept, held ~3 GB; with 1 GiB
the main process's anonymous memory still grew by ~1 GB through the first round (a
profile of that run). At 512 MiB the same diagnosis replays 96 dropped runs again (3828
simulations instead of 3732) and answers identically."""


def _run_bytes(run: "FieldRun") -> int:
    return int(sum(v.nbytes for f in dataclass_fields(run) if isinstance(v := getattr(run, f.name), np.ndarray)))


class Request(NamedTuple):
    """A request of :meth:`Evidence.runs_together`: ``models`` (:class:`Spec` or effect
    dicts; with ``jacobian``, :class:`Directions`) on every sequence of ``role``, with the
    paper's per-frame error when ``paper``, on the fine grid when ``fine``, on ``grid`` (a
    box phantom's (nx, ny, nz)) when given; a ``phantom.stl`` phantom's mesh at
    ``element_size`` (m) when given (``grid`` then only names the mesh in the cache)."""

    models: Sequence
    role: str
    paper: bool = False
    fine: bool = False
    jacobian: bool = False
    grid: tuple | None = None
    element_size: float | None = None


@dataclass(frozen=True)
class Spec:
    """A model of the diagnosis: effect dicts (SESSION_FORMAT.md) and Young's modulus (Pa)."""

    effects: tuple
    youngs_modulus: float
    law: str | None = None
    """Material law (None: the configured one); a model-form variant of :mod:`core.diagnosis.nuisance`."""
    poisson_ratio: float | None = None
    """Poisson's ratio (None: the configured one)."""
    stiffening: float = 0.0
    """The Yeoh coefficient of ``law`` "stable_yeoh"."""
    simulation: tuple = ()
    """``SimulationConfig`` fields changed from the run's default, as (name, value) pairs."""


class Evidence:
    """Runs field trials through an executor and caches them by (effects, sequence, E, grid);
    holds the weights of the evidence: bin counts per face noise, and with force data
    the measured force and its noise.

    Residual vectors (:meth:`vector`) hold, sequence after sequence of a role, the field
    ``sqrt(n) r`` over frames and bins (frame-major), then with force data the force
    residual times ``sqrt(sigma2)`` in units of the force noise, over frames and axes:
    ``v @ v / sigma2`` is the chi-square of a run. :meth:`frames` gives each entry's
    frame and :meth:`blocks` its block of frames for the bootstrap."""

    def __init__(self, prepared: PreparedSession, cfg: DiagnosisConfig, executor: Executor, layout: FieldLayout):
        self.prepared, self.cfg, self.executor, self.layout = prepared, cfg, executor, layout
        self.cache = LruCache(RUNS_CACHE_BYTES, _run_bytes)
        self._lock = threading.Lock()
        """Guards the cache and the counters: :meth:`runs_together` may be called from
        several threads at once (independent fits side by side on a concurrent executor)."""
        self.delta: dict[str, np.ndarray] = {}
        self.force_delta: dict[str, np.ndarray] = {}
        self.force_ratio: dict[str, float] = {}
        self.simulations = 0
        self.repeated = 0
        """Simulations of runs the cache had made and dropped (its limits cost this many)."""
        self.indentation: dict[str, np.ndarray] = {}
        """Per sequence: the nominal probe's depth into the rest phantom at each frame, m
        (filled on first use; a curved shape's depth costs a proximity query)."""
        self.names = {role: [n for n, s in prepared.sequences.items() if s.role == role] for role in ("train", "validation", "test")}
        self.counts, self.raw_counts = {}, {}
        centres = layout.centres3()
        for n, s in prepared.sequences.items():
            counts = frame_bins(s.clouds, layout)[2]
            release_pages(s.clouds)  # this process needs only the counts (workers read the points)
            self.raw_counts[n] = counts
            c = s.probe.at(s.frame_times)
            dist = np.linalg.norm(centres[None, :, :] - c[:, None, :], axis=2)
            if cfg.probe_exclusion > 0:
                counts = np.where(dist < cfg.probe_exclusion, 0, counts)
            if cfg.side_probe_exclusion > 0:
                side = layout.face_of_bin() > 0
                counts = np.where(side[None, :] & (dist < prepared.probe_radius + cfg.side_probe_exclusion), 0, counts)
            self.counts[n] = counts.astype(np.float64)
        self.force, self.force_sigma, self.force_note = _force_evidence(prepared, cfg.use_force)
        self.fine_element_size = None
        if prepared.stl_path is not None:
            coarse = replay_mesh(prepared, cfg.grid, cfg.element_size)
            self.fine_element_size = refined_element_size(coarse, cfg.element_size)
        self.sigma2 = 1.0  # the top face's point noise variance, m^2 (set by weigh_faces)

    @property
    def use_force(self) -> bool:
        return self.force is not None

    def weigh_faces(self, face_sigma2: np.ndarray, sigma2: float) -> None:
        """Scale each bin's point count by ``sigma2 / face_sigma2`` of its face, so that
        ``n r^2 / sigma2`` is chi2 on every face (a face without noise estimate gets 0)."""
        face_of = self.layout.face_of_bin()
        ratio = np.where(face_sigma2 > 0, sigma2 / np.where(face_sigma2 > 0, face_sigma2, 1.0), 0.0)[face_of]
        for n in self.counts:
            self.counts[n] = self.counts[n] * ratio[None, :]
            self.raw_counts[n] = self.raw_counts[n] * ratio[None, :]
        self.sigma2 = float(sigma2)

    def spec(self, effects: Sequence[dict] = (), E: float | None = None, simulation: tuple = ()) -> Spec:
        return Spec(tuple(effects), float(E or self.cfg.youngs_modulus), simulation=tuple(simulation))

    def trial(self, seq: str, spec: Spec, grid, element_size: float | None = None) -> Trial:
        """The :class:`~core.identification.trials.Trial` of ``spec`` on sequence ``seq``
        and the box ``grid``; a ``phantom.stl`` phantom's mesh at ``element_size`` (m) when
        given, else at the fine reference's size on the fine grid and the replay's on
        the others."""
        c = self.cfg
        coarse = c.fine_grid is not None and tuple(grid) != tuple(c.fine_grid)
        sim = SimulationConfig(dt=c.coarse_dt) if coarse and c.coarse_dt else SimulationConfig()
        if spec.simulation:
            sim = replace(sim, **dict(spec.simulation))
        if element_size is None:
            element_size = c.element_size
            if self.prepared.stl_path is not None and c.fine_grid is not None \
                    and tuple(grid) == tuple(c.fine_grid):
                element_size = self.fine_element_size  # any phantom: the fine mesh halves the element size
        return Trial(sequence=seq, youngs_modulus=spec.youngs_modulus, poisson_ratio=spec.poisson_ratio or c.poisson_ratio,
                     grid=tuple(grid), law=spec.law or c.law, effects=spec.effects, simulation=sim, stiffening=spec.stiffening,
                     element_size=element_size)

    @staticmethod
    def _key(spec: Spec, seq, paper, grid):
        return (repr(tuple(sorted(repr(sorted(e.items())) for e in spec.effects))), seq, spec.youngs_modulus, paper, grid,
                spec.law, spec.poisson_ratio, spec.stiffening, spec.simulation)

    def runs(self, models: Sequence[Spec | Sequence[dict]], role: str, *, paper: bool = False,
             fine: bool = False) -> list[list[FieldRun]]:
        """Field runs of every model (a :class:`Spec`, or effect dicts at the configured
        E) on every sequence of ``role`` (on the fine grid when ``fine`` and one is configured)."""
        return self.runs_together([Request(models, role, paper=paper, fine=fine)])[0]

    def jacobian_runs(self, directions: Sequence[Directions], role: str, *, fine: bool = False) -> list[list[FieldRun]]:
        """Field runs at each ``directions``' parameters on every sequence of ``role``, with
        their derivatives along them (:class:`FieldRun` ``jac_*``; see :meth:`jacobian`)."""
        return self.runs_together([Request(directions, role, fine=fine, jacobian=True)])[0]

    def runs_together(self, requests: Sequence["Request"]) -> list[list[list[FieldRun]]]:
        """The runs of several requests (as :meth:`runs` or, with ``jacobian``,
        :meth:`jacobian_runs` would make them) through one executor map, so that the
        workers stay busy across roles and models: a role of one sequence asked alone
        leaves one of two workers idle (the test stage of a 4 x 12 s diagnosis ran at 1.04
        cores).

        Returns:
            Per request, per model, the runs on the role's sequences (in ``names`` order).
        """
        todo, keys, found = [], [], {}
        plans = []
        with self._lock:  # the map itself runs unlocked: other threads' runs go beside it
            for req in requests:
                names = self.names[req.role]
                grid = (tuple(req.grid) if req.grid else tuple(self.cfg.fine_grid) if req.fine and self.cfg.fine_grid
                        else tuple(self.cfg.grid))
                h = None if req.element_size is None else float(req.element_size)
                mesh = grid if h is None else (grid, h)  # the cache's name of the mesh
                if req.jacobian:
                    items = [(Spec(d.effects(d.theta), d.youngs(d.theta), law=d.law, poisson_ratio=d.poisson_ratio,
                                   stiffening=d.stiffening, simulation=d.simulation), d) for d in req.models]
                else:
                    items = [(m if isinstance(m, Spec) else self.spec(m), None) for m in req.models]
                rows = []
                for m, d in items:
                    row = []
                    for n in names:
                        k = self._key(m, n, req.paper, mesh)
                        if d is not None:
                            k = k + ("jacobian", None if d.space is None else d.space.kind, d.fit_youngs)
                        row.append(k)
                        if k in found or k in keys:
                            continue
                        hit = self.cache.get_recent(k)
                        if hit is not None:
                            found[k] = hit
                        else:
                            self.repeated += k in self.cache.dropped
                            keys.append(k)
                            # the base model on the replay's own mesh: the inversion note's runs
                            todo.append(FieldTrial(self.trial(n, m, grid, h), self.layout, req.paper, d,
                                                   count_inverted=not m.effects and mesh == tuple(self.cfg.grid)))
                    rows.append(row)
                plans.append(rows)
        if todo:
            out = self.executor.map(run_field, self.prepared, todo)
            with self._lock:
                self.simulations += len(todo)
                for k, r, item in zip(keys, out, todo):
                    found[k] = r
                    self.cache.put(k, r)
                    if item.directions is not None and k[:-3] not in self.cache:
                        # the run itself answers plain requests too
                        self.cache.put(k[:-3], replace(r, jac_field=None, jac_force=None, d_youngs=None, d_offset=None))
        return [[[found[k] for k in row] for row in rows] for rows in plans]

    def jacobian(self, runs: list[FieldRun], shifted: bool = True, discrepancy: Discrepancy | None = None) -> np.ndarray:
        """(L, p) d :meth:`vector` / d theta of runs from :meth:`jacobian_runs`: the field's
        derivative weighted as the vector, then with force data the force's (a coarse run's
        mapped onto the fine grid as :meth:`_shifted_force` maps the force) in noise units;
        ``discrepancy`` as in :meth:`vector`."""
        parts = []
        for r in runs:
            if r.jac_field is None:
                raise TissueTwinError("jacobian() needs runs with derivatives (jacobian_runs)")
            p = r.jac_field.shape[0]
            w = np.sqrt(self.counts[r.sequence].astype(np.float64))
            clocked = r.d_offset is not None and np.any(r.d_offset != 0.0)
            dfield = r.jac_field
            delta = self._delta(r.sequence, discrepancy)
            if shifted and clocked and delta is not None:
                # the discrepancy moves with the clock (:meth:`_on_clock`)
                dfield = dfield + r.d_offset[:, None, None] * self._on_clock(delta, r, rate=True)[None]
            parts.append((w[None] * dfield).reshape(p, -1))
            if self.use_force:
                df = r.jac_force
                if shifted and r.sequence in self.force_delta:
                    df = (self.force_ratio[r.sequence] * df
                          + self.force_delta[r.sequence][None] * (r.d_youngs / self.cfg.youngs_modulus)[:, None, None])
                parts.append((np.sqrt(self.sigma2) * df / self.force_sigma).reshape(p, -1))
        J = np.concatenate(parts, axis=1).T
        return J if all(r.ok for r in runs) else np.full(J.shape, np.inf)

    def discrepancy(self, roles: Sequence[str]) -> list[str]:
        """Store ``fine - coarse`` base fields (and forces) of the sequences of ``roles``
        (see ``fine_grid``); the coarse and fine runs of every role go through one map.

        Returns:
            The sequences whose fine-mesh base run diverged where the coarse one did not
            (nothing is stored then; the caller drops the fine reference).

        Raises:
            TissueTwinError: the base model diverged on the replay's own mesh."""
        if not self.cfg.fine_grid:
            return []
        pairs = self._coarse_and_fine([], roles)
        for c, _ in pairs:
            if not c.ok:
                raise TissueTwinError(f"{self.prepared.path}: the base model diverged on {c.sequence}")
        failed = [f.sequence for _, f in pairs if not f.ok]
        if failed:
            return failed
        for c, f in pairs:
            self.delta[c.sequence] = f.field - c.field
            cc = float(np.sum(c.force**2))
            ratio = float(np.sum(f.force * c.force)) / cc if cc > 0 else 1.0
            self.force_ratio[c.sequence] = ratio
            self.force_delta[c.sequence] = f.force - ratio * c.force
        return []

    def drop_fine_reference(self) -> DiagnosisConfig:
        """Carry on without the fine-mesh reference (``fine_grid`` None): forget the stored
        discrepancies and the runs made so far (the coarse runs used ``coarse_dt``; without
        a fine reference every run takes the default step); later runs are on the replay's
        own mesh only.

        Returns:
            The configuration now in force (the caller's copy still names the fine grid).
        """
        self.cfg = replace(self.cfg, fine_grid=None)
        self.cache.clear()
        self.delta.clear()
        self.force_delta.clear()
        self.force_ratio.clear()
        return self.cfg

    def _on_clock(self, a: np.ndarray, r: FieldRun, rate: bool = False) -> np.ndarray:
        """A base-model discrepancy ``a`` ((F, ...) over the sequence's frames) read at the
        run's clock: at frame time t, its value at t + ``r.clock_offset`` (linear in time,
        held at the ends); ``rate``: its time derivative there (per s).

        The discrepancy was measured on the base model, whose probe at frame time t is at
        the kinematics' position at t; a run with a clock offset c puts it there at t - c,
        so its fine-minus-coarse difference at t is the base model's at t + c. Kept at the
        base model's timing, the correction of a 0.15 s offset's replay was out of step
        with it by 0.15 s: on a lab session with that offset (field seed 64, 12 s, force)
        the corrected field's train misfit dropped most near 75 ms and was worse at 0.15 s
        than at 0 (drop -1392); read at the run's clock, it drops 4990 at 0.15 s, most
        (5177) at 0.10 s."""
        c = float(r.clock_offset)
        if c == 0.0 and not rate:
            return a
        t = self.prepared.sequences[r.sequence].frame_times
        q = np.clip(t + c, t[0], t[-1])
        i = np.clip(np.searchsorted(t, q, side="right") - 1, 0, t.size - 2)
        dt = t[i + 1] - t[i]
        shape = (-1,) + (1,) * (a.ndim - 1)
        if rate:
            inside = ((t + c > t[0]) & (t + c < t[-1])).astype(np.float64)
            return (a[i + 1] - a[i]) / dt.reshape(shape) * inside.reshape(shape)
        w = ((q - t[i]) / dt).reshape(shape)
        return (1.0 - w) * a[i] + w * a[i + 1]

    def _delta(self, sequence: str, discrepancy: Discrepancy | None) -> np.ndarray | None:
        """The fine-minus-coarse field of ``sequence`` in force: ``discrepancy``'s when it
        holds the sequence, else the base model's (:meth:`discrepancy`), else None."""
        if discrepancy is not None and sequence in discrepancy:
            return discrepancy[sequence]
        return self.delta.get(sequence)

    def field(self, r: FieldRun, discrepancy: Discrepancy | None = None) -> np.ndarray:
        """(F, B) residual field of a coarse run, discrepancy-corrected (the discrepancy
        read at the run's clock, :meth:`_on_clock`; ``discrepancy`` as in :meth:`vector`)."""
        d = self._delta(r.sequence, discrepancy)
        return r.field if d is None else r.field + self._on_clock(d, r)

    def discrepancy_at(self, model: Spec, roles: Sequence[str]) -> Discrepancy:
        """``{sequence: (F, B) fine - coarse field}`` of ``model`` on the sequences of
        ``roles`` (coarse and fine runs through one map): the mesh error measured at this
        model rather than at the base model (:meth:`discrepancy`). A cause that moves where
        or how deep the probe presses (``Effect.moves_contact``) changes the mesh error,
        which grows with the press: measured on field seed 11 with a 5 mm robot offset (the
        probe higher than calibrated; 4 x 6 s, no force), the base model's discrepancy,
        measured on presses 5 mm too deep, put the train misfit's minimum along the offset
        at 2 mm (54210, against 71477 at the lab's 5 mm), where the fine grid's own runs
        have it at 5 mm (62487 at none, 33288 at 5 mm). Empty without a fine grid; a
        sequence whose fine run diverged is left out (the base model's stands for it).

        The fine run steps at ``cfg.fine_fit_dt``, plus the base model's change from the
        simulator's step to it, ``fine(base, 1/120 s) - fine(base, fine_fit_dt)`` (one more
        fine run per sequence, once): at no effect the result is then the base model's
        discrepancy exactly. Measured on field gravity seed 92 (4 x 12 s, force): the fine
        runs of two train sequences take 1.87 s at 1/60 s against 3.86 s at 1/120 s; at a
        1.5 mm robot offset and an 8 mm probe the corrected discrepancy differs from the
        1/120 s one by 0.0001-0.0008 mm RMS (at most 0.024 mm) per sequence, on
        discrepancies of 0.09-0.25 mm RMS. The diagnoses' maps of this method took 28.5 s
        instead of 39.5 s (gravity seed 92); its claims, answers and sizes were unchanged on
        that session and on the robot offset and probe radius sessions of seed 92.

        Args:
            model: the model (its E and effects; the coarse runs at the configured law).
            roles: "train" and/or "validation".
        """
        if not self.cfg.fine_grid:
            return {}
        step = self.cfg.fine_fit_dt
        if not step or model.simulation:
            return {c.sequence: f.field - c.field for c, f in self._coarse_and_fine(model, roles) if c.ok and f.ok}
        # the fine run at the fine fits' step, corrected by the base model's change from the
        # simulator's step to it (so that at no effect this is the base model's discrepancy
        # exactly): see the docstring
        at = (("dt", float(step)),)
        reqs = [Request([m], role, fine=fine) for role in roles
                for m, fine in ((model, False), (replace(model, simulation=at), True), (self.spec(), True),
                                (self.spec(simulation=at), True))]
        runs = self.runs_together(reqs)
        out = {}
        for i in range(0, len(runs), 4):
            for c, f, b, bs in zip(*(runs[i + j][0] for j in range(4))):
                if c.ok and f.ok and b.ok and bs.ok:
                    out[c.sequence] = f.field - c.field + (b.field - bs.field)
        return out

    def _coarse_and_fine(self, model: Spec | Sequence[dict], roles: Sequence[str]) -> list[tuple[FieldRun, FieldRun]]:
        """[(coarse run, fine run)] of ``model`` on every sequence of ``roles``, all through one map."""
        runs = self.runs_together([Request([model], role, fine=fine) for role in roles for fine in (False, True)])
        return [(c, f) for i in range(0, len(runs), 2) for c, f in zip(runs[i][0], runs[i + 1][0])]

    def _shifted_force(self, r: FieldRun, shifted: bool) -> np.ndarray:
        """(F, 3) force of a run, N; a coarse run's (``shifted``) mapped onto the fine grid:
        ``c f + (f_fine - c f_coarse)(E / E_base)``, with ``c`` the least-squares ratio of
        the base model's fine to coarse force on the sequence. The coarse grid locks
        (measured c = 0.57-0.93 per sequence), so every force it makes, the changes a
        candidate makes included (a friction force, a deeper dent), is too large by
        about 1 / c; the remainder is additive, and proportional to E, as the force is
        at a fixed dent."""
        if not shifted or r.sequence not in self.force_delta:
            return r.force
        E = r.youngs_modulus / self.cfg.youngs_modulus
        # the force is on the robot's clock whatever the run's offset: so is its discrepancy
        return self.force_ratio[r.sequence] * r.force + self.force_delta[r.sequence] * E

    def force_residual(self, r: FieldRun, shifted: bool = True) -> np.ndarray:
        """(F, 3) simulated minus measured force in units of the force noise (a coarse
        run's force mapped onto the fine grid's, see :meth:`_shifted_force`)."""
        return (self._shifted_force(r, shifted) - self.measured_force(r)) / self.force_sigma

    def measured_force(self, r: FieldRun) -> np.ndarray:
        """(F, 3) measured force at the run's frame times, N (the rows at the frame times
        on the robot's clock, where every run's force is, see ``FieldRun.force``)."""
        return self.force[r.sequence]

    def vector(self, runs: list[FieldRun], shifted: bool = True, discrepancy: Discrepancy | None = None) -> np.ndarray:
        """Weighted residual vector over the runs (inf if diverged): sqrt(n) r over bins
        and frames, then, with force data, the force residual in noise units;
        ``shifted``: coarse runs, discrepancy-corrected (fine runs: False), by
        ``discrepancy``'s fields where it holds the sequence (:meth:`discrepancy_at`), else
        by the base model's."""
        parts = []
        for r in runs:
            w = np.sqrt(self.counts[r.sequence].astype(np.float64))
            v = (w * (self.field(r, discrepancy) if shifted else r.field)).ravel()
            if self.use_force:
                v = np.concatenate([v, np.sqrt(self.sigma2) * self.force_residual(r, shifted).ravel()])
            parts.append(v if r.ok else np.full(v.size, np.inf))
        return np.concatenate(parts)

    def youngs_column(self, runs: list[FieldRun], shifted: bool = True) -> np.ndarray:
        """d vector / d log10 E of the runs if force is proportional to E and the field
        does not depend on it: zero on the bins, ln(10) times the (shifted) force in
        noise units (the vector's scale) on the force."""
        parts = []
        for r in runs:
            z = np.zeros(r.field.size)
            f = self._shifted_force(r, shifted)
            parts += [z, math.log(10.0) * np.sqrt(self.sigma2) * (f / self.force_sigma).ravel()]
        return np.concatenate(parts)

    def frames(self, role: str) -> np.ndarray:
        """(L,) int64: for each entry of a :meth:`vector` of ``role``, its frame's index
        among all frames of the role's sequences (in order)."""
        out, base = [], 0
        B = self.layout.n_bins
        for n in self.names[role]:
            F = self.prepared.sequences[n].frame_times.size
            f = np.arange(F) + base
            out.append(np.repeat(f, B))
            if self.use_force:
                out.append(np.repeat(f, 3))
            base += F
        return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)

    def frame_blocks(self, role: str) -> list[np.ndarray]:
        """Per sequence of ``role``, (F,) int64 block of each frame: frames within
        ``cfg.block`` seconds of the sequence's start of a block, numbered from 0."""
        out = []
        for n in self.names[role]:
            t = self.prepared.sequences[n].frame_times
            out.append(np.floor((t - t[0]) / self.cfg.block).astype(np.int64))
        return out

    def blocks(self, role: str) -> np.ndarray:
        """(L,) int64: for each entry of a :meth:`vector` of ``role``, its block
        (:meth:`frame_blocks`), numbered over the role."""
        per_frame, base = [], 0
        for b in self.frame_blocks(role):
            per_frame.append(b + base)
            base += int(b.max()) + 1
        return np.concatenate(per_frame)[self.frames(role)] if per_frame else np.zeros(0, dtype=np.int64)

    def force_rms(self, runs: list[FieldRun], shifted: bool = False) -> float:
        """RMS norm of simulated minus measured force over the frames of ``runs``, N."""
        res = np.concatenate([self.force_residual(r, shifted) * self.force_sigma for r in runs])
        return float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if np.all(np.isfinite(res)) else math.nan


def _force_evidence(prepared: PreparedSession, use_force: bool | None):
    """Measured force at frame times per sequence, its noise per axis, and a note.

    The noise is the RMS of each axis over rest frames (probe clear of the phantom for a
    second), where the true force is zero, floored at 1 mN as the E fit's
    (:func:`core.identification.objective.force_noise`).

    Returns:
        ({sequence: (F, 3) N} or None, (3,) N or None, note: why force is (not) used).

    Raises:
        TissueTwinError: ``use_force`` is True and a sequence has no force columns.
    """
    seqs = prepared.sequences
    missing = [n for n, s in seqs.items() if s.force is None]
    if use_force is False:
        return None, None, "not used (use_force=False)"
    if missing:
        if use_force:
            raise TissueTwinError(f"{prepared.path}: use_force needs force columns (fx, fy, fz) in every "
                                  f"kinematics.csv; {', '.join(missing)} has none")
        return None, None, "no force columns in kinematics.csv"
    force = {n: s.force_at(s.frame_times) for n, s in seqs.items()}
    rest = np.concatenate([force[n][prepared.rest_frames(n)] for n in seqs])
    if rest.shape[0] < 10:
        if use_force:
            raise TissueTwinError(f"{prepared.path}: cannot estimate the force noise: {rest.shape[0]} frames "
                                  "with the probe clear of the phantom (need 10)")
        return None, None, f"not used: {rest.shape[0]} rest frames to estimate the force noise (need 10)"
    sigma = np.maximum(np.sqrt(np.mean(rest**2, axis=0)), 1e-3)
    return force, sigma, f"used: noise {', '.join(f'{1e3 * v:.1f}' for v in sigma)} mN (x, y, z) from {rest.shape[0]} rest frames"



