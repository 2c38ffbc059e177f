"""Settings of a diagnosis (:class:`DiagnosisConfig`)."""

from __future__ import annotations

from dataclasses import dataclass

from core.diagnosis.candidates import KINDS

__all__ = ["DiagnosisConfig", "NUISANCES"]

NUISANCES = ("youngs", "mesh", "law", "poisson", "damping", "contact", "registration", "robot", "dent", "force_law")
"""The base model's nuisances, each a direction in which a real session's data differ
from the replay model without any effect kind: Young's modulus (with force data: force
scales with it), the model-form gap of the mesh (finer than the replay grid), the
material law (stable neo-Hookean instead of corotational), Poisson's ratio, Rayleigh
damping and the contact stiffness, the camera's registration (a rigid motion of the
measured surface), the robot's calibration (a probe offset within its precision), each
within a plausible range; and a generic smooth discrepancy of the
dent's shape and of the force-indentation law (see :mod:`core.diagnosis.nuisance`)."""


@dataclass(frozen=True)
class DiagnosisConfig:
    """Settings of a diagnosis.

    Attributes:
        youngs_modulus: E of the base model, Pa (the paper's 5e3 unless the session pins it).
        poisson_ratio, grid, law: the replay model (the paper's 0.44, 13x5x5, corotational).
        element_size: target element size (m) of a phantom given by ``phantom.stl`` (None:
            about the paper's node count); its fine mesh (``fine_grid`` set) halves the
            mean edge. surface_patches: patches of such a phantom's residual field
            (:class:`core.diagnosis.patches.PatchLayout`, instead of ``layout_bins`` and
            ``side_rows`` of the box's faces).
        fine_grid: the grid the base residual and the reported errors come from
            (multi-fidelity: signatures and fits run on ``grid``, their fields shifted by
            the discrepancy ``fine - coarse`` of the base model, sequence by sequence). The
            coarse grid's dent is ~1 mm off a 25x9x9 one's, more than several causes'
            signal. None: everything on ``grid``.
        coarse_dt: time step (s) of the coarse-grid runs when ``fine_grid`` is set (None:
            the simulator's 1/120 s); a surrogate whose base field and force are shifted
            onto the fine grid's. Measured on a 6 s session, 1/60 s against 1/120 s: fields
            within 0.002 mm (noise 0.77 mm), forces within 1-4 mN (noise 8 mN).
        fine_fit_dt: time step (s) of the fits on ``fine_grid`` (the final refit of the
            claimed causes and of E, and the fields shown on train and validation; None: the
            simulator's 1/120 s). The errors on test step at 1/120 s. Measured on a 4 x 12 s session, 25x9x9 at 1/60
            against 1/120 s: fields within 0.001 mm RMS (0.02 mm at most), forces within
            4-20 mN at load changes (noise 3-15 mN), 1.7x faster.
        layout_bins: bins of the residual field along x and y of the top face.
        side_rows: bins along z on each side face (0: the top face only). Side faces carry
            what the top cannot: side pokes, where a probe's radius and lateral offsets
            show, and a phantom that sags sideways (gravity that is not straight down).
        probe_exclusion: bins whose centre lies within this distance (m) of the measured
            probe centre are left out (0: none).
        side_probe_exclusion: side-face bins whose centre lies within this distance (m) of
            the probe's sphere are left out: a side bin spans a third of the face's height,
            the replay's 5 nodes over 36 mm cannot shape a side dent, and the instrument's
            remains sit there (measured on a session of the replay's own model: 10x the
            noise's chi2 per side bin during side presses, 1x elsewhere).
        nuisances: the base model's nuisance directions (:data:`NUISANCES`): a cause is
            claimed only for what it explains on held-out data beyond them. Every real
            session carries a model-form gap that no effect kind describes.
        alpha: the family-wise false-claim rate of each selection round: on a session
            without any effect, the chance that anything is claimed (Holm 1979 across the
            candidate kinds, each kind's null distribution from the session itself).
        consistency_alpha: one-sided level at which a candidate that makes a channel of
            the held-out data (top face, side faces, force) worse is refused
            (:func:`core.diagnosis.claims.channel_worsening`): a cause that is there
            improves every channel it changes, a model-form gap fitted by a wrong cause
            is paid for in another channel. 0 turns the check off. It only refuses
            claims, so it cannot raise the false-claim rate ``alpha``; a real cause fails
            it only where it leaves a channel unchanged in expectation (at most this
            rate) or where a model-form gap outweighs it there.
        n_null: wild block-bootstrap replicates of each kind's null distribution.
        null_residual: what the bootstrap resamples: ``"candidate"`` (the default since
            2026-11-29), the residual each candidate's fit leaves (the wild bootstrap's
            unrestricted residuals: a null that does not grow with the effect its kind
            explains, while a wrong kind's residual still holds it), or ``"round"``, the
            residual of the round's model without the candidate (it holds an effect that is
            there, so the null and the critical value grow with it, and ``min_size`` is
            solved against that growth: :func:`core.diagnosis.sizing.growing_critical`).
            Measured on fresh lab seeds, 4 x 6 s, with the claim-path checks of the same
            day: hidden-kind seed 82 with force, 2 of 8 named by "candidate" (gravity, the
            compliant base 3 % off) against 1 by "round", no spurious claim by either;
            no-effect seeds 1178-1181 with and without force: no claim (0/8); the shared
            sample session: no claim. See the README.
        block: length of the bootstrap's blocks of frames, s (the residual is correlated
            within a poke; blocks of 1 s are treated as independent).
        lm_iterations: most Levenberg-Marquardt iterations per candidate...
        lm_tolerance: ...which stop early once a step lowers the train chi2 by less than
            this (a fraction of one unit of chi2 cannot change a claim).
        contact_relinearisations: for a kind that moves where or how deep the probe presses
            (a robot offset, a probe radius), how often its coarse fit measures the mesh
            error (fine minus coarse) again at its parameters and continues from there
            (:meth:`core.diagnosis.evidence.Evidence.discrepancy_at`; 0: the base model's
            throughout, which biased a 5 mm robot offset's fit to 0.77 mm on field seed 11).
        contact_mesh_refinements: a claim of a kind that moves the contact must still explain
            held-out data replayed on meshes each of these times finer than the fine
            reference: box grids with that many times the fine grid's cells per axis, a
            ``phantom.stl`` phantom's own mesh at the fine element size over it
            (:func:`core.diagnosis.model_form.beyond_finer_mesh`), and such a kind's
            ``min_size`` holds on them too (:func:`core.diagnosis.sizing.world_min_size`;
            empty: neither).
        fine_refit_iterations: Levenberg-Marquardt iterations of the final refit of the
            claimed causes on ``fine_grid`` (0: keep the coarse fits); one exact-Jacobian
            step from the coarse fit.
        nested_size_refit: in a model-form world where a candidate's fit, added unchanged,
            explains less than its critical value, refit its size alone on train there and
            judge that (:func:`core.diagnosis.model_form.beyond_model_form`'s ``resize``;
            False: the test before 2026-12-01).
        joint_refit_iterations: with force data, Levenberg-Marquardt iterations of the
            claimed causes' refit with E on ``fine_grid`` (each cause with E in turn;
            :func:`core.diagnosis.worlds.refit_jointly`; 0: E alone beside them, one iteration).
        world_refit_iterations: iterations of that refit in each model-form world on the
            coarse grid (:func:`core.diagnosis.worlds.claimed_worlds`; 0: no worlds).
        max_causes: most causes claimed.
        fit_youngs: report E fitted with the claimed causes (otherwise keep ``youngs_modulus``).
        refine_mesh, n_boot: passed to the E fit (no force data); n_boot is also the
            number of bootstrap replicates of the test gain's interval.
        kinds: candidate kinds considered (all by default).
        detectability: state for every kind the smallest size this session's data would
            have claimed (``detectability`` in diagnosis.json).
        seed: of the bootstraps.
        segments: fit and test the candidates on at most this many segments of the train
            sequences, and as many of the validation sequences (informative frames,
            :mod:`core.preparation.segments`: pokes cut at rest, replayed from rest and in
            parallel, chosen to cover the palpation's kinds, never by their residuals), so
            that the diagnosis's cost stops growing with the recording's length; the test
            sequences stay whole. None: whole sequences.
        sensitivities: the fits' Jacobians are the replay's exact sensitivities
            (:mod:`core.simulation.sensitivity`: the candidate's variables, and log10 E, as
            extra right-hand sides of each step); False: a forward difference of one replay
            per variable (the method before, kept for comparison).
        use_force: put the probe force residual (simulated minus measured, per frame and
            axis, in units of the force noise measured on rest frames) into the evidence
            beside the residual field. None: when every sequence has force columns
            (kinematics.csv ``fx, fy, fz``).
    """

    youngs_modulus: float = 5000.0
    poisson_ratio: float = 0.44
    grid: tuple[int, int, int] = (13, 5, 5)
    law: str = "corotational"
    fine_grid: tuple[int, int, int] | None = (25, 9, 9)
    element_size: float | None = None
    surface_patches: int = 32
    coarse_dt: float | None = 1.0 / 60.0
    fine_fit_dt: float | None = 1.0 / 60.0
    layout_bins: tuple[int, int] = (16, 8)
    side_rows: int = 2
    probe_exclusion: float = 0.0
    side_probe_exclusion: float = 0.010
    nuisances: tuple[str, ...] = NUISANCES
    alpha: float = 0.01
    consistency_alpha: float = 0.05
    n_null: int = 9999
    null_residual: str = "candidate"
    block: float = 1.0
    lm_iterations: int = 4
    lm_tolerance: float = 1.0
    fine_refit_iterations: int = 1
    contact_relinearisations: int = 2
    contact_mesh_refinements: tuple[float, ...] = (1.25, 1.5)
    nested_size_refit: bool = True
    joint_refit_iterations: int = 3
    world_refit_iterations: int = 3
    max_causes: int = 3
    fit_youngs: bool = True
    refine_mesh: bool = True
    n_boot: int = 200
    kinds: tuple[str, ...] = KINDS
    detectability: bool = True
    seed: int = 0
    segments: int | None = None
    sensitivities: bool = True
    use_force: bool | None = None

    @property
    def fine_step(self) -> tuple:
        """``Spec.simulation`` of the runs at the fine fits' step: ``(("dt", fine_fit_dt),)``,
        or ``()`` (the run's default step) without ``fine_fit_dt``."""
        return (("dt", float(self.fine_fit_dt)),) if self.fine_fit_dt else ()

    def __post_init__(self):
        from core.errors import TissueTwinError

        unknown = [k for k in self.kinds if k not in KINDS]
        if unknown:
            raise TissueTwinError(f"unknown effect kind(s) {unknown}; expected some of {list(KINDS)}")
        bad = [n for n in self.nuisances if n not in NUISANCES]
        if bad:
            raise TissueTwinError(f"unknown nuisance(s) {bad}; expected some of {list(NUISANCES)}")
        if self.null_residual not in ("round", "candidate"):
            raise TissueTwinError(f"null_residual must be 'round' or 'candidate', got {self.null_residual!r}")
        if not 0.0 < self.alpha < 0.5:
            raise TissueTwinError(f"alpha must be in (0, 0.5), got {self.alpha}")
        if not 0.0 <= self.consistency_alpha < 0.5:
            raise TissueTwinError(f"consistency_alpha must be in [0, 0.5), got {self.consistency_alpha}")
        if self.n_null < 99:
            raise TissueTwinError(f"n_null must be at least 99, got {self.n_null}")
