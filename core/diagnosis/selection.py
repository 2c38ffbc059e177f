"""Which significant kind a selection round claims, or which kinds it reports as confounded.

One round of the diagnosis's greedy forward selection (:mod:`core.diagnosis.engine`) ends
with every candidate kind's held-out drop ``T`` (chi2), its p-value and the claim checks
(:func:`core.diagnosis.claims.claim_check`). :func:`choose` decides from those:

1. The passing kind with the largest drop is the best.
2. **A larger explanation that could not be confirmed.** A kind that explained more
   (significant by Holm's procedure, but its fitted change too small to claim: the
   ``not_reproduced`` verdict) shadows the best unless the best adds significant
   held-out evidence on top of that kind's fit. When it does not, the residual has two
   explanations, one too weak to claim and one that lives off the other's absence: both
   are reported as confounded and neither is claimed. (Measured on a randomised-lab
   session hiding gravity, with force: gravity dropped the held-out chi-square by 7560
   with a fitted change worth 6969 against a critical 7376, and a compliant base, at a
   drop of 3004, was claimed in its place.)
3. **Rivals.** A passing kind with at least 0.8 of the best's drop and a similar change
   of the held-out data (cosine above 0.9) is compared by nested tests: the one that adds
   what the other cannot is kept; when neither adds to the other, both are confounded.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

__all__ = ["choose", "RIVAL_SHARE", "RIVAL_COSINE"]

RIVAL_SHARE = 0.8
"""A rival explains at least this share of the best's held-out drop."""
RIVAL_COSINE = 0.9
"""... with a change of the held-out data at least this similar (cosine)."""


def choose(passing: Sequence[str], unconfirmed: Sequence[str], statistic: dict[str, float],
           change: Callable[[str], np.ndarray], adds: Callable[[str, str], bool]) -> tuple[str | None, list[str]]:
    """The kind a round claims, or the kinds it reports as confounded.

    Args:
        passing: the kinds that passed every claim check (non-empty).
        unconfirmed: kinds significant by Holm's procedure whose fitted change is below a
            claim (they cannot be claimed themselves).
        statistic: every kind's held-out drop ``T``, chi2.
        change: ``change(kind)`` (M,) float64, what the kind's fit changes in the
            validation data (field and force residuals, in the statistic's units).
        adds: ``adds(kind, given)`` True when ``kind`` adds significant held-out evidence
            on top of ``given``'s fit (a nested test; it costs a fit, so it is asked only
            where needed).

    Returns:
        ``(kind, [])`` to claim ``kind``, or ``(None, group)`` with the confounded kinds
        (two or more, the best first) when the round claims nothing and stops.

    Raises:
        ValueError: ``passing`` is empty.
    """
    if not passing:
        raise ValueError("choose: no kind passed the round's checks")
    ranked = sorted(passing, key=lambda k: -statistic[k])
    best = ranked[0]
    for k in sorted(unconfirmed, key=lambda k: -statistic[k]):
        if statistic[k] > statistic[best] and not adds(best, k):
            return None, [best, k]
    ref = change(best)
    rivals = []
    for k in ranked[1:]:
        if statistic[k] < RIVAL_SHARE * statistic[best]:
            continue
        other = change(k)
        cos = float(ref @ other / (np.linalg.norm(ref) * np.linalg.norm(other) + 1e-30))
        if cos > RIVAL_COSINE:
            rivals.append(k)
    survivors = [best]
    for k in rivals:
        best_over_k, k_over_best = adds(best, k), adds(k, best)
        if k_over_best and not best_over_k:
            survivors = [k]  # the rival explains what the best cannot
        elif not best_over_k and not k_over_best:
            survivors.append(k)  # neither adds to the other: confounded
    if len(survivors) > 1:
        return None, survivors
    return survivors[0], []
