"""The base model's nuisances: how a real session differs from the replay without any effect.

Every real session carries a model-form gap that no effect kind describes: the phantom's
material law is not corotational, its mesh is not the replay's, its damping, Poisson's
ratio and contact stiffness are not the paper's, Young's modulus is unknown, and the
camera's registration and the phantom's measured geometry are off by a fraction of a
millimetre. Each of these is a direction in the space of residual vectors:

- **model-form variants**: the change of the replay's weighted residual (field and
  force) when one property of the base model moves by a fixed step: a finer mesh (the
  fine grid minus the coarse one), stable neo-Hookean instead of corotational, nu 0.44
  to 0.47, Rayleigh stiffness damping 0.1 to 0.2 s, a 10x softer contact;
- **Young's modulus**: E + 5 % (with force data, or with a body force or foundation
  that sets a scale for it);
- **registration**: a rigid motion of the measured surface (three translations, three
  small rotations about the phantom's centre), constant over time;
- **robot calibration**: the probe displaced by a constant offset (x, y, z) within three
  standard errors of the corner-touch calibration (``Calibration.probe_sigma``, 0.1 mm
  when unknown). With a stiff contact the force is very sensitive to where the probe
  really is: a 0.1 mm deeper press changes it by ~10 mN, the force noise of a frame. A
  robot offset is claimed only beyond what the calibration's precision explains;
- **a generic smooth discrepancy in space and loading phase**: on the surface, a change
  of the dent's shape (hat functions of the distance from the probe's sphere, 0-14 mm,
  times the indentation depth and its square: "dent"); on the force, a change of the
  force-indentation law along the replayed force (depth, depth squared, indentation
  rate: "force_law"). Real phantoms differ from any replay in exactly these: the law's
  nonlinearity, the mesh's and the contact's resolution of the dent, damping.

The nuisance part of a residual is its least-squares fit on these directions with each
coefficient **bounded to a plausible range** (:data:`BOUNDS`): a model-form gap of the
size a real phantom has, not any size (Kennedy & O'Hagan's (2001) model discrepancy,
low-rank and physically shaped, with a bounded rather than a Gaussian prior: with
thousands of points a Gaussian prior on one shared coefficient is overwhelmed, and a
static offset of any size would be "registration"; bounded, a 0.05 mm offset is absorbed
and a 0.8 mm sag is not). Coefficients are fitted on the train sequences and carried over
to the validation sequences. A cause is claimed only for what it explains on held-out
data beyond them (:mod:`core.diagnosis.engine`).

The variant directions are linearised at the model of the round (its fixed causes and
E); the mesh direction, which needs fine-grid runs, is taken at the base model only.
"""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from core.diagnosis.evidence import Evidence, Request, Spec

__all__ = ["Nuisance", "FreeBeside", "nuisance_columns", "model_form_ends", "beyond_model_form", "model_form_worlds", "mesh_world",
           "model_form_drops", "VARIANTS", "BOUNDS"]

VARIANTS: dict[str, dict] = {
    "law": {"law": "stable_neo_hookean"},
    "poisson": {"poisson_ratio": 0.47},
    "damping": {"simulation": (("rayleigh_stiffness", 0.2),)},
    "contact": {"simulation": (("contact_stiffness_per_modulus", 2e4),)},
}
"""Model-form variants of the base model whose change of the residual is a nuisance direction
(the law's is the other law when the base model is itself replayed with this one: see
:func:`variant`)."""


def variant(name: str, cfg) -> dict:
    """The Spec fields of model-form variant ``name`` of :data:`VARIANTS` for a base model of
    ``cfg`` (a :class:`core.diagnosis.config.DiagnosisConfig`): as listed, except the law's,
    which is the corotational law when the base model already uses the stable neo-Hookean
    one (a variant equal to the base would be no direction at all)."""
    change = dict(VARIANTS[name])
    if "law" in change and change["law"] == getattr(cfg, "law", "corotational"):
        change["law"] = "corotational"
    return change

YOUNGS_STEP = 0.02
"""log10 step of Young's modulus of the ``youngs`` direction."""

