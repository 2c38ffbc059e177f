"""The paper's grid search for Young's modulus (Wu et al. 2020, Sec. 4.3, Tables 1-2).

A sweep also carries the fit's verdict on E (:func:`core.identification.verdict.sweep_verdict`):
the lowest error of the grid is not an estimate when the whole sweep is within the noise.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.identification.trials import Trial, TrialResult, run_trial
from core.identification.verdict import sweep_verdict
from core.preparation import PreparedSession
__all__ = ["PAPER_COARSE", "refine_grid", "SweepResult", "sweep", "write_sweep"]

PAPER_COARSE = (1e1, 1e2, 1e3, 1e4, 1e5, 1e6)
"""Table 1: every decade from 1e1 to 1e6 Pa."""


def refine_grid(best: float) -> list[float]:
    """Table 2's fine grid around the best coarse value 10^k: {2.5, 5, 7.5} x 10^(k-1)
    and {2.5, 5, 7.5} x 10^k (for 1e4: 2.5e3 ... 7.5e4, as in the paper)."""
    k = math.floor(math.log10(best) + 1e-9)
    return [m * 10.0**e for e in (k - 1, k) for m in (2.5, 5.0, 7.5)]


@dataclass(frozen=True)
class SweepResult:
    """Rows of a sweep: one per (E, sequence), in submission order.

    Attributes:
        results: the trials.
        verdict: whether these data identify E, by the fit's rule
            (:func:`core.identification.verdict.sweep_verdict`: ``identifiable``, ``value``
            Pa or None, ``interval`` [lo, hi] Pa or None, ``reason``, ``statistic``); None
            when not computed.
    """

    results: tuple[TrialResult, ...]
    verdict: dict | None = None

    def table(self) -> dict[float, float]:
        """Mean error (m) per E over the swept sequences (NaN if any trial diverged)."""
        out: dict[float, list] = {}
        for r in self.results:
            out.setdefault(r.trial.youngs_modulus, []).append(r)
        return {
            E: (float(sum(r.frame_sums.sum() for r in rs) / sum(r.frame_counts.sum() for r in rs)) if all(r.ok for r in rs) else float("nan"))
            for E, rs in sorted(out.items())
        }

    def best(self) -> float:
        """The swept E (Pa) with the lowest mean error: the paper's "best" value. Not an
        estimate of E unless ``verdict["identifiable"]``."""
        table = {E: e for E, e in self.table().items() if np.isfinite(e)}
        if not table:
            raise TissueTwinError("every trial of the sweep diverged")
        return min(table, key=table.get)


def sweep(
    prepared: PreparedSession,
    youngs: Sequence[float],
    *,
    sequences: Sequence[str] | None = None,
    base: Trial | None = None,
    refine: bool = False,
    executor: Executor | None = None,
    progress: Callable[[int, int], None] | None = None,
    verdict: bool = True,
) -> SweepResult:
    """Replay the sequences for every Young's modulus (and the fine grid if ``refine``).

    Args:
        prepared: calibrated session with cleaned clouds.
        youngs: values of E in Pa (the paper: :data:`PAPER_COARSE`).
        sequences: names (default: the ``train`` sequences, as the paper swept a training sequence).
        base: template trial for the other parameters (Poisson's ratio, grid, effects, numerics).
        refine: add :func:`refine_grid` around the best coarse value, as the paper did.
        executor: where trials run (default: in this process).
        verdict: attach the fit's verdict on E (``SweepResult.verdict``; a bootstrap over
            the sweep's frames, plus 5 E values near the optimum for the calibration term
            when the rest of the fit's rule holds).

    A diverged trial is recorded with status "diverged" and the sweep goes on.
    """
    executor = executor or SerialExecutor()
    base = base or Trial(sequence="", youngs_modulus=1.0)
    names = list(sequences) if sequences else [n for n, s in prepared.sequences.items() if s.role == "train"]
    if not names:
        names = list(prepared.sequences)
    values = [float(E) for E in youngs]
    if not values or any(not (E > 0 and np.isfinite(E)) for E in values):
        raise TissueTwinError(f"Young's moduli must be positive numbers, got {list(youngs)}")
    trials = [replace(base, sequence=n, youngs_modulus=E) for E in values for n in names]
    total = len(trials) + (6 * len(names) if refine else 0)
    done = [0]

    def tick(i, n):
        if progress:
            progress(done[0] + i, total)

    results = executor.map(run_trial, prepared, trials, tick)
    done[0] = len(trials)
    if refine:
        coarse = SweepResult(tuple(results))
        fine = [E for E in refine_grid(coarse.best()) if E not in values]
        extra = [replace(base, sequence=n, youngs_modulus=E) for E in fine for n in names]
        results += executor.map(run_trial, prepared, extra, tick)
    result = SweepResult(tuple(results))
    if verdict:
        result = SweepResult(result.results, sweep_verdict(prepared, result, executor=executor))
    return result


def write_sweep(result: SweepResult, out: str | Path) -> Path:
    """Write ``sweep.csv`` (youngs_modulus,poisson_ratio,sequence,mean_error,status; errors
    in m, rounded to 1e-12 m), ``sweep.png`` (error against E, log axis, like Tables 1-2)
    and, with a verdict, ``sweep.json`` (``{"youngs_modulus": verdict, "table": [{E Pa,
    mean_error m or null}]}``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "sweep.csv.tmp"
    with tmp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["youngs_modulus", "poisson_ratio", "sequence", "mean_error", "status"])
        for r in sorted(result.results, key=lambda r: (r.trial.youngs_modulus, r.trial.sequence)):
            err = f"{r.mean_error:.12f}" if r.ok else ""
            w.writerow([f"{r.trial.youngs_modulus:g}", f"{r.trial.poisson_ratio:g}", r.trial.sequence, err, r.status])
    tmp.replace(out / "sweep.csv")
    if result.verdict is not None:
        table = [{"youngs_modulus": E, "mean_error": e if math.isfinite(e) else None} for E, e in result.table().items()]
        (out / "sweep.json").write_text(json.dumps({"youngs_modulus": result.verdict, "table": table}, indent=2))
    _plot(result, out / "sweep.png")
    return out


def _plot(result: SweepResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    by_seq: dict[str, list] = {}
    for r in result.results:
        by_seq.setdefault(r.trial.sequence, []).append(r)
    for name, rs in sorted(by_seq.items()):
        rs = sorted(rs, key=lambda r: r.trial.youngs_modulus)
        E = [r.trial.youngs_modulus for r in rs]
        e = [r.mean_error * 1e3 if r.ok else np.nan for r in rs]
        ax.plot(E, e, "o-", label=name)
        for r in rs:
            if not r.ok:
                ax.annotate("N/A (diverged)", (r.trial.youngs_modulus, np.nanmin(e) if np.isfinite(np.nanmin(e)) else 0), rotation=90, fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel("Young's modulus E (Pa)")
    ax.set_ylabel("mean distance cloud -> mesh (mm)")
    ax.set_title("Young's modulus sweep (cf. Wu et al. 2020, Tables 1-2)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
