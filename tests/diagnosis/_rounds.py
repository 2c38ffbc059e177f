"""A stand-in round for the size solve's tests: two free nuisance directions, a held-out
test from a small noise draw, and a flat base residual."""

from types import SimpleNamespace

import numpy as np

from core.diagnosis.inference import HeldOutTest
from core.diagnosis.nuisance import Nuisance


def stand_in_round(rng: np.random.Generator, L: int, sigma2: float, block: int) -> SimpleNamespace:
    """A round with what :mod:`core.diagnosis.sizing` reads (``fixed``, ``youngs_modulus``,
    ``nuisance``, ``test``, ``r_train``, ``r_validation``, ``discrepancy``): ``L`` entries per
    role, noise variance ``sigma2``, the test's blocks ``block`` entries long (999 replicates)."""
    N_t, N_v = rng.normal(size=(L, 2)), rng.normal(size=(L, 2))
    nuis = Nuisance(N_t, N_v, ("dent", "dent"), np.full(2, -np.inf), np.full(2, np.inf))
    e_t, e_v = rng.normal(scale=0.1, size=L), rng.normal(scale=0.1, size=L)
    blocks = np.arange(L) // block
    test = HeldOutTest(nuis, nuis.project(e_t), e_v, blocks, blocks, sigma2, replicates=999, seed=0)
    base = np.full(L, 0.1)
    return SimpleNamespace(fixed=[], youngs_modulus=5000.0, nuisance=nuis, test=test, r_train=base, r_validation=base,
                           discrepancy=None)
