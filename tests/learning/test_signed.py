"""The signed column of the learned correction's reports: the mean signed vertical
residual over the top face's interior (core.identification.residuals.top_residuals)."""

import numpy as np

from core.learning import signed_residual


def test_signed_residual_measures_a_vertical_shift_with_its_sign(wrong_e_frames, gravity_prepared):
    f = next(s for s in wrong_e_frames.values() if s.role == "test")
    base, n = signed_residual(f.positions, f.clouds, f.grid, gravity_prepared.size)
    assert n > 1000 and np.isfinite(base)
    lifted = f.positions + np.array([0.0, 0.0, 1e-3])  # the whole mesh 1 mm higher
    up, n_up = signed_residual(lifted, f.clouds, f.grid, gravity_prepared.size)
    assert n_up == n
    assert up == np.float64(up) and abs((base - up) - 1e-3) < 1e-12  # the measured points now lie 1 mm lower
    # a diverged frame makes the figure unknown rather than silently partial
    broken = f.positions.copy()
    broken[-1] = np.nan
    assert np.isnan(signed_residual(broken, f.clouds, f.grid, gravity_prepared.size)[0])
