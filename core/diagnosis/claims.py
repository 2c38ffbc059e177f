"""Whether a kind that passed the held-out test may be claimed: the checks against the model-form gap.

The held-out test (:class:`core.diagnosis.inference.HeldOutTest`, Holm's procedure across
the kinds) treats the session's residual as noise. A real session's model-form gap (law,
mesh, contact, damping, geometry) is not noise: it repeats in every block, and a wrong kind
can fit part of it on train and gain on validation. The checks here need no simulation;
they read the held-out residual before and after the candidate's change:

- :func:`reproduction`: the held-out drop ``T`` against the worth ``S`` of the change the
  fitted candidate itself makes;
- :func:`channel_worsening`: whether the candidate makes a channel of the held-out data
  (top face, side faces, force) significantly worse (a self-normalised wild cluster t);
- :func:`claim_check`: the verdict from both (reproduced at its fitted size, no channel
  worse);
- :func:`train_validation_disagree`: train asked for a change worth a claim that
  validation did not confirm (answered "cannot tell", not "not found").

The third check, in the model-form worlds, needs simulations:
:func:`core.diagnosis.model_form.beyond_model_form`.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["channel_worsening", "claim_check", "reproduction", "train_validation_disagree"]


def channel_worsening(before: np.ndarray, after: np.ndarray, channels: dict[str, np.ndarray],
                      blocks: np.ndarray, level: float, sigma2: float = 1.0) -> dict[str, dict]:
    """Does a candidate make any channel of the held-out data significantly worse?

    A cause that is really there improves, in expectation, every channel it changes: with
    ``before`` the held-out residual without it and ``after`` with it, the drop of a
    channel's chi-square is ``d = |before|^2 - |after|^2 = -2 sum_i D_i m_i`` (``D`` the
    change ``after - before``, ``m`` their mean), which is ``+|D|^2`` plus noise when the
    cause is real and ``-|D|^2`` plus noise when it is not. A model-form gap that one
    channel shows (a force the contact law misses) can be fitted by a wrong cause that
    then pays for it in another channel (the surface it moves where nothing moved): the
    gain of one channel bought with a loss in another. The loss is judged by a
    self-normalised wild cluster statistic (the residual is correlated within a block,
    blocks are independent): with ``b_k = sum_{i in block k} D_i m_i``,
    ``t = sum_k b_k / sqrt(sum_k b_k^2)``, compared with Student's t at ``K - 1`` degrees
    of freedom (``K`` blocks with a change; Ibragimov & Mueller 2010 for t-tests on few
    clusters). ``t`` is at most ``sqrt(K)``, when every block is worse by the same amount.

    Args:
        before, after: (L,) held-out residual vectors (any units; ``sigma2`` their
            variance unit for the reported chi-square drop).
        channels: {name: (L,) bool mask}; a channel the candidate does not change is skipped.
        blocks: (L,) int64 block of each entry.
        level: one-sided level of the test of each channel (0 < level < 0.5).
        sigma2: the variance that makes ``|r|^2 / sigma2`` a chi-square.

    Returns:
        {channel: {"delta_chi2": d, "t": t, "critical": t quantile, "worse": bool}} for
        every channel with a change in at least two blocks.

    Raises:
        ValueError: mismatched shapes.
    """
    from scipy.stats import t as student

    before, after, blocks = np.asarray(before, float), np.asarray(after, float), np.asarray(blocks)
    if before.shape != after.shape or before.shape != blocks.shape:
        raise ValueError(f"channel_worsening: shapes {before.shape}, {after.shape}, {blocks.shape} differ")
    out = {}
    D, m = after - before, 0.5 * (after + before)
    for name, mask in channels.items():
        mask = np.asarray(mask, bool)
        if not np.any(D[mask] != 0) or not np.all(np.isfinite(D[mask])):
            continue
        _, inv = np.unique(blocks[mask], return_inverse=True)
        b = np.bincount(inv, weights=D[mask] * m[mask])
        K = int(np.count_nonzero(b))
        if K < 2:
            continue
        t = float(b.sum() / math.sqrt(float(b @ b)))
        crit = float(student.ppf(1.0 - level, K - 1))
        out[name] = {"delta_chi2": float(-2.0 * b.sum() / sigma2), "t": t, "critical": crit, "worse": bool(t > crit)}
    return out


def train_validation_disagree(worth: float, critical: float, statistic: float) -> bool:
    """Whether train and validation disagree on a kind: the change its fit made on train
    was worth a claim (``worth``, :func:`reproduction`'s ``expected``, at least the finite
    ``critical``) and the held-out drop ``statistic`` (T) did not confirm it (chi2 units).
    Such a kind's size cannot be bounded from the data: it is answered "cannot tell"
    (:func:`core.diagnosis.detectability.unsettled`) and E's interval holds it at its train
    fit (:func:`core.diagnosis.youngs.unexcluded_effects`)."""
    return math.isfinite(critical) and worth >= critical > statistic


def reproduction(before: np.ndarray, after: np.ndarray, sigma2: float = 1.0) -> dict:
    """The held-out drop against the change the fitted candidate itself makes.

    If the data held exactly the fitted effect, the held-out drop ``T = |before|^2 -
    |after|^2`` would be ``S = |D|^2`` (``D = after - before``, the candidate's change)
    plus the noise term ``-2 after . D``. A drop far above ``S`` means the validation
    data ask for ``(T / S + 1) / 2`` times what the train data fitted (train and
    validation disagree: a gap that looks like the kind here, or a fit stuck short of
    its optimum); :func:`claim_check` refuses a claim whose ``S`` is below the critical value.

    Args:
        before, after: (L,) held-out residual vectors.
        sigma2: the variance that makes ``|r|^2 / sigma2`` a chi-square.

    Returns:
        {"expected": S, "observed": T}, chi2 units.
    """
    before, after = np.asarray(before, float), np.asarray(after, float)
    D = after - before
    return {"expected": float(D @ D / sigma2), "observed": float((before @ before - after @ after) / sigma2)}


def claim_check(statistic: float, critical: float, reproduced: dict, channels: dict) -> tuple[str, str] | None:
    """Whether a kind whose held-out drop passed Holm's procedure may be claimed, before the
    model-form worlds are asked (:func:`core.diagnosis.rounds.beyond_verdict`).

    Two checks against the model-form gap, which the wild bootstrap treats as noise
    although it repeats in every block:

    1. **Reproduced at its fitted size.** The change the fit makes must itself be worth a
       claim: ``S = reproduced["expected"] >= critical`` (an effect of exactly the fitted
       size would reach the critical value without help from noise). A drop ``T`` far
       above ``S`` means the validation data ask for ``(T / S + 1) / 2`` times what the
       train data fitted: a residual of the kind's shape that does not reproduce between
       the two.
    2. **No channel made worse** (:func:`channel_worsening`): a gain in one channel bought
       with a significant loss in another is the gap, not the kind.

    A third, in the model-form worlds, needs simulations and is run by the caller
    (:func:`core.diagnosis.model_form.beyond_model_form`): the fitted cause, added to each
    phantom of the gap's plausible range that explains part of the residual, must still
    explain its critical value there.

    Args:
        statistic: the held-out drop T, chi2. critical: the T the claim needed, chi2.
        reproduced: :func:`reproduction` of the candidate. channels: :func:`channel_worsening` of it.

    Returns:
        None when the claim stands, else ``(reason, why)`` with reason ``"channel_worse"``
        (answer "cannot tell") or ``"not_reproduced"`` (answer "not found" above its size).
    """
    worse = [c for c, v in channels.items() if v["worse"]]
    if worse:
        gains = [c for c, v in channels.items() if v["delta_chi2"] > 0]
        return ("channel_worse",
                f"cannot tell from this data: its fit explained a residual of its shape in "
                f"{' and '.join(gains) or 'no channel'} but made the held-out {' and '.join(worse)} "
                f"significantly worse (" + ", ".join(f"{c} t = {channels[c]['t']:.2f}" for c in worse)
                + "): the base model's form gap explains that residual as well as this kind")
    S = float(reproduced.get("expected", math.inf))
    if S < critical:
        ask = 0.5 * (statistic / max(S, 1e-12) + 1.0)
        return ("not_reproduced",
                f"its fitted change is worth {S:.0f} (chi2) against a critical value of {critical:.0f}; the held-out "
                f"drop {statistic:.0f} asks for {ask:.1f} times that change")
    return None
