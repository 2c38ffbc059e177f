"""Hidden-effect scenarios: a session design per effect kind, for tests and benchmarks of
the diagnosis.

Each scenario hides one effect of ``SESSION_FORMAT.md`` (or none) at a magnitude the lab
can detect, in a ``small``-preset session, with a palpation protocol that exercises it:
the inclusion's location varies with the seed and the probe searches the region above
it (a surgeon palpates where a tumour is suspected; an inclusion that no poke comes near
leaves no trace in any data), and friction is probed by sliding. The other kinds use the
preset's protocol. Whether a kind is detectable is a property of the data as well as of
the effect: a wrong probe radius, a stiff inclusion or friction barely change the
surface the camera sees under a displacement-controlled probe, but change the probe
force, so force columns are written by default.

    lab, effects = scenario("inclusion", seed=3, duration=6.0)
    generate_session(out, preset=lab, seed=3, effects=effects, with_force=True)
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from core.lab.generate import PHANTOM_SIZE, PRESETS, LabConfig
from core.simulation.effects import EFFECT_KINDS, PhantomContext

__all__ = ["SCENARIO_KINDS", "hidden_effects", "scenario"]

SCENARIO_KINDS = (*EFFECT_KINDS, "none")
"""Every effect kind of SESSION_FORMAT.md, and "none" (no effect)."""


def _context(shape: str) -> PhantomContext:
    """The phantom context of the lab's ``shape`` (``"box"`` or one of
    :data:`core.lab.shapes.SHAPES`), probe radius 5 mm."""
    if shape == "box":
        return PhantomContext(np.asarray(PHANTOM_SIZE), 0.005)
    from core.lab.shapes import shape_surface
    from core.preparation.shape import SurfaceShape

    surface = SurfaceShape(*shape_surface(shape))
    return PhantomContext(surface.size, 0.005, shape=surface)


def hidden_effects(kind: str, seed: int, shape: str = "box") -> list[dict]:
    """The effect dicts hidden for ``kind`` (SI, phantom frame; empty for "none"): the
    kind's own example (:meth:`core.simulation.effects.Effect.example`) on the lab's
    ``shape`` (an inclusion lies under its surface), drawn with
    ``numpy.random.default_rng(1000 + seed)``.

    Magnitudes: standard gravity; a 10 mm inclusion 6x stiffer than the bulk, 2 mm under
    the top, its centre varied with the seed; a Maxwell arm twice as stiff as the elastic
    solid relaxing in 0.5 s; Coulomb friction 0.8 (wet gel on steel is 0.3-1); a
    foundation of 5e4 Pa/m (a 5 kPa gel on a soft pad); a 7.5 mm probe recorded as 5 mm;
    a 0.15 s clock offset (a few camera frames); a robot calibration error of
    (1.5, -1, -1.5) mm.

    Raises:
        ValueError: unknown kind.
    """
    if kind == "none":
        return []
    if kind not in EFFECT_KINDS:
        raise ValueError(f"unknown scenario kind {kind!r}; expected one of {SCENARIO_KINDS}")
    return [EFFECT_KINDS[kind].example(_context(shape), np.random.default_rng(1000 + seed)).to_dict()]


def scenario(kind: str, seed: int, duration: float = 10.0, preset: str | LabConfig = "small",
             shape: str = "box") -> tuple[LabConfig, list[dict]]:
    """The lab configuration and hidden effects of ``kind``'s scenario.

    Args:
        kind: an effect kind or "none".
        seed: varies the inclusion's centre (and, through ``generate_session``, everything else).
        duration: length of each of the preset's sequences, s.
        preset: the base configuration (default the ``small`` preset: 4 sequences, validation,
            test and two train).
        shape: the lab's phantom (``"box"``, ``"dome"``, ``"kidney"``; pass the same to
            :func:`core.lab.generate_session`).

    Returns:
        (LabConfig, effects) for :func:`core.lab.generate_session`.

    Raises:
        ValueError: unknown kind.
    """
    effects = hidden_effects(kind, seed, shape)
    base = PRESETS[preset] if isinstance(preset, str) else preset
    lab = base.with_duration(duration)
    probing = lab.probing
    if kind == "inclusion":
        c = effects[0]["center"]
        # pokes land within 9 mm of the centre (x and y), on the sphere and at its rim:
        # presses at one distance only cannot tell a stiff inclusion from a stiffer bulk
        half = 0.009
        probing = replace(probing, top_region=(c[0] - half, c[1] - half, c[0] + half, c[1] + half), side_probability=0.0)
        if shape != "box":  # every press lands over the inclusion, at a thin part of a dome
            probing = replace(probing, max_strain=0.25)
    elif kind == "friction":
        # every poke slides, briskly, so that even a 6 s sequence holds a slide
        probing = replace(probing, slide_probability=1.0, side_probability=0.0, hold_range=(0.3, 0.8),
                          slide_length_range=(0.004, 0.008), slide_speed_range=(0.006, 0.012))
    elif kind == "probe_radius":
        probing = replace(probing, face_cycle=("side", "top"), travel_speed=0.08, speed_range=(0.015, 0.025),
                          hold_range=(0.2, 0.4), rest_range=(0.1, 0.3), start_rest_range=(0.2, 0.4))
    return replace(lab, probing=probing), effects
