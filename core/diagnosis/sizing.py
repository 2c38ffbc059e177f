"""Sizing: the smallest size of an effect kind that these data would claim, solved from its signature.

A kind's signature, its change of the train and validation residual vectors, is simulated
at the kind's reference size against a round's model (:func:`signatures`; on the fine mesh
for a kind that moves the contact, :func:`fine_signature`) and scaled
(:meth:`core.simulation.effects.Effect.strength`). The smallest strength that the
session's own noise replicates would claim at :data:`POWER`, against the critical value
grown with the effect the data hold (:func:`growing_critical`), is solved on the bounded
nuisance projection (:func:`min_sizes`, from :func:`expected_statistic`), and once more in
each model-form world (:func:`world_min_size`, from :func:`world_statistic`): the size a
"not found above" statement must hold whichever phantom of the model-form gap's plausible
range made the data. Split from :mod:`core.diagnosis.detectability`, which states each
kind's answer from these sizes and keeps the claims' bookkeeping.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from core.diagnosis.evidence import Evidence, Request, Spec
from core.diagnosis.inference import TAIL_MIN_COUNT
from core.diagnosis.model_form import finer_meshes, mesh_world, model_form_worlds
from core.diagnosis.nuisance import FreeBeside, Nuisance
from core.simulation.effects import PhantomContext

if TYPE_CHECKING:  # the engine's round: its model, nuisances, held-out test and residuals
    from core.diagnosis.rounds import Round

__all__ = ["POWER", "expected_statistic", "fine_signature", "growing_critical", "least_informative", "min_sizes",
           "signatures", "world_min_size", "world_statistic"]


def fine_signature(ev: Evidence, cls) -> bool:
    """Whether a kind's signature is taken on the fine mesh: a kind that moves the contact
    (``Effect.moves_contact``), whose fit measures the mesh error again at its parameters
    (:meth:`~core.diagnosis.evidence.Evidence.discrepancy_at`), so that the test fits it
    as the fine mesh makes it (coarse runs corrected by the fine ones at the fit). Its
    coarse change alone, under the base model's constant correction, is another change:
    measured on field seed 11 (a 5 mm robot offset, no force), "no size up to 5 mm" from
    the coarse signature of a vertical offset whose fit the test then claimed.

    Args:
        ev: the session's evidence (its ``cfg``: ``fine_grid``, ``contact_relinearisations``).
        cls: the effect kind's class (:data:`core.simulation.effects.EFFECT_KINDS`).
    """
    return bool(cls.moves_contact and ev.cfg.fine_grid and ev.cfg.contact_relinearisations > 0)


def signatures(ev: Evidence, rnd: "Round", effects: list[dict], fine: bool = False
               ) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """(train, validation) change of the residual vectors when each effect joins the round's
    model (None where it diverged); the runs of every effect on both roles go through one
    executor map (asked one effect at a time, a signature was two maps, the second a
    single validation sequence on one worker). ``fine``: the change on the fine mesh (its
    runs with and without the effect, at ``cfg.fine_fit_dt``; :func:`fine_signature`).

    Args:
        ev: the session's evidence, which runs the models. rnd: the round whose model
            (``fixed``, ``youngs_modulus``, ``discrepancy``) the effects join, and whose
            residuals (``r_train`` (L_t,), ``r_validation`` (L_v,)) they change.
        effects: effect dicts (:meth:`core.simulation.effects.Effect.to_dict`).
        fine: take the change on the fine mesh.

    Returns:
        Per effect, in order, ``(d_train (L_t,), d_validation (L_v,))`` in the units of the
        residual vectors (:meth:`core.diagnosis.evidence.Evidence.vector`: ``v @ v /
        sigma2`` is chi2), or None where a run diverged (a non-finite entry); ``[]`` for no
        effects.

    Raises:
        Nothing of its own: the executor's errors propagate
        (:meth:`core.diagnosis.evidence.Evidence.runs_together`).
    """
    if not effects:
        return []
    if fine:
        sim = ev.cfg.fine_step
        specs = [Spec(tuple(rnd.fixed), rnd.youngs_modulus, simulation=sim)] + [
            Spec(tuple(rnd.fixed) + (e,), rnd.youngs_modulus, simulation=sim) for e in effects]
        trains, valids = ev.runs_together([Request(specs, "train", fine=True), Request(specs, "validation", fine=True)])
        b_t, b_v = ev.vector(trains[0], shifted=False), ev.vector(valids[0], shifted=False)
        pairs = [(ev.vector(tr, shifted=False) - b_t, ev.vector(va, shifted=False) - b_v)
                 for tr, va in zip(trains[1:], valids[1:])]
    else:
        specs = [Spec(tuple(rnd.fixed) + (e,), rnd.youngs_modulus) for e in effects]
        trains, valids = ev.runs_together([Request(specs, "train"), Request(specs, "validation")])
        pairs = [(ev.vector(tr, discrepancy=rnd.discrepancy) - rnd.r_train,
                  ev.vector(va, discrepancy=rnd.discrepancy) - rnd.r_validation) for tr, va in zip(trains, valids)]
    return [(d_t, d_v) if np.all(np.isfinite(d_t)) and np.all(np.isfinite(d_v)) else None for d_t, d_v in pairs]


def expected_statistic(rnd: "Round", D_t: np.ndarray, D_v: np.ndarray, s: float, sigma2: float) -> float:
    """The held-out statistic T (chi2 units) that ``s`` times the signature (D_t, D_v) would
    give without noise: the fit along D explains it on train, and the model of the round
    keeps what its bounded nuisances, fitted on train, leave of it on validation.

    Args:
        rnd: the round (its ``nuisance``). D_t, D_v: the signature per unit strength, (L_t,)
            and (L_v,), residual-vector units. s: the strength. sigma2: the noise variance
            the residual vectors are scaled by (``Evidence.sigma2``, m^2).
    """
    h = rnd.nuisance.held_out(s * D_v, s * D_t)
    return float(h @ h) / sigma2


def least_informative(rnd: "Round", sigs: list, directions: list, s: float, sigma2: float
                      ) -> tuple[list[float], tuple[np.ndarray, np.ndarray]] | None:
    """The direction, in the span of ``directions``, that the held-out test sees least: the
    eigenvector of the smallest eigenvalue of the Fisher information of the direction's
    coefficients in the test's metric, ``F_ij = h(D_i) . h(D_j) / sigma2`` (``h``: what the
    round's nuisances fitted on train leave of a change on validation,
    :func:`expected_statistic`), taken by polarisation at strength ``s`` so that the
    bounded nuisances count as they do at that strength.

    A vector effect (a robot calibration offset) stated "not found above" its size from its
    axes alone is optimistic: the statistic of an offset ``s u`` is ``s^2 u^T F u``, whose
    least value over unit ``u`` is the smallest eigenvalue of ``F``, below the smallest
    diagonal entry unless ``F`` is diagonal. Measured on field seed 92 (4 x 12 s, force):
    a 2.35 mm offset (1.5, -1.0, -1.5) mm not claimed where the axes' least detectable
    size, along x, was stated as 1.95 mm.

    Args:
        rnd: the round (its ``nuisance``). sigs: per direction, its signature at strength
            ``s``, ``(d_t (L_t,), d_v (L_v,))`` (:func:`signatures`), or None where it diverged.
        directions: the directions' unit vectors, (k,) lists of floats, in the phantom frame.
        s: the strength the signatures were simulated at (> 0). sigma2: the residual
            vectors' noise variance (m^2).

    Returns:
        ``(u, (d_t, d_v))``: the unit direction (a list of floats, phantom frame, its sign
        chosen so that its largest component is positive, as the axes are) and its
        signature at strength ``s``, the linear combination of ``sigs`` (the size solve
        simulates it again at the size it finds); None when a signature is missing, fewer
        than two directions are given, or the information matrix is zero.
    """
    if len(sigs) < 2 or any(sig is None for sig in sigs) or not s > 0:
        return None
    k = len(sigs)
    D_t = np.stack([sig[0] for sig in sigs], axis=1) / s
    D_v = np.stack([sig[1] for sig in sigs], axis=1) / s

    def stat(c):
        return expected_statistic(rnd, D_t @ c, D_v @ c, s, sigma2)

    eye = np.eye(k)
    diag = [stat(eye[i]) for i in range(k)]
    F = np.diag(diag)
    for i in range(k):
        for j in range(i + 1, k):
            F[i, j] = F[j, i] = 0.5 * (stat(eye[i] + eye[j]) - diag[i] - diag[j])
    if not np.all(np.isfinite(F)) or not np.any(F):
        return None
    c = np.linalg.eigh(F)[1][:, 0]  # eigenvalues ascending: the least informative first
    u = np.asarray(directions, dtype=np.float64).T @ c
    n = float(np.linalg.norm(u))
    if not n > 0:
        return None
    c, u = c / n, u / n
    if u[int(np.argmax(np.abs(u)))] < 0:
        c, u = -c, -u
    return [float(v) for v in u], (s * (D_t @ c), s * (D_v @ c))


POWER = 0.8
"""A kind's ``min_size`` is claimed with this probability (the minimum detectable effect at 80 % power)."""


