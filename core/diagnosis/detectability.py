"""Detectability: how large each effect kind would have to be for these data to claim it.

For every kind, its signature is simulated at the kind's reference size against the
last round's model and scaled (:meth:`core.simulation.effects.Effect.strength`); the
smallest size that the session's own noise replicates would claim at 80 % power is the
kind's ``min_size`` (SESSION_FORMAT.md ``detectability``): "not found above this size",
"cannot tell" when even the kind's ``max_size`` would not show, "found" or "confounded"
as the selection decided (:mod:`core.diagnosis.engine`). A "not found" size must also
hold whichever phantom of the model-form gap's plausible range made the data: the chosen
placement is re-solved with the kind's change simulated in each model-form world and the
largest size kept (:func:`core.diagnosis.sizing.world_min_size`). Split from the engine,
which holds the selection rounds; the size solve itself is :mod:`core.diagnosis.sizing`'s,
this module states each kind's answer from it and keeps the claims' bookkeeping
(withdrawn claims, kinds the palpation cannot show).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

from core.diagnosis.claims import train_validation_disagree
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence
from core.diagnosis.results import Detectability
from core.diagnosis.sizing import (POWER, fine_signature, growing_critical, least_informative, min_sizes, signatures,
                                   world_min_size)
from core.simulation.effects import EFFECT_KINDS, PhantomContext, effect_from_dict

if TYPE_CHECKING:  # the engine's round: its model, nuisances, held-out test and residuals
    from core.diagnosis.rounds import Round

# POWER and growing_critical: the size solve's, re-exported (core.diagnosis.sizing)
__all__ = ["detectability", "held_by_inversion", "unobservable", "unsettled", "undersized_claims", "with_dependents",
           "withdraw", "UNDERSIZED",
           "POWER", "growing_critical"]

UNDERSIZED = 0.1
"""A claim whose size is below this fraction of its own kind's ``min_size`` is withdrawn
(:func:`undersized_claims`). Measured on the saved lab diagnoses with a claim: the true
claims' size / min_size ran 0.49-17 (gravity without force 0.49-0.79, viscoelasticity
0.71), the false ones' 1.3e-5 and 0.0057 (compliant bases at 1e8 and 4.7e6 Pa/m, field
seed 71), or the kind could not be told at any size (two more such bases). Any factor
between 0.006 and 0.49 separates them; a decade below is the one stated."""



def _short(v):
    """A parameter for a sentence: floats to 4 significant digits (0.1 mm in m), lists of them too."""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(str(_short(x)) for x in v) + "]"
    return v


def _why(kind: str, cls, min_size: float | None, assumed: dict, palp: dict, answer: str) -> str:
    unit = cls.size_unit
    said = ", ".join(f"{k} {_short(v)}" for k, v in assumed.items()) if assumed else ""
    channels = "the surface and the probe force" if palp.get("force") else "the surface (no force recorded)"
    if min_size is None:
        # friction without slides and a probe radius from top presses without force never
        # get here: they are not fitted (:func:`unobservable`)
        hint = {
            "friction": "the slides were too short or too light to show it",
            "inclusion": "no press came near enough to it" if not palp.get("top_presses") else
                         "a stiffer spot under the presses did not change " + channels + " beyond the noise and the nuisances",
            "probe_radius": "its wider dent stays within the noise and the nuisances",
            "viscoelasticity": "the presses were too short or too slow to show relaxation",
            "time_offset": "the probe moved too little while the camera watched",
        }.get(kind, "its change of " + channels + " stays within the noise and the base model's nuisances")
        return (f"cannot tell from this data: even {cls.max_size:g} {unit}" + (f" ({said})" if said else "")
                + f" would not be claimed: {hint}")
    text = (f"an effect of {min_size:.3g} {unit} or more" + (f" ({said})" if said else "")
            + f" would have been claimed from {channels}")
    if answer == "found":
        return "found; " + text
    if answer == "confounded":
        return "confounded with another kind that explains the same residual; " + text
    return "not found: " + text


def _pick(sized: list[tuple[float | None, dict]], assume: str) -> tuple[float | None, dict] | None:
    """Of ``[(min_size or None, assumed), ...]`` the least detectable (None, "cannot tell",
    beats any size; else the largest) or the most detectable (the smallest size); None
    for an empty list."""
    if not sized:
        return None
    if assume == "least_detectable":
        return next((x for x in sized if x[0] is None), None) or max(sized, key=lambda x: x[0])
    told = [x for x in sized if x[0] is not None]
    return min(told, key=lambda x: x[0]) if told else sized[0]


def _directional(cls, placements) -> bool:
    """Whether a kind's detectability is stated over directions of a vector (the axes, each
    ``{"direction": unit vector}``), so that the least detectable direction of their span
    is tried beside them (:func:`core.diagnosis.sizing.least_informative`)."""
    return (cls.assume == "least_detectable" and len(placements) > 1
            and all(set(a) == {"direction"} for a in placements))


def _friction_blind(palp: dict) -> bool:
    return not palp.get("slides")


def _probe_radius_blind(palp: dict) -> bool:
    return not palp.get("force") and not palp.get("side_presses")


_BLIND = {
    # kind: (the palpation a set of sequences must lack to be blind to it, what would show it)
    "friction": (_friction_blind, "no press slid along the surface",
                 "friction leaves no trace in presses normal to a nearly incompressible gel, so it was not fitted "
                 "(a slide of a few millimetres in each would show it)"),
    "probe_radius": (_probe_radius_blind, "every press was into the top, without force",
                     "from the surface alone a larger sphere's dent is a deeper press's dent (and our contact's own "
                     "sinking), so it was not fitted (the probe force, or a press into a side face, in each would "
                     "show it)"),
}
"""Kinds that some palpation cannot show at any size: {kind: (blind(palpation) -> bool, what
the sequences lacked, why that hides the kind and what would show it)}."""


def unobservable(kinds, palp_train: dict, palp_validation: dict) -> dict[str, str]:
    """{kind: why} of the kinds of ``kinds`` that the palpation of these sequences cannot
    show at any size, so that they are not fitted and are answered "cannot tell". A kind is
    fitted only when the train sequences (to fit it) and the validation sequences (to judge
    it) both palpated in a way that shows it:

    - friction needs a slide: in presses normal to the surface of a nearly incompressible
      gel, friction between the probe and the surface barely changes the dent or the force
      (for Poisson's ratio 0.5, frictional and frictionless indentation coincide: Spence
      1975), so a fit of it there only soaks up the contact's and the mesh's model-form gap.
      Measured before this rule (field preset, force columns, every press normal to the
      top): mu 1.8 claimed on no-effect seed 902 and mu 2.0 in place of a hidden inclusion
      on seed 25, both at the bound of mu, 94-96 % of their held-out drop in the force channel.
    - the probe radius needs the probe force or a press into a side face: outside the
      contact, which the probe hides from the camera, a sphere of radius R pressed to depth
      d dents the surface like a point load ~ sqrt(R) d^(3/2) (Hertz; Johnson 1985, ch. 3),
      so from the surface alone a larger sphere is a deeper press, and a deeper press is what
      the replay's penalty contact (the sphere sinks into the replayed surface, issue 16)
      lacks. Measured before this rule: no-effect seed 941 (field preset, no force, three
      top presses) claimed a radius of 8.2 mm for 5 mm (T 2001 against a critical 311).

    Args:
        kinds: candidate kinds. palp_train, palp_validation:
            :func:`core.diagnosis.summary.palpation` of the train and the validation
            sequences.

    Returns:
        {kind: "cannot tell from this data: ..."} naming the sequences that lacked it.
    """
    out = {}
    for kind in kinds:
        if kind not in _BLIND:
            continue
        blind, lacked, why = _BLIND[kind]
        where = [r for r, p in (("train", palp_train), ("validation", palp_validation)) if blind(p)]
        if where:
            out[kind] = f"cannot tell from this data: {lacked} in the {' and '.join(where)} sequences; {why}"
    return out


def unsettled(e, alpha: float) -> str | None:
    """Why a kind that was neither claimed nor confounded cannot be bounded from its last
    fit, or None when it can ("not found" above its ``min_size``).

    Two cases make "not found" dishonest:

    - train and validation disagree: the fit on train moved the model by a change worth a
      claim (``reproduction["expected"] >= critical``) that validation did not confirm
      (``statistic < critical``): a model-form gap of the kind's shape, where the
      linearised power behind ``min_size`` does not hold;
    - the data lean towards it: its held-out drop is evidence at the round's level
      (``statistic > 0`` and ``p_value <= alpha``) short of a claim (Holm's procedure
      across the kinds, or its critical value beside the nuisances). Measured on field
      sessions before this rule: a viscoelastic phantom's fit at p 0.004 and a 0.15 s clock
      offset's at p 0.004 were both reported "not found" above a smaller size. Where the
      drop passed its critical value but the change its fit makes did not (not reproduced,
      :func:`core.diagnosis.claims.claim_check`), the reason says so: lab seed 78's hidden
      gravity (force, 4 x 6 s) explained 25799 against a critical 23722 with a change worth
      23026, and the text had read "a claim needs 23722".

    Args:
        e: the kind's evidence of the last round (the engine's ``_Evidence``: ``statistic``,
            ``critical``, ``p_value`` and ``reproduction``, chi2 units).
        alpha: the family-wise level of a selection round (``DiagnosisConfig.alpha``).
    """
    if train_validation_disagree(e.reproduction.get("expected", 0.0), e.critical, e.statistic):
        return (f"cannot tell from this data: the fit on the train sequences found a change worth "
                f"{e.reproduction['expected']:.0f} (chi2; a claim needs {e.critical:.0f}) but the "
                f"validation sequences gave it {e.statistic:.0f}: train and validation disagree on this "
                "kind (a model-form gap of its shape), so its size cannot be bounded from these data")
    if e.statistic > 0 and e.p_value <= alpha:
        said = (f"cannot tell from this data: its fit explained {e.statistic:.0f} (chi2) of the held-out "
                f"residual, evidence at the level {alpha:g} (p {e.p_value:.2g})")
        S = e.reproduction.get("expected")
        if not (math.isfinite(e.critical) and e.statistic >= e.critical):
            return (said + f", but a claim needs {e.critical:.0f} beside the other kinds and the base model's "
                    "nuisances: the data lean towards it without showing it")
        if S is not None and S < e.critical:
            return (said + f", above the {e.critical:.0f} a claim needs, but the change its fit makes is worth "
                    f"{S:.0f}, short of that: the held-out data ask for more of it than the train data fitted, "
                    "a residual of its shape that does not reproduce")
        return (said + f", above the {e.critical:.0f} a claim needs, but the round's selection did not claim it "
                "(Holm's procedure across the kinds, or a rival's nested test)")
    return None


def detectability(ev: Evidence, rnd: "Round", ctx: PhantomContext, cfg: DiagnosisConfig, cands: dict,
                  nulls: dict, palp: dict, *, claimed: list[str], confounded: list[list[str]],
                  refused: dict[str, str] | None = None, small: dict[str, str] | None = None,
                  progress=None, without=None, claimed_critical: dict[str, float] | None = None) -> dict:
    """{kind: :class:`Detectability`} for every kind of ``cfg.kinds`` against the round's model
    (a claimed kind against ``without(kind)``, when given: the round of the model without
    its claim; measured before: a compliant base claimed at 2.06e-5 m/Pa (lab 2e-5, 3 %
    off) was stated detectable from 1.79e-4, its signature taken on top of its own claim,
    a second base spring in parallel, and on another seed a claim 13 % off was withdrawn
    as far below that size).

    A kind in ``refused`` ({kind: why}: its held-out evidence passed but it made a channel
    significantly worse) is "cannot tell" with no size, whatever its signature's size. A
    kind in ``small`` ({kind: why}: its held-out drop passed but the change its fit makes
    is below what a claim needs, :func:`core.diagnosis.claims.claim_check`) is "not
    found" above its size, with that said in its ``why``. A kind whose last fit (``nulls``) moved the model by a change
    worth a claim (``S >= critical``) that the validation data did not confirm (``T <
    critical``) is "cannot tell" too: train and validation disagree on it, and the
    linearised power behind ``min_size`` does not hold there. So is a kind whose last fit
    showed held-out evidence at the level ``alpha`` (``p <= alpha``) without being claimed.

    A kind stated over directions (the robot offset: the three axes) is stated for the least
    detectable of the axes and of both ways along the direction of least Fisher information
    in their span (:func:`core.diagnosis.sizing.least_informative`), each direction's size in
    ``parameters["directions"]``: the axes alone said "not found above 1.95 mm" on field
    seed 92 (4 x 12 s, force), where that direction needs 2.57 mm in the replay's own
    physics (2.77 mm in its least favourable model-form world).

    The critical value of a kind is its null's quantile at ``alpha`` over the number of
    kinds and its searches (from the round's fit of it when it was tested, else from a
    fit along its signature alone). The model-form gap enters through the worlds
    (:func:`core.diagnosis.sizing.world_min_size`: the kind's change simulated in each, the weakest kept), as
    a claim must still explain its critical value in each world that explains part of the
    residual (:func:`core.diagnosis.rounds.beyond_verdict`); until 2026-11-29 the bar was the
    best world's drop itself (on a dome with force columns 7330 chi2, mostly the whole
    phantom's force, against a hidden stiff inclusion fit's 4379). ``progress(i, kind)``,
    when given, is called before the i-th kind.

    A claimed kind's critical value is the one its claim needed (``claimed_critical``:
    {kind: the critical value of the round that claimed it}), not one drawn from the
    residual of the model without it, which holds the claimed effect itself: measured on
    field seed 11 with a 5 mm robot offset (no force), a vertical offset's null from that
    residual put the critical value at 1852 (chi2) where the claim had needed 256, and the
    claim, at 5.35 mm, was withdrawn as below its own detectability.
    """
    out = {}
    in_group = {k for g in confounded for k in g}
    n_kinds = len(cfg.kinds)
    refused = dict(refused or {})  # the caller's, and the kinds train and validation disagree on
    for i, kind in enumerate(cfg.kinds):
        if progress is not None:
            progress(i, kind)
        cls = EFFECT_KINDS[kind]
        # a claimed kind's size against the model without it: added on top of its own claim,
        # its signature is another change (a second base spring in parallel stiffens the base)
        here = without(kind) if kind in claimed and without is not None else rnd
        options = cls.assumptions(ctx)  # once: an inclusion's ask the surface about every press
        e = nulls.get(kind)
        if kind not in claimed and kind not in in_group and kind not in refused and e is not None:
            reason = unsettled(e, cfg.alpha)
            if reason is not None:
                refused[kind] = reason
        if kind in refused and kind not in claimed and kind not in in_group:
            # no size is stated, so none is simulated
            params = dict(options[0]) if options else {}
            out[kind] = Detectability(kind, None, params, refused[kind], "cannot_tell", cls.size_unit)
            continue
        searches = cands[kind].searches
        level = cfg.alpha / max(n_kinds * searches, 1)
        # the round's fit of the kind gives one null for every placement: its critical value once
        shared = max(here.test.critical(e.null, level), 0.0) if e is not None and e.null.size > 1 else None
        if kind in claimed and kind in (claimed_critical or {}) and math.isfinite(claimed_critical[kind]):
            shared = max(float(claimed_critical[kind]), 0.0)

        bars = {}  # repr(assumed): the statistic a claim of that placement needed

        def sizes_of(placements):
            """[(min_size or None, assumed)] of the ``placements`` whose signature did not
            diverge, their signatures simulated together (:func:`core.diagnosis.sizing.min_sizes`)."""
            sigs = signatures(ev, here, [cls.sized(cls.reference_size, ctx, **a).to_dict() for a in placements],
                              fine=fine_signature(ev, cls))
            if _directional(cls, placements):
                # the direction the test sees least, of the span of the axes, beside them
                worst = least_informative(here, sigs, [a["direction"] for a in placements],
                                          cls.strength(cls.reference_size), ev.sigma2)
                if worst is not None:  # both ways: through the contact, +u and -u change the data differently
                    u, (d_t, d_v) = worst
                    placements = list(placements) + [{"direction": u}, {"direction": [-v for v in u]}]
                    sigs = list(sigs) + [(d_t, d_v), (-d_t, -d_v)]
            jobs, first = [], []
            for assumed, sig in zip(placements, sigs):
                critical = shared
                if critical is None:
                    if sig is None:
                        continue
                    critical = max(here.test.critical(here.test.null(sig[0][:, None], sig[1][:, None]), level), 0.0)
                bars[repr(assumed)] = critical
                jobs.append((assumed, critical, level))
                first.append(sig)
            sizes = min_sizes(ev, here, cls, ctx, jobs, first)
            return [(None if size is None or size > cls.max_size else size, assumed)
                    for size, (assumed, _, _) in zip(sizes, jobs)]

        sized = sizes_of(options)
        best = _pick(sized, cls.assume)
        size, assumed = best if best is not None else (None, {})
        world, replay_size = "", size
        if size is not None and kind not in claimed and kind not in in_group:
            # "not found above min_size" must hold whichever phantom of the model-form gap's
            # plausible range made the data, not only the replay's own physics
            size, world = world_min_size(ev, here, cls, ctx, assumed, size, bars[repr(assumed)], level)
            size = None if size is None or size > cls.max_size else max(size, replay_size)
        answer = ("found" if kind in claimed else "confounded" if kind in in_group
                  else "cannot_tell" if size is None else "not_found")
        params = dict(assumed)
        if world and (size is None or size > replay_size * 1.05):
            params["model_form_world"] = world
            params["replay_min_size"] = replay_size
        if cls.assume == "least_detectable" and len(options) > 1:
            params["note"] = f"the least detectable of the {cls.assumed_over} tried"
            if _directional(cls, options):
                params["note"] += " (the axes and both ways along the direction of least Fisher information in their span)"
                params["directions"] = [{**a, "min_size": s} for s, a in sized]
        beside_text = ""
        if cls.assume == "most_detectable" and best is not None:
            params["placements"] = [{**a, "min_size": s} for s, a in sized]
            near = cls.beside(ctx, assumed) if answer == "not_found" else ()
            if near:
                # how far a press's reach extends: the least detectable of the placements
                # one beside_distance to the side of the best one
                far = _pick(sizes_of(list(near)), "least_detectable")
                far_size = None if far is None else far[0]
                params["beside"] = {"distance": cls.beside_distance, "min_size": far_size}
                if far_size is not None:  # held to the model-form worlds as the best placement is
                    far_world, _ = world_min_size(ev, here, cls, ctx, far[1], far_size, bars[repr(far[1])], level)
                    far_world = None if far_world is None or far_world > cls.max_size else max(far_world, far_size)
                    params["beside"].update(min_size=far_world, replay_min_size=far_size)
                    far_size = far_world
                beside_text = (f"; {cls.beside_distance * 1e3:.0f} mm to the side of it "
                               + (f"{far_size:.3g} {cls.size_unit}" if far_size is not None else "it could not be told at any size"))
        why = _why(kind, cls, size, assumed, palp, answer)
        if "model_form_world" in params:
            why += (f"; stated for a phantom with {world} (within the model-form gap's plausible range), where its "
                    f"change of the data is weaker or of another shape than the replay's own"
                    + (f" (in the replay's own physics {replay_size:.3g} {cls.size_unit})" if replay_size is not None else ""))
        if cls.assume == "most_detectable" and (len(sized) > 1 or beside_text):
            told = [s for s, _ in sized if s is not None]
            spread = (f": {min(told):.3g}-{max(told):.3g}" if len(told) > 1 else "") + (
                f", {len(sized) - len(told)} of them could not be told" if len(told) < len(sized) else "")
            why += f" (best-placed of {len(sized)} placements under the presses{spread}{beside_text})"
        if kind in (small or {}) and answer != "found":
            why += f"; its fit passed on held-out data but {small[kind]}: a residual of its shape that does not reproduce"
        out[kind] = Detectability(kind, size, params, why, answer, cls.size_unit)
    return out


def undersized_claims(effects: dict[str, dict], det: dict, ctx: PhantomContext) -> dict[str, str]:
    """{kind: why} of the claims that their own kind's signature could not have made.

    ``min_size`` of a claimed kind is the smallest size of it that these data would have
    claimed (:func:`detectability`, in the replay's own physics). A claim far below that
    (below :data:`UNDERSIZED` times it), or of a kind that could not be told at any
    size, was not made by the kind's signature: its fit absorbed a residual of another
    shape (a model-form gap: a compliant base at 1e8 Pa/m, nearly a fixed one, bends the
    force-depth curve of a stiffening phantom by at most 1 %, which a force channel of 2 N at
    7.6 mN noise weighs at 2.9e6 chi2). Such a claim is withdrawn.

    Args:
        effects: {kind: its claimed effect dict}. det: :func:`detectability`'s result.
        ctx: the phantom's context (sizes of effects).
    """
    out = {}
    for kind, effect in effects.items():
        d = det.get(kind)
        if d is None:
            continue
        size = float(effect_from_dict(dict(effect)).size(ctx))
        unit = EFFECT_KINDS[kind].size_unit
        if d.min_size is None:
            out[kind] = (f"withdrawn: claimed at {size:.3g} {unit}, but no size of this kind up to its largest "
                         f"plausible one would have been claimed from these data by its own signature; its fit took up "
                         f"a residual of another shape (a model-form gap), so it cannot be told")
        elif size < UNDERSIZED * d.min_size:
            out[kind] = (f"withdrawn: claimed at {size:.3g} {unit}, below a tenth of the {d.min_size:.3g} {unit} that "
                         f"these data would have needed to claim it by its own signature; its fit took up a residual "
                         f"of another shape (a model-form gap), so it cannot be told")
    return out


def with_dependents(claimed: list, whys: dict[str, str]) -> dict[str, str]:
    """``whys`` with the claims made on top of a withdrawn one: each round of the selection
    fits its candidates with the causes claimed before it in the model, so a claim of a
    later round than a withdrawn one was judged against a model holding a cause that does
    not stand, and is withdrawn with it. (A new selection without the withdrawn kind could
    recover it; not done: it costs the rounds again.) Measured (with a null drawn from each
    candidate's own residual, tried at stop 51): a hidden compliant base claimed in round
    0 and withdrawn below its own detectability, and a 15 mm probe radius claimed in
    round 1 on top of it, left standing.

    Args:
        claimed: ``[(fit space, fit, report)]`` of the claimed causes (``report.round``:
            the selection round that claimed it). whys: {kind: why} of the claims withdrawn.
    """
    if not whys:
        return whys
    out = dict(whys)
    first = min((rep.round, c.kind) for c, _, rep in claimed if c.kind in whys)
    for c, _, rep in claimed:
        if c.kind not in out and rep.round is not None and rep.round > first[0]:
            out[c.kind] = (f"withdrawn: claimed in round {rep.round} on top of {first[1].replace('_', ' ')}, "
                           f"whose claim was withdrawn ({whys[first[1]]})")
    return out


def held_by_inversion(det: dict, inverted: list[str]) -> dict:
    """``det`` ({kind: :class:`Detectability`}) with every "not found" answer turned to
    "cannot tell" when the base model's replay turned tetrahedra inside out under the probe
    on the sequences ``inverted`` (names; none: ``det`` unchanged).

    A "not found above min_size" is the replay's own change of the data at that size,
    simulated where the probe pressed; where the replay inverted elements there, that
    change is no phantom's (the corotational law has no resistance to inversion, and a
    neo-Hookean mesh that inverts is too coarse for the presses), so it bounds nothing.
    Measured on the lab's dome with a hidden stiff inclusion (ratio 6, 10 mm; 4 x 12 s,
    force, `scenario("inclusion", 3, shape="dome")`): the corotational replay inverted up
    to 18 tetrahedra and answered "not found above ratio 2.16"; the neo-Hookean replay, which
    inverted none, fitted the inclusion 0.3 mm from its centre and answered "cannot tell".
    The size the replay gave is kept in ``parameters["inverted_replay_min_size"]``; claimed
    ("found"), confounded and already "cannot tell" kinds are left as they are.

    Args:
        det: the detectability statements. inverted: the train and validation sequences
            whose base-model replay inverted elements (``FieldRun.inverted`` > 0).

    Returns:
        A new dict of the same kinds.
    """
    if not inverted:
        return det
    out = {}
    for kind, d in det.items():
        if d.answer != "not_found":
            out[kind] = d
            continue
        out[kind] = replace(
            d, min_size=None, answer="cannot_tell", parameters={**d.parameters, "inverted_replay_min_size": d.min_size},
            why=(f"cannot tell from this data: the replay turned tetrahedra inside out under the probe on "
                 f"{', '.join(inverted)}, so its change of the data there is no phantom's, and the "
                 f"{d.min_size:.3g} {d.unit} it would have claimed bounds nothing (replay with a law or a mesh "
                 f"that does not invert: see the diagnosis's notes)"))
    return out


def withdraw(claimed: list, reports: list, det: dict | None, whys: dict[str, str], basis: str,
             stated: dict[str, str] | None = None) -> tuple[list, list, dict | None, list, list[str]]:
    """Claims taken back after they were made: below their own detectability
    (:func:`undersized_claims`) or, refitted in the model-form worlds, holding no effect in
    their interval (:func:`core.diagnosis.worlds.absence_within`).

    Args:
        claimed: ``[(fit space, fit, report)]`` of the claimed causes. reports: every
            candidate's :class:`~core.diagnosis.results.CauseReport`. det: {kind:
            :class:`Detectability`}, or None (not computed). whys: {kind: why} of the claims
            to withdraw. basis: how their fits are described beside E. stated: {kind: why}
            for ``det`` when it should read otherwise than ``whys``.

    Returns:
        (the claims that stand, ``reports`` with the withdrawn ones unclaimed, ``det`` with
        each withdrawn kind "cannot tell" and its reason, ``[(kind, effect dict, basis)]`` of
        their fits as unclaimed causes for E (:func:`core.diagnosis.youngs.unexcluded_youngs`),
        a note for diagnosis.json per withdrawn kind).
    """
    if not whys:
        return claimed, reports, det, [], []
    stated = stated or whys
    if det is not None:
        det = {k: Detectability(k, None, dict(d.parameters), stated[k], "cannot_tell", d.unit) if k in whys else d
               for k, d in det.items()}
    gone = [(c.kind, f.effect, basis) for c, f, _ in claimed if c.kind in whys]
    notes = [f"the claim of {kind.replace('_', ' ')} was {why}" for kind, why in whys.items()]
    return ([t for t in claimed if t[0].kind not in whys], [replace(r, claimed=False) if r.kind in whys else r for r in reports],
            det, gone, notes)
