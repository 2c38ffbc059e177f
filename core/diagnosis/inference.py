"""Held-out claims with a stated false-claim rate, and the smallest effect that would be claimed.

**The statistic.** A candidate kind is fitted on the train sequences (with the base
model's nuisance directions, :mod:`core.diagnosis.nuisance`, fitted beside it) and judged
on the validation sequences, which its fit never saw: ``T`` is the drop of the
validation chi-square from the model of the round to the model with the candidate, both
with their nuisance coefficients carried over from train. Noise alone gives a ``T`` near
or below zero; a cause that holds on held-out data gives a large one.

**Its null distribution comes from the session itself**, resampled from the residual the
candidate's fit leaves (``DiagnosisConfig.null_residual`` "candidate", :meth:`HeldOutTest.under`;
or from the round's, which holds a real effect and grows with it: :meth:`HeldOutTest.null_with_effect`). Under "this kind is absent",
linearised at the fit, ``T`` is a function of the train and validation noise:
``theta = (J'J)^-1 J' e_t`` (``J`` the candidate's signature on train without its
nuisance part), ``r0 = e_v - N_v N_t^+ e_t`` (the held-out residual), and
``T = (2 r0' G theta - theta' G'G theta) / sigma^2`` with ``G = J_v - N_v N_t^+ J_t`` its
held-out signature. The noise is resampled by a wild cluster bootstrap of the session's
own residuals (Cameron, Gelbach & Miller 2008): each block of frames (1 s of one
sequence: the residual is correlated within a poke) keeps its residuals, multiplied by
one random weight of Webb's six-point distribution (Webb 2023, for few clusters). This
keeps the session's noise level, its heteroscedasticity (points per bin, faces, force
axes) and its within-block correlation, and removes any alignment with the signature.
The p-value of a kind is the share of replicates at or above the observed ``T`` (beyond
the last ten replicates, the tail of a generalised Pareto distribution fitted to the
largest ones, :func:`tail_p_value`: a count cannot go below ``1 / (R + 1)``), times
the number of places its fit searched (an inclusion's starting locations: a
look-elsewhere factor), and the kinds of a round are tested together by Holm's (1979)
step-down procedure at the family-wise rate ``alpha``. A null whose median ``m`` lies below
zero is shifted up by ``2|m|`` (mirrored about zero): where the candidate's signature
differs between train and validation (a probe radius seen on the side pokes of one
sequence only), fitting noise on train costs much on validation, the null sits far below
zero, and a small positive ``T`` would beat it without being evidence of anything
(measured on a randomised-lab session with friction hidden: T = 29 against a critical
value of -569 claimed a 9 mm probe). Chance fits that cost ``|m|`` could as well gain it.

**Detectability.** For an effect of strength ``s`` along a signature ``D`` (simulated at
the kind's reference size and scaled, :meth:`core.simulation.effects.Effect.strength`),
the same statistic is computed on ``e + s D``; the smallest size it would claim is the
``s`` at which 80 % of the replicates reach the kind's critical value (the quantile of
its null at ``alpha`` over the number of kinds, Bonferroni's bound of Holm's first step):
the minimum detectable effect at 80 % power. The size is that of a fit along the
signature itself (one parameter); a fit with more parameters needs a little more.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from core.diagnosis.nuisance import Nuisance

__all__ = ["HeldOutTest", "cluster_robust_covariance", "holm", "holm_adjusted", "tail_p_value", "tail_quantile",
           "webb_weights"]

_WEBB = np.array([-math.sqrt(1.5), -1.0, -math.sqrt(0.5), math.sqrt(0.5), 1.0, math.sqrt(1.5)])


def webb_weights(rng: np.random.Generator, replicates: int, clusters: int) -> np.ndarray:
    """(replicates, clusters) float64 weights of Webb's six-point distribution (mean 0,
    variance 1), for a wild cluster bootstrap with few clusters."""
    return _WEBB[rng.integers(0, 6, size=(replicates, clusters))]


TAIL_MIN_COUNT = 10
"""Below this many null replicates at or above an observed statistic (or expected above a
quantile), the p-value and the quantile come from the null's fitted tail (Knijnenburg et
al. 2009), not from the count."""

TAIL_EXCEEDANCES = 250
"""Replicates in the fitted tail (the largest ones; fewer, at least 50, for a small null)."""


def _tail(null: np.ndarray):
    """``(threshold, exceedances share, (shape, scale))`` of a generalised Pareto
    distribution fitted by maximum likelihood (``scipy.stats.genpareto``, location 0) to the
    excesses of the largest :data:`TAIL_EXCEEDANCES` replicates of ``null`` over the next
    one, its shape at least 0 (the exponential tail otherwise); None when the null is too
    small (fewer than 500 replicates) or the fit fails."""
    from scipy import stats

    x = np.asarray(null, dtype=np.float64).ravel()
    n_exc = min(TAIL_EXCEEDANCES, x.size // 10)
    if n_exc < 50:
        return None
    top = np.partition(x, x.size - n_exc - 1)[x.size - n_exc - 1:]
    t = float(np.min(top))
    exc = np.sort(top)[1:] - t
    if not np.any(exc > 0):
        return None
    with np.errstate(all="ignore"):
        try:
            c, _, scale = stats.genpareto.fit(exc, floc=0.0)
        except (ValueError, RuntimeError, FloatingPointError):
            return None
    if not (math.isfinite(c) and math.isfinite(scale) and scale > 0):
        return None
    # the null of T is a quadratic form in the noise: an exponential tail (shape 0) in
    # theory. A fitted shape below 0 (a bounded tail; its standard error is ~0.06 at 250
    # excesses) gave p-values 5x too small at 1e-4 on a chi-square null, so the tail is
    # the exponential one (its maximum-likelihood scale: the mean excess) unless the fit
    # says heavier: the more conservative of the two
    if c <= 0.0:
        c, scale = 0.0, float(np.mean(exc))
    return t, n_exc / x.size, (float(c), float(scale))


def tail_p_value(null: np.ndarray, observed: float) -> float:
    """P(T >= observed) under the replicates ``null`` (R,).

    The Monte-Carlo p-value ``(1 + #{null >= observed}) / (R + 1)`` while at least
    :data:`TAIL_MIN_COUNT` replicates reach ``observed``; beyond, where the count says
    little and cannot go below ``1 / (R + 1)``, the tail of a generalised Pareto
    distribution fitted to the largest replicates (Knijnenburg, Wessels, Reinders &
    Shmulevich 2009, "Fewer permutations, more accurate P-values", Bioinformatics 25:
    i161). Without it, a kind with a look-elsewhere factor ``k`` could never pass Holm's
    first step at ``alpha / m`` when ``k / (R + 1) > alpha / m`` (an inclusion searched
    from more than 12 presses among 8 kinds with 9999 replicates, at ``alpha`` 0.01).
    """
    x = np.asarray(null, dtype=np.float64).ravel()
    count = int(np.sum(x >= observed))
    p_count = (1.0 + count) / (x.size + 1.0)
    if count >= TAIL_MIN_COUNT:
        return p_count
    tail = _tail(x)
    if tail is None or observed <= tail[0]:
        return p_count
    from scipy import stats

    t, share, (c, scale) = tail
    return float(share * stats.genpareto.sf(observed - t, c, loc=0.0, scale=scale))


def tail_quantile(null: np.ndarray, level: float) -> float:
    """The ``1 - level`` quantile of the replicates ``null`` (R,): the empirical one
    ("higher") while at least :data:`TAIL_MIN_COUNT` replicates are expected above it,
    else the fitted generalised Pareto tail's (:func:`tail_p_value`), so that a level
    below ``1 / R`` still has its own critical value rather than the largest replicate."""
    x = np.asarray(null, dtype=np.float64).ravel()
    level = min(max(float(level), 0.0), 1.0)
    if level * x.size >= TAIL_MIN_COUNT:
        return float(np.quantile(x, 1.0 - level, method="higher"))
    tail = _tail(x)
    if tail is None:
        return float(np.quantile(x, 1.0 - level, method="higher"))
    from scipy import stats

    t, share, (c, scale) = tail
    return float(t + stats.genpareto.isf(min(level / share, 1.0), c, loc=0.0, scale=scale))


def holm(p: dict[str, float], alpha: float) -> set[str]:
    """The hypotheses Holm's (1979) step-down procedure rejects at family-wise rate ``alpha``.

    Args:
        p: {name: p-value}.

    Returns:
        The names whose null ("this kind is absent") is rejected.
    """
    order = sorted(p, key=lambda k: p[k])
    m = len(order)
    out: set[str] = set()
    for i, k in enumerate(order):
        if p[k] > alpha / (m - i):
            break
        out.add(k)
    return out



def holm_adjusted(p: dict[str, float]) -> dict[str, float]:
    """Holm-adjusted p-values (the smallest family-wise rate at which each is rejected)."""
    order = sorted(p, key=lambda k: p[k])
    m = len(order)
    out, run = {}, 0.0
    for i, k in enumerate(order):
        run = max(run, min(1.0, (m - i) * p[k]))
        out[k] = run
    return out


def cluster_robust_covariance(J: np.ndarray, residual: np.ndarray, blocks: np.ndarray) -> np.ndarray | None:
    """Cluster-robust (sandwich) covariance of a least-squares fit's variables.

    ``(J'J)^-1 (sum_k g_k g_k') (J'J)^-1 K / (K - 1)`` with ``g_k = sum_{i in block k} J_i r_i``
    (Liang & Zeger 1986; the CR1 form of Cameron & Miller 2015, Sec. IV): the spread of a
    Gauss-Newton estimate when the residual is correlated within blocks (here 1 s of one
    sequence, the blocks of the held-out test's bootstrap) and independent between them.
    The textbook ``sigma^2 (J'J)^-1`` assumes every entry independent; a model-form gap
    leaves residuals that share a sign over a whole poke, and that covariance is then
    too narrow by about the square root of the entries per block.

    Args:
        J: (L, n) float Jacobian of the residual at the fit.
        residual: (L,) float residual at the fit (same units as the fit's misfit).
        blocks: (L,) int block of each entry.

    Returns:
        (n, n) float64 covariance, or None with fewer than two blocks or a singular ``J'J``.

    Raises:
        ValueError: shapes that do not agree.
    """
    J, r, b = np.asarray(J, dtype=np.float64), np.asarray(residual, dtype=np.float64), np.asarray(blocks)
    if J.ndim != 2 or r.shape != (J.shape[0],) or b.shape != r.shape:
        raise ValueError(f"cluster_robust_covariance: J {J.shape}, residual {r.shape} and blocks {b.shape} do not agree")
    _, inv = np.unique(b, return_inverse=True)
    K = int(inv.max()) + 1 if inv.size else 0
    if K < 2:
        return None
    try:
        bread = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    g = _block_sums(J * r[:, None], inv, K)
    return bread @ (g.T @ g) @ bread * (K / (K - 1.0))


def _block_sums(values: np.ndarray, blocks: np.ndarray, n_blocks: int) -> np.ndarray:
    """(n_blocks, k) sums over the rows of ``values`` (L, k) in each block."""
    out = np.zeros((n_blocks, values.shape[1]))
    np.add.at(out, blocks, values)
    return out


@dataclass
class HeldOutTest:
    """The held-out statistic of the round's candidates and its wild-bootstrap null.

    Built once per round from the current model's residuals; every candidate is then
    tested (:meth:`null`) and every kind's detectability solved (:meth:`min_strength`)
    on the same bootstrap weights.

    Attributes:
        nuisance: the nuisance directions on train and validation.
        e_train: (L_t,) current train residual without its nuisance part.
        e_validation: (L_v,) current held-out validation residual.
        blocks_train, blocks_validation: (L_t,), (L_v,) block of each entry.
        sigma2: the point-noise variance, m^2 (vector entries are in units of m).
        replicates: bootstrap replicates. seed: of the weights.
    """

    nuisance: Nuisance
    e_train: np.ndarray
    e_validation: np.ndarray
    blocks_train: np.ndarray
    blocks_validation: np.ndarray
    sigma2: float
    replicates: int = 9999
    seed: int = 0

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        self.nb_t = int(self.blocks_train.max()) + 1 if self.blocks_train.size else 0
        self.nb_v = int(self.blocks_validation.max()) + 1 if self.blocks_validation.size else 0
        self.w_t = webb_weights(rng, self.replicates, self.nb_t)
        self.w_v = webb_weights(rng, self.replicates, self.nb_v)
        N_t = self.nuisance.train
        self.N_t_pinv = np.linalg.pinv(N_t) if N_t.shape[1] else np.zeros((0, N_t.shape[0]))
        self._B = self._block_coefficients(self.e_train)

    def _block_coefficients(self, e_train: np.ndarray) -> np.ndarray:
        """Per-block nuisance coefficients of a train residual ``e_train`` (L_t,): beta* = w_t @ B."""
        if not self.nuisance.train.shape[1]:
            return np.zeros((self.nb_t, 0))
        return _block_sums((self.N_t_pinv * e_train[None, :]).T, self.blocks_train, self.nb_t)

    def under(self, e_train: np.ndarray, e_validation: np.ndarray) -> "HeldOutTest":
        """The same test (bootstrap weights, blocks, nuisances) drawing its null from the
        residuals ``e_train`` (L_t,) and ``e_validation`` (L_v,): a candidate's own, once
        it is fitted (the wild bootstrap's unrestricted residuals, instead of those of the
        model without it).

        Why: the round's residual holds whatever the round's model lacks, a real effect
        included, and the null resampled from it grows with that effect as the statistic
        does. Measured on a field session (seed 11, 4 x 6 s, no force): gravity's critical
        value was 37.5 without an effect, 8934 with 2x its stated ``min_size`` hidden
        (T 11437) and 35068 with 4x (T 44211): the ratio of the two stayed ~1.27 whatever
        the size, so the size stated said nothing of what a claim needed (with three
        sequences the ratio was 1.02 at 2x and the claim failed its nested test)."""
        from copy import copy

        new = copy(self)
        new.e_train = np.asarray(e_train, dtype=np.float64)
        new.e_validation = np.asarray(e_validation, dtype=np.float64)
        new._B = new._block_coefficients(new.e_train)
        return new

    def train_signature(self, J: np.ndarray) -> np.ndarray:
        """(L_t, p) ``J - N_t N_t^+ J``: a train signature ``J`` (L_t, p) without its nuisance part
        (the linear projection the null uses)."""
        if self.nuisance.size == 0:
            return J
        return J - self.nuisance.train @ (self.N_t_pinv @ J)

    def held_out_signature(self, J_t: np.ndarray, J_v: np.ndarray) -> np.ndarray:
        """(L_v, p) ``G = J_v - N_v N_t^+ J_t``: what a change along ``J`` does to the
        held-out residual once the nuisance coefficients are refitted on train."""
        if self.nuisance.size == 0:
            return J_v
        return J_v - self.nuisance.validation @ (self.N_t_pinv @ J_t)

    def _resampled(self, Jp: np.ndarray, G: np.ndarray, Minv: np.ndarray, e_t: np.ndarray, e_v: np.ndarray,
                   B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(theta (R, p), g (R, p)): per replicate, the train fit along ``Jp`` of the
        resampled train residual ``e_t`` and the product ``e_v*' G`` of the resampled
        held-out residual ``e_v`` (less the nuisance refit of the resampled train residual,
        ``B`` its :meth:`_block_coefficients`). Both are linear in the residuals."""
        theta = (self.w_t @ _block_sums(Jp * e_t[:, None], self.blocks_train, self.nb_t)) @ Minv
        g = self.w_v @ _block_sums(G * e_v[:, None], self.blocks_validation, self.nb_v)
        if self.nuisance.size:
            g = g - (self.w_t @ B) @ (self.nuisance.validation.T @ G)
        return theta, g

    def _replicates(self, J_t: np.ndarray, J_v: np.ndarray) -> tuple:
        """Per-replicate pieces of the statistic for a signature J (p columns)."""
        Jp = self.train_signature(np.asarray(J_t, dtype=np.float64))
        G = self.held_out_signature(J_t, J_v)
        Minv = np.linalg.pinv(Jp.T @ Jp)
        theta, g = self._resampled(Jp, G, Minv, self.e_train, self.e_validation, self._B)
        return theta, g, G, Jp, Minv

    @staticmethod
    def _mirrored(null: np.ndarray) -> np.ndarray:
        """``null`` mirrored about zero where its median is below it: chance fits that cost
        ``|m|`` on validation could as well gain it."""
        return null - 2.0 * min(float(np.median(null)), 0.0)

    def null(self, J_t: np.ndarray, J_v: np.ndarray) -> np.ndarray:
        """(R,) replicates of ``T`` (chi-square units) for a candidate with train and
        validation signatures ``J_t`` (L_t, p), ``J_v`` (L_v, p) under "absent"."""
        theta, g, G, _, _ = self._replicates(J_t, J_v)
        GG = G.T @ G
        return self._mirrored((2.0 * np.sum(g * theta, axis=1) - np.einsum("rp,pq,rq->r", theta, GG, theta)) / self.sigma2)

    def null_with_effect(self, J_t: np.ndarray, J_v: np.ndarray, X_t: np.ndarray,
                         X_v: np.ndarray) -> Callable[[float], np.ndarray]:
        """``null(s)``: the (R,) replicates of :meth:`null` for a candidate along ``J``
        ((L_t, p), (L_v, p)) when the round's residual also holds ``s`` times the change
        ``X`` ((L_t,), (L_v,)): an effect of that strength that the round's model lacks.

        The bootstrap resamples the round's residual, the effect in it included, so where
        an effect is present its null is wider than the no-effect one: each replicate is
        quadratic in ``s`` (the train fit ``theta`` and the held-out product ``g`` are
        linear in the residual), so the three coefficients are computed once and any ``s``
        costs one pass over the replicates. The effect's train part is taken without its
        nuisance part and its validation part as the held-out change (the linear
        projection, :meth:`held_out_signature`). Measured on a field session (seed 11,
        4 x 6 s, no force): gravity's critical value 37.5 without an effect, 8934 with
        2x the ``min_size`` then stated (solved against the no-effect value) and 35068 with
        4x: the held-out statistic stayed ~1.27 times it whatever the size, so the margin of
        a claim above ``min_size`` is that ratio, not the size (with three sequences 1.02,
        and the claim failed).

        Raises:
            ValueError: the shapes of ``J`` and ``X`` do not match the test's vectors.
        """
        J_t = np.asarray(J_t, dtype=np.float64).reshape(len(self.e_train), -1)
        J_v = np.asarray(J_v, dtype=np.float64).reshape(len(self.e_validation), -1)
        X_t = np.asarray(X_t, dtype=np.float64).reshape(len(self.e_train))
        X_v = np.asarray(X_v, dtype=np.float64).reshape(len(self.e_validation))
        Jp = self.train_signature(J_t)
        G = self.held_out_signature(J_t, J_v)
        Minv = np.linalg.pinv(Jp.T @ Jp)
        th0, g0 = self._resampled(Jp, G, Minv, self.e_train, self.e_validation, self._B)
        Xp = self.train_signature(X_t[:, None])[:, 0]
        th1, g1 = self._resampled(Jp, G, Minv, Xp, self.held_out_signature(X_t[:, None], X_v[:, None])[:, 0],
                                  self._block_coefficients(Xp))
        GG = G.T @ G

        def quad(a, b):
            return np.sum(a[1] * b[0] + b[1] * a[0], axis=1) - np.einsum("rp,pq,rq->r", a[0], GG, b[0])

        # per replicate: sigma^2 null = c0 + c1 s + c2 s^2 (before the mirror about zero)
        c0, c2 = quad((th0, g0), (th0, g0)), quad((th1, g1), (th1, g1))
        c1 = quad((th0, g0), (th1, g1)) + quad((th1, g1), (th0, g0))

        def null(s: float) -> np.ndarray:
            return self._mirrored((c0 + s * c1 + s * s * c2) / self.sigma2)

        return null

    def p_value(self, observed: float, null: np.ndarray, searches: int = 1) -> float:
        """Share of ``null`` replicates at or above ``observed`` (:func:`tail_p_value`: the
        Monte-Carlo share, or its generalised Pareto tail beyond the last few replicates),
        times ``searches``, at most 1."""
        if not math.isfinite(observed):
            return 1.0
        return min(1.0, tail_p_value(null, observed) * max(int(searches), 1))

    def critical(self, null: np.ndarray, level: float) -> float:
        """The (1 - level) quantile of ``null`` (the smallest T a claim at ``level`` needs),
        :func:`tail_quantile`."""
        return tail_quantile(null, level)

    def _strength_pieces(self, D_t: np.ndarray, D_v: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """``(chance, cross, GG)`` of a signature ``D`` ((L_t,), (L_v,)) fitted along itself:
        data holding ``s`` times it give the (R,) replicates ``T(s) = chance + s cross + s^2
        GG / sigma^2`` (``chance`` the noise's own fit along D, ``cross`` twice the noise
        along the held-out signature G per unit strength, ``GG = |G|^2``). None of them
        depends on ``s``, so they are computed once."""
        D_t = np.asarray(D_t, dtype=np.float64).reshape(-1, 1)
        D_v = np.asarray(D_v, dtype=np.float64).reshape(-1, 1)
        theta0, g0, G, _, _ = self._replicates(D_t, D_v)
        GG = float((G.T @ G)[0, 0])
        theta0, g0 = theta0[:, 0], g0[:, 0]
        return (2.0 * g0 * theta0 - GG * theta0**2) / self.sigma2, 2.0 * g0 / self.sigma2, GG

    def statistic(self, D_t: np.ndarray, D_v: np.ndarray, strength: float) -> np.ndarray:
        """(R,) replicates of ``T`` for data holding ``strength`` times the signature
        ``D`` ((L_t,), (L_v,)), fitted along ``D`` itself."""
        chance, cross, GG = self._strength_pieces(D_t, D_v)
        s = float(strength)
        return chance + s * cross + s * s * GG / self.sigma2

    def min_strength(self, D_t: np.ndarray, D_v: np.ndarray, critical: float | Callable[[float], float],
                     s_max: float, power: float = 0.8, expected: Callable[[float], float] | None = None) -> float | None:
        """The smallest strength (>= 0) along ``D`` at which ``T`` reaches ``critical`` in a
        share ``power`` of the replicates (the minimum detectable effect at that power),
        by bisection to 0.1 %; None when even ``s_max`` does not.

        ``critical``: a number, or ``critical(s)``, the critical value a claim needs when
        the data hold strength ``s`` (the null grows with an effect in the round's
        residual, :meth:`null_with_effect`); then ``T`` and it may cross more than once,
        and the first crossing is found on a geometric scan of 40 strengths up to
        ``s_max`` before the bisection.

        ``expected(s)``: the noise-free ``T`` at strength ``s`` (default ``s^2 |G|^2 /
        sigma^2``, the linear projection ``free(s)``), so that a caller whose nuisances are
        bounded passes its own noise-free statistic. The noise's part at that power is the
        replicates' ``1 - power`` quantile of ``chance + 2 s k(s) e_v* . G / sigma^2``:
        ``chance`` is the noise's own fit along D (as in :meth:`null`), the second term the
        noise along the change the effect leaves on held-out data. That change is ``s G``
        for the linear projection; where bounded nuisances absorb part of it, what is left
        has the norm ``sqrt(expected(s) sigma^2)``, so the noise along it is scaled by
        ``k(s) = sqrt(expected(s) / free(s))`` (without the scale, the noise along the
        whole linear change made the minimum strength 1.47x too large where half of the
        change survives the nuisances and 6.1x where a tenth does; ``k`` exceeds 1 where
        the bounds leave more than the unbounded projection would). With the default
        ``expected`` this is exactly the quantile of :meth:`statistic`."""
        if not (np.all(np.isfinite(D_t)) and np.all(np.isfinite(D_v))) or s_max <= 0:
            return None
        chance, cross, GG = self._strength_pieces(D_t, D_v)
        if not GG > 0:
            return None  # the signature does not change the held-out data at any strength

        def free(s):
            return s * s * GG / self.sigma2

        exp = expected or free

        def T(s):
            e, f = max(float(exp(s)), 0.0), free(s)
            k = math.sqrt(e / f) if f > 0 else 1.0
            return e + float(np.quantile(chance + (s * k) * cross, 1.0 - power))

        crit = critical if callable(critical) else (lambda s: critical)

        def passes(s):
            return T(s) >= crit(s)

        lo, hi = 0.0, float(s_max)
        if passes(lo):
            return 0.0
        if callable(critical):  # the first strength that passes, then bisect below it
            scan = s_max * np.geomspace(1e-4, 1.0, 40)
            first = next((i for i, s in enumerate(scan) if passes(float(s))), None)
            if first is None:
                return None
            lo, hi = (float(scan[first - 1]) if first else 0.0), float(scan[first])
        elif not passes(hi):
            return None
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if passes(mid) else (mid, hi)
            if hi - lo <= 1e-3 * hi:
                break
        return hi