def growing_critical(rnd: "Round", D_t: np.ndarray, D_v: np.ndarray, critical: float, level: float,
                     X_t: np.ndarray | None = None, X_v: np.ndarray | None = None, null: str = "round"):
    """``critical(s)``: the critical value a claim of a kind needs when the data hold
    strength ``s`` of the change ``X`` ((L_t,), (L_v,), per unit strength; default the
    kind's signature ``D``, its change in a model-form world otherwise) and the kind is
    fitted along ``D``, from ``critical``, its value without an effect.

    The held-out test draws its null from the round's residual, which holds the effect
    itself where there is one (:meth:`core.diagnosis.inference.HeldOutTest.null_with_effect`):
    a size solved against the no-effect critical value said little of what a claim needed
    (gravity on field seed 11: critical 37.5 without an effect, 8934 at 2x the size then
    stated). The growth is that of the null of a fit along ``D`` alone, at ``level`` (at
    least ``TAIL_MIN_COUNT / R``, where the replicates' own quantile holds: the fitted tail
    costs ~40 ms a call and the solve asks ~50 strengths per placement), added to
    ``critical``: exact where ``critical`` is that null's, a little short where it comes
    from the kind's own fit of more parameters, which takes up more of a resampled effect.
    (Scaled as a ratio instead, a critical value far above the one-column null's multiplied
    the growth: 3x the change's own statistic on a synthetic case, where the one-column
    null reached 0.29 of it.)

    ``null`` "candidate" (``DiagnosisConfig.null_residual``: the null drawn from the
    residual each fitted candidate leaves): what grows the null is only the part of ``X``
    that the fit along ``D`` leaves (its least-squares part along ``D`` on train, without
    the nuisances, taken out on both roles): nothing for the replay's own signature, the
    rest of a model-form world's change otherwise.

    Args:
        rnd: the round (its ``test``, a :class:`core.diagnosis.inference.HeldOutTest`).
        D_t, D_v: the kind's signature per unit strength, (L_t,) and (L_v,).
        critical: the critical value without an effect (chi2). level: the test's level.
        X_t, X_v: the change the data hold per unit strength, (L_t,) and (L_v,); ``D``
            when None. null: ``DiagnosisConfig.null_residual`` ("round" or "candidate").

    Returns:
        ``critical(s) -> float`` (chi2), >= ``critical``, of the strength ``s``.
    """

    test = rnd.test
    X_t = D_t if X_t is None else np.asarray(X_t, dtype=np.float64)
    X_v = D_v if X_v is None else np.asarray(X_v, dtype=np.float64)
    if null == "candidate":
        Dp, Xp = test.train_signature(D_t[:, None])[:, 0], test.train_signature(X_t[:, None])[:, 0]
        dd = float(Dp @ Dp)
        c = float(Dp @ Xp) / dd if dd > 0 else 0.0
        X_t, X_v = X_t - c * D_t, X_v - c * D_v
        if not (np.any(X_t) or np.any(X_v)):
            return lambda s: critical
    grown = test.null_with_effect(D_t[:, None], D_v[:, None], X_t, X_v)
    lv = max(float(level), TAIL_MIN_COUNT / max(test.replicates, 1))

    def q(s: float) -> float:
        return float(np.quantile(grown(s), 1.0 - lv, method="higher"))

    q0 = q(0.0)
    return lambda s: critical + max(q(s) - q0, 0.0)