DENT_KNOTS = (0.0, 0.004, 0.008, 0.014)
"""Knots (m) of the hat functions of the distance from the probe's sphere of the "dent" directions."""

REGISTRATION_UNIT = 1e-4
"""Registration directions are per 0.1 mm of motion (rotations: at the phantom's half size)."""

BOUNDS: dict[str, tuple[float, float]] = {
    "youngs": (-np.inf, np.inf),
    "mesh": (-0.5, 1.5),
    "law": (-1.0, 2.0),
    "poisson": (-2.0, 1.5),
    "damping": (-0.5, 2.0),
    "contact": (-1.0, 1.0),
    "registration": (-2.0, 2.0),
    "robot": (-3.0, 3.0),
    "dent": (-np.inf, np.inf),
    "force_law": (-np.inf, np.inf),
}
"""Plausible range of each nuisance coefficient, in units of its step: E is free; the
remaining mesh error may be up to 1.5 times the fine minus coarse grid's; the law up to
twice the neo-Hookean/corotational difference; nu between 0.38 and 0.485; Rayleigh
stiffness damping between 0.05 and 0.3 s; the contact between 10x softer and 1.9x stiffer
(the same linear step the other way); the camera's registration and the phantom's geometry off by up to 0.2 mm; the
robot's calibration within three of its standard errors (the robot directions are per
standard error). The generic discrepancy's coefficients are free."""


def _registration_columns(ev: Evidence, role: str) -> np.ndarray:
    """(L, 6) rigid motions of the measured surface (translations x, y, z; rotations about
    x, y, z through the phantom's centre), each per :data:`REGISTRATION_UNIT` of motion, as
    changes of the weighted residual field (zero on the force)."""
    lay = ev.layout
    centres = lay.centres3()
    normals = lay.normals3()
    size = np.asarray(lay.size, dtype=np.float64)
    arm = centres - size / 2
    half = float(np.max(size) / 2)
    per_bin = np.zeros((lay.n_bins, 6))
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        # a rigid motion of the measured surface by +u moves the residual (p - model) . n by -u . n;
        # the sign is immaterial for a fitted coefficient
        per_bin[:, j] = normals @ e
        per_bin[:, 3 + j] = np.einsum("bk,bk->b", np.cross(e[None, :] * np.ones_like(arm), arm), normals) / half
    per_bin *= REGISTRATION_UNIT
    cols = []
    for n in ev.names[role]:
        w = np.sqrt(ev.counts[n])  # (F, B)
        c = (w[:, :, None] * per_bin[None, :, :]).reshape(-1, 6)
        cols.append(c)
        if ev.use_force:
            F = w.shape[0]
            cols.append(np.zeros((F * 3, 6)))
    return np.concatenate(cols, axis=0)


