"""Material identification: the paper's sweeps, fits with intervals, and where they run.

    with executor() as ex:                       # local Dask cluster (or scheduler=...)
        sweep(prepared, PAPER_COARSE, refine=True, executor=ex)
        fit_youngs_modulus(prepared, executor=ex)

Both say whether E is identifiable by one rule (:mod:`core.identification.verdict`).
"""

from core.identification.execution import DaskExecutor, Executor, SerialExecutor, executor
from core.identification.fit import FitResult, fit_youngs_modulus, refined_grid
from core.identification.sweep import PAPER_COARSE, SweepResult, refine_grid, sweep, write_sweep
from core.identification.trials import Trial, TrialResult, run_trial
from core.identification.verdict import sweep_verdict, youngs_verdict

__all__ = [
    "DaskExecutor",
    "Executor",
    "SerialExecutor",
    "executor",
    "FitResult",
    "fit_youngs_modulus",
    "refined_grid",
    "PAPER_COARSE",
    "SweepResult",
    "refine_grid",
    "sweep",
    "write_sweep",
    "Trial",
    "TrialResult",
    "run_trial",
    "youngs_verdict",
    "sweep_verdict",
]