def min_sizes(ev: Evidence, rnd: "Round", cls, ctx: PhantomContext, jobs: list[tuple[dict, float]],
              first: list | None = None) -> list[float | None]:
    """For each ``(assumed, critical, level)`` of ``jobs``: the smallest size of ``cls`` with the
    ``assumed`` parameters that the round's test would claim with probability
    :data:`POWER`: the strength whose noise-free held-out statistic, plus the noise's part at
    that power (from the session's own replicates, :meth:`HeldOutTest.min_strength`),
    reaches ``critical`` as it grows with the effect (:func:`growing_critical`). The nuisances keep their bounds (a 0.8 mm sag is not a 0.2 mm
    registration error), so this is solved by bisection on the bounded projection. The
    signature is simulated at the reference size and scaled, then once more at the size
    found (the change is not linear in the size for every kind); each of the two steps
    simulates every job's signature in one map (the first step's are ``first`` when the
    caller has them, :func:`signatures` at the reference size). None where no size up to
    the kind's largest would be claimed.

    Args:
        ev: the session's evidence. rnd: the round whose test would claim it. cls: the
            kind's class. ctx: the phantom's context (:meth:`Effect.sized`).
        jobs: ``[(assumed parameters, critical value (chi2), level)]``.
        first: the jobs' signatures at the kind's reference size (:func:`signatures`), or
            None to simulate them.

    Returns:
        Per job, the size in the kind's ``size_unit`` (it may exceed ``cls.max_size``:
        the caller caps it), or None.
    """
    sizes = [float(cls.reference_size)] * len(jobs)
    found: list[float | None] = [None] * len(jobs)
    s_max = cls.strength(cls.max_size)
    todo = list(range(len(jobs)))
    for step in range(2):
        sigs = (first if step == 0 and first is not None
                else signatures(ev, rnd, [cls.sized(sizes[j], ctx, **jobs[j][0]).to_dict() for j in todo],
                                fine=fine_signature(ev, cls)))
        again = []
        for j, sig in zip(todo, sigs):
            _, critical, level = jobs[j]
            st = cls.strength(sizes[j])
            if sig is None or st == 0:
                continue
            D_t, D_v = sig[0] / st, sig[1] / st
            grown = growing_critical(rnd, D_t, D_v, critical, level, null=ev.cfg.null_residual)
            s = rnd.test.min_strength(D_t, D_v, grown, s_max, POWER,
                                      expected=lambda s: expected_statistic(rnd, D_t, D_v, s, ev.sigma2))
            if s is None:
                found[j] = None
                continue
            found[j] = cls.size_at(s)
            if abs(found[j] - sizes[j]) > 0.05 * max(abs(sizes[j]), 1e-12):
                sizes[j] = found[j]
                again.append(j)
        todo = again
    return found


