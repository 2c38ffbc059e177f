"""FEM replay of probe-phantom interaction (Wu et al. 2020, Sec. 3.2), fast.

Public surface::

    mesh = box_mesh(size, grid=(13, 5, 5))
    model = build_model(mesh, mass, Material(E, nu), SimulationConfig(), effects)
    result = simulate(model, ProbePath(t, centres), radius, output_times)
"""

from core.simulation.effects import (
    EFFECT_KINDS,
    BaseCompliance,
    Effect,
    Friction,
    Gravity,
    Inclusion,
    KinematicOffset,
    ProbeRadius,
    TimeOffset,
    Viscoelasticity,
    effect_from_dict,
)
from core.simulation.mesh import TetMesh, box_mesh
from core.simulation.model import Material, Model, SimulationConfig, State, build_model
from core.preparation.probe import ProbePath
from core.simulation.solver import SimulationResult, StepInfo, simulate, static_equilibrium, step

__all__ = [
    "EFFECT_KINDS",
    "BaseCompliance",
    "Effect",
    "Friction",
    "Gravity",
    "Inclusion",
    "KinematicOffset",
    "ProbeRadius",
    "TimeOffset",
    "Viscoelasticity",
    "effect_from_dict",
    "TetMesh",
    "box_mesh",
    "Material",
    "Model",
    "SimulationConfig",
    "State",
    "build_model",
    "ProbePath",
    "SimulationResult",
    "StepInfo",
    "simulate",
    "static_equilibrium",
    "step",
]