def _indentation(ev: Evidence, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of sequence ``name``: the probe sphere's depth into the rest phantom (m, >= 0),
    its rate (m/s) and the sphere centres (F, 3), m, phantom frame."""
    seq = ev.prepared.sequences[name]
    t = seq.frame_times
    c = seq.probe.at(t)
    if name not in ev.indentation:
        ev.indentation[name] = np.maximum(ev.prepared.shape.penetration_depth(c, float(ev.prepared.probe_radius)), 0.0)
    depth = ev.indentation[name]
    rate = np.gradient(depth, t) if t.size > 1 else np.zeros_like(depth)
    return depth, rate, c


def _discrepancy_columns(ev: Evidence, role: str, base_runs: list, names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """(L, k) the generic smooth discrepancy's directions ("dent" on the field, "force_law"
    on the force) on the sequences of ``role`` (see the module docstring)."""
    lay = ev.layout
    centres = lay.centres3()
    r = float(ev.prepared.probe_radius)
    knots = np.asarray(DENT_KNOTS)
    use_dent, use_force = "dent" in names, "force_law" in names and ev.use_force
    n_dent = 2 * len(knots) if use_dent else 0
    n_force = 3 if use_force else 0
    blocks = []
    for n, run in zip(ev.names[role], base_runs):
        depth, rate, c = _indentation(ev, n)
        F = depth.size
        w = np.sqrt(ev.counts[n])  # (F, B)
        field = np.zeros((F, lay.n_bins, n_dent + n_force))
        if use_dent:
            rho = np.maximum(np.linalg.norm(centres[None, :, :] - c[:, None, :], axis=2) - r, 0.0)  # (F, B)
            for j in range(len(knots)):
                lo = knots[j - 1] if j > 0 else None
                hi = knots[j + 1] if j + 1 < len(knots) else None
                k = knots[j]
                up = np.ones_like(rho) if lo is None else np.clip((rho - lo) / (k - lo), 0.0, 1.0)
                down = np.zeros_like(rho) if hi is None else np.clip((hi - rho) / (hi - k), 0.0, 1.0)
                hat = np.where(rho <= k, up, down) if lo is not None else np.where(rho <= k, 1.0, down)
                field[:, :, 2 * j] = hat * depth[:, None] * w
                field[:, :, 2 * j + 1] = hat * (depth[:, None] ** 2 / 0.01) * w
        block = field.reshape(F * lay.n_bins, -1)
        if ev.use_force:
            force = np.zeros((F, 3, n_dent + n_force))
            if use_force:
                f = np.asarray(run.force, dtype=np.float64)
                nrm = np.linalg.norm(f, axis=1, keepdims=True)
                u = np.where(nrm > 1e-9, f / np.maximum(nrm, 1e-300), 0.0)  # (F, 3) the replayed force's direction
                scale = np.sqrt(ev.sigma2) / ev.force_sigma  # force residual units (see Evidence.vector)
                for j, v in enumerate((depth / 0.01, (depth / 0.01) ** 2, rate / 0.01)):
                    force[:, :, n_dent + j] = u * v[:, None] * scale[None, :]
            block = np.concatenate([block, force.reshape(F * 3, -1)], axis=0)
        blocks.append(block)
    cols = np.concatenate(blocks, axis=0)
    return cols, ["dent"] * n_dent + ["force_law"] * n_force


def nuisance_columns(ev: Evidence, role: str, fixed: Sequence[dict], E: float,
                     names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """The nuisance directions on the sequences of ``role`` at the model (``fixed``, E).

    Args:
        ev: the evidence (runs, weights).
        role: "train", "validation" or "test".
        fixed: effect dicts of the model of the round. E: its Young's modulus, Pa.
        names: which nuisances (see ``core.diagnosis.config.NUISANCES``); "youngs" only
            counts with force data or with a body force or foundation among ``fixed``.

    Returns:
        ((L, m) float64 columns in the units of :meth:`Evidence.vector`, their m names;
        the registration's six columns are named "registration"). Columns of diverged
        variants are dropped.
    """
    base = Spec(tuple(fixed), float(E))
    specs, labels = [], []
    for name in names:
        if name in VARIANTS:
            specs.append(Spec(tuple(fixed), float(E), **variant(name, ev.cfg)))
            labels.append(name)
        elif name == "youngs" and (ev.use_force or any(e["kind"] in ("gravity", "base_compliance") for e in fixed)):
            specs.append(Spec(tuple(fixed), float(E) * 10.0 ** YOUNGS_STEP))
            labels.append(name)
    sigma = float(getattr(ev.prepared.calibration, "probe_sigma", float("nan")))
    sigma = sigma if np.isfinite(sigma) and sigma > 0 else 1e-4
    if "robot" in names:
        for j in range(3):
            off = [0.0, 0.0, 0.0]
            off[j] = sigma
            specs.append(Spec(tuple(fixed) + ({"kind": "kinematic_offset", "offset": off},), float(E)))
            labels.append("robot")
    runs = ev.runs([base] + specs, role)
    v0 = ev.vector(runs[0])
    cols, out = [], []
    for lab, r in zip(labels, runs[1:]):
        v = ev.vector(r)
        if np.all(np.isfinite(v)) and np.all(np.isfinite(v0)):
            cols.append(v - v0)
            out.append(lab)
    if "mesh" in names and ev.cfg.fine_grid and ev.delta:
        coarse = ev.runs([Spec((), float(ev.cfg.youngs_modulus))], role)[0]
        fine = ev.runs([Spec((), float(ev.cfg.youngs_modulus))], role, fine=True)[0]
        v = ev.vector(fine, shifted=False) - ev.vector(coarse, shifted=False)
        if np.all(np.isfinite(v)):
            cols.append(v)
            out.append("mesh")
    L = v0.size
    N = np.stack(cols, axis=1) if cols else np.zeros((L, 0))
    if "registration" in names:
        N = np.concatenate([N, _registration_columns(ev, role)], axis=1)
        out += ["registration"] * 6
    if "dent" in names or "force_law" in names:
        D, labels = _discrepancy_columns(ev, role, runs[0], names)
        N = np.concatenate([N, D], axis=1)
        out += labels
    return N, out


def _variant_ends(ev: Evidence) -> dict[str, list[tuple[str, dict]]]:
    """{variant: [(label, Spec fields), ...]}: each numeric variant of :data:`VARIANTS` at
    ``base + bound * (variant - base)`` for both of its :data:`BOUNDS`, the law at its
    alternative (a law has no ends)."""
    from core.simulation import SimulationConfig

    sim0 = SimulationConfig()
    out: dict[str, list[tuple[str, dict]]] = {}
    for name in VARIANTS:
        if name not in ev.cfg.nuisances:
            continue
        change = variant(name, ev.cfg)
        lo, hi = BOUNDS[name]
        if "law" in change:
            out[name] = [(f"law {change['law']}", dict(change))]
        elif "poisson_ratio" in change:
            base, step = float(ev.cfg.poisson_ratio), float(change["poisson_ratio"]) - float(ev.cfg.poisson_ratio)
            out[name] = [(f"Poisson's ratio {base + b * step:.3g}", {"poisson_ratio": base + b * step}) for b in (lo, hi)]
        else:
            (field_name, value), = change["simulation"]
            base = float(getattr(sim0, field_name))
            ends = [base + b * (float(value) - base) for b in (lo, hi)]
            out[name] = [(f"{field_name} {v:.3g}", {"simulation": ((field_name, v),)}) for v in ends]
    return out


def model_form_worlds(ev: Evidence) -> list[tuple[str, dict]]:
    """Each model-form variant of :data:`VARIANTS` alone at either end of its plausible
    range, as ``(label, Spec fields)`` (Rayleigh stiffness damping 0.05 and 0.3 s, Poisson's
    ratio 0.38 and 0.485, the contact 10x softer and 1.9x stiffer, the neo-Hookean law; 7
    with the default nuisances): the phantoms a kind's detectability must hold for
    (:mod:`core.diagnosis.detectability`)."""
    return [end for ends in _variant_ends(ev).values() for end in ends]


def mesh_world(ev: Evidence) -> tuple[str, dict] | None:
    """The phantom as the fine mesh makes it, ``(label, Spec fields)`` of runs on
    ``cfg.fine_grid`` (at ``cfg.fine_fit_dt``; a ``phantom.stl`` phantom's fine mesh is its
    own at half the mean edge, :attr:`Evidence.fine_element_size`, and the label says so),
    or None without the mesh nuisance or a fine grid. A world a kind's detectability must
    hold for beside :func:`model_form_worlds`: a real phantom is a continuum, and where a
    kind's change of the data is a feature of the replay's coarse mesh the fine mesh does
    not make it. Measured on a lab session
    (seed 77, a 10 mm probe recorded as 5 mm, Yeoh law on 19x7x7, force): a 5 mm larger
    sphere's change of the data on 25x9x9 lies at cos 0.76 to the 13x5x5 replay's and
    fitted along the replay's it explains -907 (chi2) of held-out data against the 5692
    of the replay's own; every coarse world of :func:`model_form_worlds` kept 4310 or
    more, and the diagnosis said "not found above 4.32 mm" of a 5 mm difference it missed."""
    if "mesh" not in ev.cfg.nuisances or not ev.cfg.fine_grid:
        return None
    sim = (("dt", float(ev.cfg.fine_fit_dt)),) if ev.cfg.fine_fit_dt else ()
    element = getattr(ev, "fine_element_size", None)  # a phantom.stl's fine mesh: half the mean edge
    label = (f"the finer mesh ({element * 1e3:.2g} mm elements)" if element
             else f"the {'x'.join(str(n) for n in ev.cfg.fine_grid)} mesh")
    return label, ({"simulation": sim} if sim else {})


def model_form_ends(ev: Evidence) -> list[tuple[str, dict]]:
    """The model-form variants a claim must beat, as ``(label, Spec fields)``: each
    variant alone at either end of its plausible range (Rayleigh stiffness damping 0.05
    and 0.3 s, Poisson's ratio 0.38 and 0.485, the contact 10x softer and 1.9x stiffer,
    the neo-Hookean law), then every corner of that box (each variant at one of its ends,
    the law at either; 16 with the default nuisances). A real phantom differs in all of
    them at once: on a no-effect field session damped at 0.233 s (Yeoh law, nu 0.474) no
    single end reached a spurious clock offset's held-out drop (429 against 542), the
    corner of the neo-Hookean law, 0.3 s, 0.485 and the soft contact did (1264)."""
    per = _variant_ends(ev)
    out = [end for ends in per.values() for end in ends]
    if len(per) > 1:
        choices = [ends + ([("", {})] if name == "law" else []) for name, ends in per.items()]
        for combo in itertools.product(*choices):
            fields: dict = {}
            for _, f in combo:
                for key, value in f.items():
                    fields[key] = fields.get(key, ()) + value if key == "simulation" else value
            labels = [label for label, _ in combo if label]
            if len(labels) > 1:
                out.append((", ".join(labels), fields))
    return out


def model_form_drops(ev: Evidence, fixed: Sequence[dict], E: float, nuis: "Nuisance",
                     r_train: np.ndarray, r_validation: np.ndarray) -> dict[str, float]:
    """{variant: T} the held-out drop of chi-square (units of :meth:`Evidence.vector` over
    ``ev.sigma2``) that each model-form variant at the ends of its plausible range, alone or
    at a corner of the box (:func:`model_form_ends`), brings to the model (``fixed``, E),
    judged as a candidate is:
    the bounded nuisances refitted on its train residual and carried over to validation.

    The nuisance directions are the variants' linear changes at one step; the drop of a
    variant at an end of its range is what that linearisation and its bounds miss (a
    damping gap of a field session moved the held-out chi-square by -180 to +490 across the
    range where the linear nuisance fitted its coefficient at the wrong bound). A cause is
    claimed only for more than any of them explains. Diverged variants are left out.

    Args:
        ev: the evidence. fixed: effect dicts of the model. E: its Young's modulus, Pa.
        nuis: the model's nuisance directions. r_train, r_validation: the model's residual vectors.
    """
    ends = model_form_ends(ev)
    if not ends:
        return {}
    specs = [Spec(tuple(fixed), float(E), **fields) for _, fields in ends]
    trains, valids = ev.runs_together([Request(specs, "train"), Request(specs, "validation")])
    out = {}
    for (label, _), tr, va in zip(ends, trains, valids):
        drop = nuis.held_out_drop((r_train, r_validation), (ev.vector(tr), ev.vector(va)))
        if math.isfinite(drop):
            out[label] = drop / ev.sigma2
    return out


BEYOND_CHUNK = 4
"""Model-form worlds simulated together by :func:`beyond_model_form` (one executor map each):
the worlds are tried in order of their drop and the test stops at the first that explains
the candidate's residual, so most refusals cost one chunk."""


def beyond_model_form(ev: Evidence, fixed: Sequence[dict], E: float, nuis: "Nuisance", effects: Sequence[dict],
                      drops: dict[str, float], critical: float) -> tuple[bool, str, float]:
    """Whether a candidate still explains held-out data once the model is in each
    model-form world that explains part of the residual (``drops``, :func:`model_form_drops`,
    above zero): the nested test of the candidate beside the model-form gap.

    In every such world the candidate's fitted ``effects`` are added to the model,
    unchanged (not refitted there, which could only gain), and the held-out drop they
    bring to the world is ``T_w = (|h_W|^2 - |h_{W+c}|^2) / sigma^2`` with the bounded
    nuisances refitted on train (:meth:`Nuisance.held_out_drop`), as :func:`model_form_drops`
    judges the world itself (the world's own runs are those, from the cache while it holds them). The candidate passes when ``T_w >=
    critical`` (its own null's critical value) in every such world. A residual that one of
    the worlds explains leaves the candidate nothing there (a damping gap taken up by a
    Maxwell arm, a soft contact's shallow dent taken up by a downward robot offset); a
    residual of another shape (a stiff spot under a few presses, where a law or a Poisson's
    ratio changes the whole phantom's force) is still explained.

    Why, instead of the bar before 2026-11-29 (a claim's drop had to exceed the best
    world's): the two are drops of two different residuals. On a dome with force columns
    (lab inclusion scenario seed 3, 4 x 12 s) the best world explained 7330 (chi2) while a
    hidden stiff inclusion's fit explained 4379: no localised cause of a few presses could
    pass a bar set by the whole phantom's force. And a cause above the bar may still be the
    gap: on a no-effect field session without force (seed 1145, 4 x 6 s) a 3 mm sphere 31x
    stiffer just under a pressed spot (a stiffer contact there) explained 881 against a
    bar of 355 and was claimed.

    Args:
        ev: the evidence. fixed: effect dicts of the round's model. E: its Young's modulus, Pa.
        nuis: the round's nuisances. effects: the candidate's fitted effect dicts.
        drops: {variant label: its drop}, chi2. critical: the candidate's critical value, chi2.

    Returns:
        (passes, the variant that decided (the first that refused, else the one where the
        candidate explained least; "" when no world explains any of the residual), the
        candidate's drop in that world, chi2; -inf where a run diverged).
    """
    ends = dict(model_form_ends(ev))
    worlds = [label for label, d in sorted(drops.items(), key=lambda kv: -kv[1]) if d > 0]
    if not worlds:
        return True, "", math.inf
    least = ("", math.inf)
    fixed = tuple(fixed)
    for i in range(0, len(worlds), BEYOND_CHUNK):
        chunk = worlds[i: i + BEYOND_CHUNK]
        specs = ([Spec(fixed, float(E), **ends[w]) for w in chunk]
                 + [Spec(fixed + tuple(effects), float(E), **ends[w]) for w in chunk])
        trains, valids = ev.runs_together([Request(specs, "train"), Request(specs, "validation")])
        n = len(chunk)
        for j, label in enumerate(chunk):
            t_w = nuis.held_out_drop((ev.vector(trains[j]), ev.vector(valids[j])),
                                     (ev.vector(trains[n + j]), ev.vector(valids[n + j]))) / ev.sigma2
            if t_w < critical:
                return False, label, t_w
            if t_w < least[1]:
                least = (label, t_w)
    return True, least[0], least[1]


@dataclass(frozen=True)
class Nuisance:
    """Nuisance directions on train and validation, with bounded coefficients.

    Attributes:
        train: (L_t, m) columns on the train sequences. validation: (L_v, m) the same
            directions on the validation sequences.
        names: the nuisance of each column.
        lower, upper: (m,) bounds of the coefficients.
    """

    train: np.ndarray
    validation: np.ndarray
    names: tuple[str, ...]
    lower: np.ndarray = field(default_factory=lambda: np.zeros(0))
    upper: np.ndarray = field(default_factory=lambda: np.zeros(0))
    _svd: tuple = field(init=False, repr=False, compare=False, default=())

    def __post_init__(self):
        # the thin SVD of the train columns, once: every projection of a residual is then
        # an (m, m) problem (the bounded one too: |N c - r|^2 = |S V' c - U' r|^2 + const)
        if self.train.shape[1]:
            U, sv, Vt = np.linalg.svd(self.train, full_matrices=False)
            cut = np.finfo(np.float64).eps * max(self.train.shape) * (sv[0] if sv.size else 0.0)
            object.__setattr__(self, "_svd", (U, sv, Vt, sv > cut))

    @classmethod
    def build(cls, ev: Evidence, fixed: Sequence[dict], E: float, names: Sequence[str]) -> "Nuisance":
        """The nuisance directions of the model (``fixed``, E) on train and validation."""
        tr, n_tr = nuisance_columns(ev, "train", fixed, E, names)
        va, n_va = nuisance_columns(ev, "validation", fixed, E, names)
        if n_tr != n_va:  # a variant diverged on one role only
            common = [n for n in dict.fromkeys(n_tr) if n in n_va]
            ti = [i for i, n in enumerate(n_tr) if n in common]
            vi = [i for i, n in enumerate(n_va) if n in common]
            tr, va, n_tr = tr[:, ti], va[:, vi], [n_tr[i] for i in ti]
        # drop columns that vanish on train (e.g. a face the camera never sees)
        norms = np.linalg.norm(tr, axis=0)
        ok = norms > 1e-9 * max(float(norms.max(initial=0.0)), 1e-300)
        tr, va = tr[:, ok], va[:, ok]
        labels = [n for n, o in zip(n_tr, ok) if o]
        lo = np.array([BOUNDS[n][0] for n in labels]) * 1.0
        hi = np.array([BOUNDS[n][1] for n in labels]) * 1.0
        return cls(tr, va, tuple(labels), lo, hi)

    @property
    def size(self) -> int:
        return int(self.train.shape[1])

    def coefficients(self, r_train: np.ndarray) -> np.ndarray:
        """(m,) coefficients of the nuisance directions fitted to ``r_train`` by bounded
        least squares (Stark & Parker 1995, scipy's BVLS)."""
        if self.size == 0 or not np.all(np.isfinite(r_train)):
            return np.zeros(self.size)
        free = np.isinf(self.lower) & np.isinf(self.upper)
        U, sv, Vt, keep = self._svd
        b = U.T @ r_train
        c = Vt[keep].T @ (b[keep] / sv[keep])  # the minimum-norm least-squares solution (as lstsq)
        if np.all(free | ((c >= self.lower) & (c <= self.upper))):
            return c
        from scipy.optimize import lsq_linear

        return lsq_linear(sv[:, None] * Vt, b, bounds=(self.lower, self.upper), method="bvls").x

    def project(self, r_train: np.ndarray) -> np.ndarray:
        """``r_train`` minus its nuisance part on train (inf stays inf)."""
        if self.size == 0 or not np.all(np.isfinite(r_train)):
            return r_train
        return r_train - self.train @ self.coefficients(r_train)

    def held_out(self, r_validation: np.ndarray, r_train: np.ndarray) -> np.ndarray:
        """The validation residual of a model minus the nuisance part fitted on its train
        residual (the coefficients carried over to held-out data)."""
        if self.size == 0 or not np.all(np.isfinite(r_validation)):
            return r_validation
        return r_validation - self.validation @ self.coefficients(r_train)

    def held_out_drop(self, before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray]) -> float:
        """``|h(before)|^2 - |h(after)|^2`` (units of the residual vectors squared; divide by
        sigma^2 for chi2): the held-out drop of a change of the model, each model's nuisance
        part fitted on its train residual (:meth:`held_out`). ``before`` and ``after`` are
        (train, validation) residual vectors; -inf where one of them is not finite (a run
        that diverged)."""
        if not all(np.all(np.isfinite(v)) for v in (*before, *after)):
            return -math.inf
        h0, h1 = self.held_out(before[1], before[0]), self.held_out(after[1], after[0])
        return float(h0 @ h0) - float(h1 @ h1)

    def active(self, r_train: np.ndarray) -> "Nuisance":
        """The directions whose coefficients are inside their bounds at the fit of
        ``r_train`` (the linear part of the projection there; a coefficient at its bound
        is a fixed shift). The linearised tests use these."""
        if self.size == 0:
            return self
        c = self.coefficients(r_train)
        tol_lo = 1e-9 * np.where(np.isfinite(self.lower), np.abs(self.lower), 0.0)
        tol_hi = 1e-9 * np.where(np.isfinite(self.upper), np.abs(self.upper), 0.0)
        inside = (c > self.lower + tol_lo) & (c < self.upper - tol_hi)
        if inside.all():
            # the same columns unbounded: share the arrays and their SVD (a paper-size
            # round held a second copy of both, ~0.2 GB)
            free = copy.copy(self)
            object.__setattr__(free, "lower", np.full(self.size, -np.inf))
            object.__setattr__(free, "upper", np.full(self.size, np.inf))
            return free
        return Nuisance(self.train[:, inside], self.validation[:, inside], tuple(n for n, i in zip(self.names, inside) if i),
                        np.full(int(inside.sum()), -np.inf), np.full(int(inside.sum()), np.inf))

    def beside(self, d_train: np.ndarray, d_validation: np.ndarray) -> "FreeBeside":
        """These directions with one more, free (unbounded) column in front: ``d_train``
        (L_t,) and ``d_validation`` (L_v,). Same projections as
        ``Nuisance(concat([d, train]), concat([d, validation]), ...)`` without copying the
        columns or taking a new SVD (:class:`FreeBeside`)."""
        return FreeBeside(self, np.asarray(d_train, dtype=np.float64), np.asarray(d_validation, dtype=np.float64))