def world_statistic(nuis: Nuisance, fit: FreeBeside, X_t: np.ndarray, X_v: np.ndarray, s: float, sigma2: float) -> float:
    """The noise-free held-out statistic T (chi2 units) of data holding ``s`` times the change
    (X_t, X_v) when the candidate is fitted along the replay's own signature: ``fit`` holds
    that signature as a free column beside the bounded nuisances ``nuis``.

    Args:
        nuis: the round's bounded nuisances. fit: ``nuis.beside(D_t, D_v)``
            (:meth:`core.diagnosis.nuisance.Nuisance.beside`). X_t, X_v: the change per
            unit strength, (L_t,) and (L_v,), residual-vector units. s: the strength.
            sigma2: the residual vectors' noise variance (``Evidence.sigma2``, m^2).
    """
    before = nuis.held_out(s * X_v, s * X_t)
    after = fit.held_out(s * X_v, s * X_t)
    return float(before @ before - after @ after) / sigma2


def world_min_size(ev: Evidence, rnd: "Round", cls, ctx: PhantomContext, assumed: dict, size: float,
                   critical: float, level: float) -> tuple[float | None, str]:
    """(min_size or None, the world that set it or ""): the smallest size of ``cls`` with
    the ``assumed`` parameters that the round's test claims at :data:`POWER` whichever
    phantom of the model-form gap's plausible range made the data.

    The kind's change of the data is simulated in the replay's own physics and in each
    model-form world (:func:`core.diagnosis.model_form.model_form_worlds`: the base model
    with one of the neo-Hookean law, Poisson's ratio 0.38 or 0.485, Rayleigh damping 0.05
    or 0.3 s, a 10x softer or 1.9x stiffer contact; and :func:`core.diagnosis.model_form.mesh_world`,
    the fine mesh) as ``X_W = run(W + effect) - run(W)``,
    at ``size`` and scaled linearly. The test still fits the kind as the replay makes it
    (along its own signature D, beside the bounded nuisances), so where a world's change
    differs from D, or is weaker, less of it is explained. Each world's size is solved with
    its own noise-free statistic (:func:`world_statistic`), the noise's part as
    :meth:`core.diagnosis.inference.HeldOutTest.min_strength` gives it, against the
    critical value grown with the change that world's data hold (:func:`growing_critical`),
    and the largest is stated; solved at ``size``
    in the coarse worlds and once more at the size found (the fine mesh only then, one
    fine run per role instead of two: the detectability stage of lab gravity seed 0, 12 s
    with force, 58 -> 40 s). A kind that moves the contact (``moves_contact``: a robot
    offset, a probe radius) has the meshes finer than the fine reference as worlds too
    (:func:`core.diagnosis.model_form.finer_meshes`, at that last step), since its claim
    must hold on them (:func:`core.diagnosis.model_form.beyond_finer_mesh`): a size the
    claim rule would refuse is not stated as one that would have shown.

    Why: a size stated from the replay's own signature assumes the phantom makes that
    signature. Measured on a field session (seed 52, a 7.5 mm probe recorded as 5 mm, force,
    the lab's phantom neo-Hookean with a 1.8x stiffer contact): "not found above 1.93 mm"
    from the replay's signature, while a 2.5 mm larger sphere in the neo-Hookean world
    explains 437 (chi2) of held-out data against the 2268 of the replay's own and a
    critical 1061 (Poisson's ratio 0.38: 125).

    Args:
        ev: the session's evidence. rnd: the round whose test would claim it. cls: the
            kind's class. ctx: the phantom's context. assumed: the placement's parameters.
        size: the replay's own min_size of that placement (the kind's ``size_unit``),
            where the solve starts. critical: the placement's critical value without an
            effect (chi2). level: the test's level.

    Returns:
        ``(size, world)``: the largest of the worlds' sizes (the kind's ``size_unit``; it
        may exceed ``cls.max_size``: the caller caps it) and the label of the world that
        set it ("" for the replay's own physics); ``(None, world)`` where that world would
        claim no size up to the kind's largest; ``(size, "")`` without worlds; where the
        signature at a step diverged or has no strength, what the steps before it found
        (``(size, "")`` at the first).
    """
    coarse = model_form_worlds(ev)
    mesh = mesh_world(ev)
    fine_w = [mesh] if mesh is not None else []
    # a kind that moves the contact is claimed only where it holds on the finer meshes too
    # (:func:`core.diagnosis.model_form.beyond_finer_mesh`): its size must hold there
    finer = finer_meshes(ev) if getattr(cls, "moves_contact", False) else []
    if not coarse and not fine_w and not finer:
        return size, ""
    s_max = cls.strength(cls.max_size)
    fixed, E = tuple(rnd.fixed), rnd.youngs_modulus
    nuis = rnd.nuisance
    found, label = size, ""
    roles = ("train", "validation")
    # a kind whose signature is the fine mesh's (:func:`fine_signature`): the fine world is its own
    own_fine = fine_signature(ev, cls) and bool(fine_w)
    for step in range(2):
        # the fine mesh only at the last step, near the size stated (a 25x9x9 step costs
        # ~10 of 13x5x5's, bench_replay 569 vs 5770 steps/s; the coarse runs of the first
        # step's size are cached)
        with_fine = fine_w if step == 1 or own_fine else []
        with_finer = finer if step == 1 or not (coarse or fine_w) else []
        eff = cls.sized(size, ctx, **assumed).to_dict()
        st = cls.strength(size)
        if st == 0:
            return found, label
        # per world the runs without and with the effect, all through one map
        specs = ([Spec(fixed + (eff,), E)] + [Spec(fixed, E, **f) for _, f in coarse]
                 + [Spec(fixed + (eff,), E, **f) for _, f in coarse])
        fine_specs = [Spec(fixed, E, **f) for _, f in with_fine] + [Spec(fixed + (eff,), E, **f) for _, f in with_fine]
        sim = ev.cfg.fine_step  # as beyond_finer_mesh runs them
        finer_specs = [Spec(fixed, E, simulation=sim), Spec(fixed + (eff,), E, simulation=sim)]
        requests = [Request(specs, role) for role in roles]
        if fine_specs:
            requests += [Request(fine_specs, role, fine=True) for role in roles]
        requests += [m.request(finer_specs, role) for m in with_finer for role in roles]
        out = ev.runs_together(requests)
        vec = {role: [ev.vector(run, discrepancy=rnd.discrepancy) for run in out[i]] for i, role in enumerate(roles)}
        vec_fine = ({role: [ev.vector(run, shifted=False) for run in out[2 + i]] for i, role in enumerate(roles)}
                    if fine_specs else {})
        first_finer = 4 if fine_specs else 2
        vec_finer = [{role: [ev.vector(run, shifted=False) for run in out[first_finer + 2 * j + i]]
                      for i, role in enumerate(roles)} for j in range(len(with_finer))]
        D_t, D_v = (vec["train"][0] - rnd.r_train) / st, (vec["validation"][0] - rnd.r_validation) / st
        if own_fine:
            D_t = (vec_fine["train"][1] - vec_fine["train"][0]) / st
            D_v = (vec_fine["validation"][1] - vec_fine["validation"][0]) / st
        if not (np.all(np.isfinite(D_t)) and np.all(np.isfinite(D_v))):
            return found, label
        changes = [("", D_t, D_v)]
        for names, runs in ((coarse, {r: v[1:] for r, v in vec.items()}), ([] if own_fine else with_fine, vec_fine),
                            *(([(m.label, None)], v) for m, v in zip(with_finer, vec_finer))):
            n = len(names)
            for i, (name, _) in enumerate(names):
                X_t = (runs["train"][n + i] - runs["train"][i]) / st
                X_v = (runs["validation"][n + i] - runs["validation"][i]) / st
                if np.all(np.isfinite(X_t)) and np.all(np.isfinite(X_v)):
                    changes.append((name, X_t, X_v))
        fit = nuis.beside(D_t, D_v)  # the signature as a free column beside the bounded nuisances
        # per world: the size its data would be claimed at, against the critical value
        # grown with the change that world's data hold (the bootstrap resamples the round's
        # residual, the effect in it included); the size stated holds in every world
        per = []
        for name, X_t, X_v in changes:
            s_w = rnd.test.min_strength(
                D_t, D_v, growing_critical(rnd, D_t, D_v, critical, level, X_t, X_v, null=ev.cfg.null_residual),
                s_max, POWER,
                expected=lambda s, X_t=X_t, X_v=X_v: world_statistic(nuis, fit, X_t, X_v, s, ev.sigma2))
            if s_w is None:
                return None, name
            per.append((s_w, name))
        s, label = max(per, key=lambda x: x[0])  # the first of equals: the replay's own before a world
        found = cls.size_at(s)
        settled = abs(found - size) <= 0.05 * max(abs(size), 1e-12) or (found > cls.max_size and size >= cls.max_size)
        if step == 1 or (settled and not fine_w and not finer):
            break
        if not settled:
            size = min(found, cls.max_size)
    return found, label
