"""diagnosis.json (SESSION_FORMAT.md contract) and a Markdown report with figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from core.diagnosis.engine import Diagnosis
from core.diagnosis.youngs import gravity_at_reported_youngs

__all__ = ["write_diagnosis"]


def _mm(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v * 1e3:.3f}"


def evidence_scores(candidates, kinds: list[str], rnd: int) -> list[float]:
    """Each kind's score (held-out chi2 drop / critical value) in round ``rnd``, NaN where
    the kind was not tested that round or its score is undefined (None: a null whose
    critical value is zero or not finite), so that the evidence plot leaves a gap."""
    out = []
    for k in kinds:
        v = next((c.score for c in candidates if c.kind == k and c.round == rnd), None)
        out.append(float(v) if v is not None else float("nan"))
    return out


def _maps(diag: Diagnosis, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lay = diag.layout
    ext = [0, diag.layout.size[0] * 1e3, 0, diag.layout.size[1] * 1e3]

    def mean_map(runs, names):
        s = np.zeros(lay.n_bins)
        c = np.zeros(lay.n_bins)
        for n in names:
            r = runs[n]
            has = r.field != 0
            s += np.where(has, r.field, 0).sum(axis=0)
            c += has.sum(axis=0)
        return (s / np.maximum(c, 1))[: lay.top_bins].reshape(lay.bins)

    names = [n for n in diag.extended_fields if n in diag.base_fields]
    base = mean_map(diag.base_fields, names) * 1e3
    extm = mean_map(diag.extended_fields, names) * 1e3
    sysm = np.array(diag.summary["systematic_rms_map_m"]) * 1e3
    lim = max(float(np.abs(base).max()), 1e-3)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.4), constrained_layout=True)
    for ax, m, title, cmap, vmin in (
        (axes[0], base, "base model: mean signed residual (mm)", "coolwarm", -lim),
        (axes[1], extm, "extended model: mean signed residual (mm)", "coolwarm", -lim),
        (axes[2], sysm, "base model: systematic RMS beyond noise (mm)", "viridis", 0.0),
    ):
        im = ax.imshow(m.T, origin="lower", extent=ext, cmap=cmap, vmin=vmin, vmax=lim if vmin < 0 else None, aspect="equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.savefig(out / "residual_maps.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.2), constrained_layout=True)
    for ax, key, title in ((axes[0], "by_phase", "when"), (axes[1], "by_distance_from_probe", "where")):
        tab = diag.summary[key]
        labels = list(tab)
        sysv = [(tab[k]["systematic_rms_m"] or 0) * 1e3 for k in labels]
        totv = [(tab[k]["total_rms_m"] or 0) * 1e3 for k in labels]
        x = np.arange(len(labels))
        ax.bar(x - 0.2, totv, 0.4, label="total RMS of bin means")
        ax.bar(x + 0.2, sysv, 0.4, label="systematic (beyond noise)")
        ax.set_xticks(x, labels, fontsize=8)
        ax.set_ylabel("mm")
        ax.set_title(f"base model residual: {title}", fontsize=9)
        ax.legend(fontsize=7)
    fig.savefig(out / "residual_when_where.png", dpi=110)
    plt.close(fig)

    rounds = sorted({c.round for c in diag.candidates})
    fig, ax = plt.subplots(figsize=(9, 3.2), constrained_layout=True)
    kinds = list(dict.fromkeys(c.kind for c in diag.candidates))
    width = 0.8 / max(len(rounds), 1)
    for j, rnd in enumerate(rounds):
        vals = evidence_scores(diag.candidates, kinds, rnd)
        ax.bar(np.arange(len(kinds)) + j * width, vals, width, label=f"round {rnd}")
    ax.axhline(1.0, color="k", lw=1, ls="--", label="what a claim needs")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_xticks(np.arange(len(kinds)) + 0.4 - width / 2, kinds, rotation=20, fontsize=8)
    ax.set_ylabel("held-out chi2 drop / critical value")
    ax.legend(fontsize=7)
    ax.set_title("evidence per candidate cause", fontsize=9)
    fig.savefig(out / "evidence.png", dpi=110)
    plt.close(fig)


def write_diagnosis(diag: Diagnosis, out: str | Path) -> Path:
    """Write ``diagnosis.json``, ``report.md`` and its PNG figures into ``out``.

    Raises:
        OSError: the folder cannot be written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = diag.to_json()
    (out / "diagnosis.json").write_text(json.dumps(data, indent=2, default=float))
    _maps(diag, out)
    E = diag.youngs
    lines = [
        f"# Diagnosis of `{diag.session}`",
        "",
        "## What is wrong",
        "",
        f"Base model (the paper's: {diag.config.law}, {'x'.join(map(str, diag.config.grid))} grid, no effects): "
        f"test error **{_mm(diag.baseline_test_error)} mm** against a noise floor of {_mm(diag.noise_floor)} mm "
        f"(rest frames against the rest mesh). Point noise of the signed top residual, from the scatter inside "
        f"bins: {_mm(diag.noise_sigma)} mm. Systematic share of the residual variance of bin means: "
        f"{100 * diag.summary['systematic_fraction_of_variance']:.0f} %.",
        "",
        "![residual maps](residual_maps.png)",
        "",
        "![when and where](residual_when_where.png)",
        "",
        "| when | systematic RMS (mm) | total RMS (mm) | bin-frames |",
        "|---|---|---|---|",
    ]
    for k, v in diag.summary["by_phase"].items():
        lines.append(f"| {k} | {_mm(v['systematic_rms_m'])} | {_mm(v['total_rms_m'])} | {v['bin_frames']} |")
    lines += ["", "| where | systematic RMS (mm) | total RMS (mm) | bin-frames |", "|---|---|---|---|"]
    for k, v in diag.summary["by_distance_from_probe"].items():
        lines.append(f"| {k} | {_mm(v['systematic_rms_m'])} | {_mm(v['total_rms_m'])} | {v['bin_frames']} |")
    if "by_face" in diag.summary:
        lines += ["", "| face | systematic RMS (mm) | total RMS (mm) | bin-frames |", "|---|---|---|---|"]
        for k, v in diag.summary["by_face"].items():
            lines.append(f"| {k} | {_mm(v['systematic_rms_m'])} | {_mm(v['total_rms_m'])} | {v['bin_frames']} |")
    if diag.force:
        fz = diag.force
        lines += ["", f"Probe force: {diag.force_note}. The base model's Young's modulus fitted to it: "
                      f"{fz['base_youngs_modulus']:.4g} Pa; its RMS force error on test is {1e3 * fz['baseline_test_rms_N']:.1f} mN "
                      f"(noise {1e3 * float(np.linalg.norm(fz['noise_N'])):.1f} mN)."]
    else:
        lines += ["", f"Probe force: {diag.force_note}. Without it, effects that change the force more than the "
                      "surface (a stiff inclusion, friction, a wrong probe radius) are hard to see."]
    for note in diag.notes:
        lines += ["", f"**Note**: {note}."]
    lines += ["", "## Why", ""]
    if diag.causes:
        lines.append("Claimed causes, most important first:")
        lines.append("")
        lines.append("| cause | parameters | confidence | test error (mm) | gain | force gain |")
        lines.append("|---|---|---|---|---|---|")
        for c in diag.causes:
            fg = "n/a" if c.force_gain is None else f"{100 * c.force_gain:.1f} %"
            lines.append(f"| {c.kind} | `{json.dumps(c.parameters)}` | {c.confidence:.2f} | {_mm(c.test_error)} | {100 * (c.gain or 0):.1f} % | {fg} |")
        for c in diag.causes:
            if c.kind == "gravity" and (g := gravity_at_reported_youngs(c.parameters["g"], diag.youngs)) is not None:
                lines += ["", f"Gravity was fitted on the replay grid at E {diag.youngs['replay_grid_value_used']:.4g} Pa; "
                              f"the sag is set by rho g / E, so at the reported E {diag.youngs['value']:.4g} Pa it reads "
                              f"|g| = {g:.2f} m/s^2."]
        ranges = [f"{c.kind}.{k} {iv['interval'][0]:.4g}-{iv['interval'][1]:.4g} {iv['unit']}"
                  + ("" if iv["model_form"] is None else
                     f" (statistical {iv['statistical'][0]:.4g}-{iv['statistical'][1]:.4g}; refitted with E "
                     f"in the model-form worlds {iv['model_form'][0]:.4g}-{iv['model_form'][1]:.4g})")
                  for c in diag.causes for k, iv in c.intervals.items()
                  if None not in iv["interval"] and None not in iv["statistical"]]
        if ranges:
            lines += ["", "95 % intervals of the claimed parameters: " + "; ".join(ranges) + "."]
        unid = [f"{c.kind}.{k}" for c in diag.causes for k, ok in c.identifiable.items() if not ok]
        if unid:
            lines += ["", "Not identifiable from these data (95 % interval too wide): " + ", ".join(unid) + "."]
    else:
        lines.append("**No effect found**: no candidate explains enough of the held-out residual, beyond noise "
                     "and the base model's nuisances, to pass the test at the stated false-claim rate.")
    if diag.confounded:
        lines += ["", "Confounded (they explain the same residual about equally well; none is picked): "
                  + "; ".join(" / ".join(g) for g in diag.confounded) + "."]
    if diag.detectability:
        words = {"found": "found", "confounded": "confounded", "not_found": "not found", "cannot_tell": "cannot tell"}
        lines += ["", "### Every kind: found, confounded, not found above a size, or cannot tell", "",
                  "| kind | answer | smallest size these data would claim | assumed | why |", "|---|---|---|---|---|"]
        for k, d in diag.detectability.items():
            size = "none (cannot tell at any size)" if d.min_size is None else f"{d.min_size:.3g} {d.unit}"
            # the placements and the reach beside the best one are in its why, in words
            assumed = ", ".join(f"{a}={json.dumps(v)}" for a, v in d.parameters.items() if a not in ("placements", "beside"))
            lines.append(f"| {k} | {words.get(d.answer, d.answer)} | {size} | {assumed} | {d.why} |")
    nuis = ", ".join(diag.nuisances) or "none"
    lines += ["", "![evidence](evidence.png)", "",
              f"A candidate is fitted on the train sequences beside the base model's nuisances ({nuis}: the "
              "model-form gap every real session carries) and judged on the validation sequences: its evidence "
              "is the drop of the validation chi-square (surface and force), its p-value the share of the "
              "session's own noise replicates (a wild block bootstrap of its residuals) that drop as much, and "
              f"the kinds of a round are tested together by Holm's procedure: on a session without any effect, "
              f"the chance that anything is claimed is at most {100 * diag.config.alpha:g} %. A kind that passes but "
              "makes a channel of the held-out data (top face, side faces, force) significantly worse is not "
              "claimed: its gain in one channel is the model-form gap, paid for in another. Nor is a kind whose "
              "fit, added to a phantom at an end of the model-form range (damping, Poisson's ratio, contact "
              "stiffness, material law, alone and together) that explains part of the residual, no longer "
              "explains its critical value of the held-out data there"
              + (f" (the range explains up to {diag.model_form['bar']:.0f} (chi2) here, from {diag.model_form['variant']})."
                 if diag.model_form and diag.model_form.get("variant") else "."), "",
              "| round | candidate | chi2 drop: surface | chi2 drop: force | critical | p-value | confidence | claimed |",
              "|---|---|---|---|---|---|---|---|"]
    for c in diag.candidates:
        fo = "n/a" if c.delta_chi2_force is None else f"{c.delta_chi2_force:.0f}"
        crit = "n/a" if c.critical is None or not math.isfinite(c.critical) else f"{c.critical:.0f}"
        pv = "n/a" if c.p_value is None else f"{c.p_value:.3g}"
        worse = [k for k, v in (c.channels or {}).items() if v.get("worse")]
        rp = c.reproduction or {}
        small = (c.p_value is not None and c.p_value <= diag.config.alpha and c.critical is not None
                 and rp.get("expected", math.inf) < c.critical)
        verdict = ("yes" if c.claimed else f"no: {' and '.join(worse)} worse" if worse
                   else "no: its change is below the critical value" if small else "")
        lines.append(f"| {c.round} | {c.kind} | {c.delta_chi2_field:.0f} | {fo} | {crit} | {pv} | {c.confidence:.2f} | "
                     f"{verdict} |")
    lines += ["", "## What the fix is worth", ""]
    lo, hi = diag.gain_interval
    lines.append(
        f"Extended model ({', '.join(diag.extended_kinds) or 'nothing added'}): test error {_mm(diag.extended_test_error)} mm, "
        f"gain {100 * diag.extended_gain:.1f} % (95 % interval {100 * lo:.1f} to {100 * hi:.1f} %, frame-block bootstrap); "
        f"{_mm(diag.extended_test_error - diag.noise_floor)} mm above the noise floor remains."
    )
    if diag.force:
        fz = diag.force
        lines.append(f"Probe force on test: RMS error {1e3 * fz['baseline_test_rms_N']:.1f} mN (base) -> "
                     f"{1e3 * fz['extended_test_rms_N']:.1f} mN (extended), gain {100 * fz['gain']:.1f} %.")
    if E.get("identifiable"):
        a, b = E["interval"]
        lines.append(f"Young's modulus with these causes: {E['value']:.4g} Pa (95 % interval {a:.4g}-{b:.4g} Pa).")
    else:
        lines.append(f"Young's modulus: not identifiable. {E.get('reason', '')}")
    lc = diag.learned_correction
    if lc:
        lines += ["", "## What the learned correction learned", "",
                  f"The network's correction of the top layer ({_mm(lc['correction_rms_m'])} mm RMS over {lc['frames']} frames of "
                  f"{', '.join(lc['sequences'])}) projected onto each cause's change of the top layer (share: fraction of the "
                  "correction's sum of squares the scaled cause reproduces; scale 1: the network moves the nodes as the "
                  "fitted cause does).", "", "| cause | share | scale | cause RMS (mm) |", "|---|---|---|---|"]
        for c in lc["causes"]:
            lines.append(f"| {c['kind']} | {100 * c['share']:.0f} % | {c['scale']:.2f} | {_mm(c['cause_rms_m'])} |")
        if lc["claimed_share"] is not None:
            lines += ["", f"The claimed causes together account for {100 * lc['claimed_share']:.0f} % of the correction; "
                          f"{100 * lc['unexplained_share']:.0f} % is something else (model-form error, noise, or a missed effect)."]
        else:
            lines += ["", "Nothing was claimed, so none of the correction is attributed to a cause."]
    lines += ["", f"{diag.simulations} simulations, {diag.timings['total']:.0f} s.", ""]
    (out / "report.md").write_text("\n".join(lines))
    return out