class FreeBeside:
    """A :class:`Nuisance` with a free column ``d`` in front of its bounded ones, sharing
    their arrays and SVD: with ``N = U S V'``, ``[d, N] = [U q] K`` where ``q`` is ``d``'s
    unit part outside ``U`` and ``K = [[U'd, S V'], [|d - U U'd|, 0]]`` is (m + 1) x (m + 1),
    so a fit of the (m + 1) coefficients is the small problem ``|K c - [U q]' r|`` (bounded:
    scipy's BVLS, as :meth:`Nuisance.coefficients`). The detectability's model-form worlds
    fit a kind's signature beside the round's nuisances this way: the concatenated copy and
    its SVD held ~0.6 GiB of a paper-size diagnosis's main process at its peak.

    Attributes:
        base: the bounded directions. d_train, d_validation: the free column on each role.
    """

    def __init__(self, base: Nuisance, d_train: np.ndarray, d_validation: np.ndarray):
        self.base, self.d_train, self.d_validation = base, d_train, d_validation
        self.names = ("effect",) + base.names
        self.lower = np.concatenate([[-np.inf], base.lower])
        self.upper = np.concatenate([[np.inf], base.upper])
        m = base.size
        if m:
            U, sv, Vt, _ = base._svd
            a = U.T @ d_train
            rest = d_train - U @ a
        else:
            U, sv, Vt, a, rest = None, np.zeros(0), np.zeros((0, 0)), np.zeros(0), d_train
        rho = float(np.linalg.norm(rest))
        self._q = rest / rho if rho > 0 else np.zeros_like(rest)
        K = np.zeros((m + 1, m + 1))
        K[:m, 0], K[m, 0] = a, rho
        if m:
            K[:m, 1:] = sv[:, None] * Vt
        self._U, self._K = U, K
        Uk, sk, Vkt = np.linalg.svd(K)
        cut = np.finfo(np.float64).eps * max(d_train.size, m + 1) * (sk[0] if sk.size else 0.0)
        self._svd = (Uk, sk, Vkt, sk > cut)

    @property
    def size(self) -> int:
        return self.base.size + 1

    def coefficients(self, r_train: np.ndarray) -> np.ndarray:
        """(m + 1,) coefficients of ``[d, N]`` fitted to ``r_train`` (bounded least squares)."""
        if not np.all(np.isfinite(r_train)):
            return np.zeros(self.size)
        b = np.concatenate([self._U.T @ r_train if self._U is not None else np.zeros(0), [self._q @ r_train]])
        Uk, sk, Vkt, keep = self._svd
        c = Vkt[keep].T @ ((Uk.T @ b)[keep] / sk[keep])
        free = np.isinf(self.lower) & np.isinf(self.upper)
        if np.all(free | ((c >= self.lower) & (c <= self.upper))):
            return c
        from scipy.optimize import lsq_linear

        return lsq_linear(self._K, b, bounds=(self.lower, self.upper), method="bvls").x

    def held_out(self, r_validation: np.ndarray, r_train: np.ndarray) -> np.ndarray:
        """As :meth:`Nuisance.held_out` of the concatenated directions."""
        if not np.all(np.isfinite(r_validation)):
            return r_validation
        c = self.coefficients(r_train)
        out = r_validation - c[0] * self.d_validation
        return out - self.base.validation @ c[1:] if self.base.size else out
