"""Virtual lab: synthetic palpation sessions with a known truth.

A software replay of the experiment of Wu et al. 2020 (Sec. 4): a dVRK PSM pokes a gel
block, an SR300-like depth camera records it, a truth FEM (finer and more faithful than
the replay model, plus any switched-on effect) deforms it. Sessions are written in the
``tissue-session/1`` format with a ``truth.json``.

Public surface::

    path = generate_session(out, preset="small", seed=0, effects=[{"kind": "gravity"}])

Modules: :mod:`core.lab.probing` (probe trajectories, random or given), :mod:`core.lab.camera`
(depth camera model), :mod:`core.lab.generate` (orchestration, truth.json), :mod:`core.lab.config` (presets, the lab's
configuration), :mod:`core.lab.phantom` (the phantom's shape, landmarks), :mod:`core.lab.truth`
(the truth FEM runs), :mod:`core.lab.robot` (robot pose, calibration touches, recorded
kinematics), :mod:`core.lab.rendering` (the camera placed for a seed, its frames),
:mod:`core.lab.variation` (a randomised lab: truth and sensors drawn per seed),
:mod:`core.lab.scenarios` (a hidden-effect session design per effect kind).
"""

from core.lab.camera import DepthCamera, DepthNoise, Instrument, Intrinsics
from core.lab.generate import (
    DEMO_EFFECTS,
    GENERATOR_NAME,
    GENERATOR_VERSION,
    INPUT_EFFECTS,
    PHANTOM_MASS,
    PHANTOM_SIZE,
    PHYSICAL_EFFECTS,
    PRESET_NOTES,
    PRESETS,
    LabConfig,
    LabError,
    complete_effects,
    generate_session,
)
from core.lab.probing import Poke, ProbePlan, ProbeTrajectory, ProbingConfig, plan_from_path, plan_sequence
from core.lab.scenarios import SCENARIO_KINDS, hidden_effects, scenario
from core.lab.variation import VARIATION_LAWS, LabVariation, apply_variation

__all__ = [
    "SCENARIO_KINDS",
    "hidden_effects",
    "scenario",
    "DEMO_EFFECTS",
    "GENERATOR_NAME",
    "GENERATOR_VERSION",
    "INPUT_EFFECTS",
    "PHANTOM_MASS",
    "PHANTOM_SIZE",
    "PHYSICAL_EFFECTS",
    "PRESET_NOTES",
    "PRESETS",
    "LabConfig",
    "LabError",
    "complete_effects",
    "generate_session",
    "DepthCamera",
    "DepthNoise",
    "Instrument",
    "Intrinsics",
    "Poke",
    "ProbePlan",
    "ProbeTrajectory",
    "ProbingConfig",
    "plan_sequence",
    "plan_from_path",
    "VARIATION_LAWS",
    "LabVariation",
    "apply_variation",
]
