"""The detectability's model-form worlds: a "not found above" size holds on the fine mesh too."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.model_form import mesh_world, model_form_worlds
from core.diagnosis.sizing import world_min_size
from core.simulation.effects import EFFECT_KINDS, PhantomContext
from tests.diagnosis._rounds import stand_in_round

L = 60  # entries of a residual vector per role
SIGMA2 = 1e-2
LEVEL = 0.01 / 8  # a kind's share of alpha 0.01 among the eight kinds


class _Evidence:
    """Stand-in evidence: a run is its (spec, fine); its residual vector is a base plus,
    with the probe-radius effect, the size (m) times the change of its world."""

    def __init__(self, cfg, change_coarse, change_fine):
        # the stand-in makes the coarse and fine meshes only: no finer-mesh worlds (those are
        # tested on real runs, test_contact_discrepancy.py and test_finer_meshes.py)
        self.cfg, self.sigma2 = replace(cfg, contact_mesh_refinements=()), SIGMA2
        self.change = {False: change_coarse, True: change_fine}  # {fine: {role: (L,) per m}}
        self.fine_runs = 0

    def runs_together(self, requests):
        self.fine_runs += sum(len(r.models) for r in requests if r.fine)
        return [[(spec, req.role, req.fine) for spec in req.models] for req in requests]

    def vector(self, run, shifted=True, discrepancy=None):
        spec, role, fine = run
        v = np.full(L, 0.3 if fine else 0.1)  # the fine mesh's base differs from the coarse one
        for e in spec.effects:
            if e["kind"] == "probe_radius":
                v = v + (e["radius"] - 0.005) * self.change[fine][role]
        return v


def _round(rng):
    return stand_in_round(rng, L, SIGMA2, 6)


@pytest.mark.parametrize("fine_grid", [(25, 9, 9), None])
def test_a_not_found_size_holds_on_the_fine_mesh_or_cannot_be_told(fine_grid):
    """Every coarse world makes the replay's own change of the data. When the fine mesh
    makes it too, the size is the replay's; when it makes half of it, a larger size is
    needed and the fine mesh is named; when its change is orthogonal to the replay's
    (after the nuisances), no size would be claimed ("cannot tell"). Without a fine grid
    the fine mesh is no world and is never simulated. (The probe radius here is sized by
    the coarse replay's change, as without ``contact_relinearisations``; with them it is
    sized by the fine mesh's own, the next test.)"""
    rng = np.random.default_rng(5)
    cfg = replace(DiagnosisConfig(), fine_grid=fine_grid, contact_relinearisations=0)
    rnd = _round(rng)
    cls, ctx = EFFECT_KINDS["probe_radius"], PhantomContext(np.array([0.06, 0.04, 0.03]), probe_radius=0.005)
    D = {"train": rng.normal(size=L) * 100, "validation": rng.normal(size=L) * 100}
    critical = 50.0

    same = _Evidence(cfg, D, D)
    base_size, world = world_min_size(same, rnd, cls, ctx, {"sign": 1.0}, 0.002, critical, LEVEL)
    # every world ties (the label is whichever rounding made least)
    ties = ("", *[n for n, _ in model_form_worlds(same)], *(mesh_world(same) or ())[:1])
    assert base_size is not None and 0 < base_size < cls.max_size and world in ties
    if fine_grid is None:
        assert mesh_world(same) is None
        weak = _Evidence(cfg, D, {r: np.zeros(L) for r in D})
        assert world_min_size(weak, rnd, cls, ctx, {"sign": 1.0}, 0.002, critical, LEVEL)[0] == pytest.approx(base_size)
        assert weak.fine_runs == 0
        return
    label = mesh_world(same)[0]
    assert label == "the 25x9x9 mesh" and same.fine_runs > 0

    half = _Evidence(cfg, D, {r: 0.5 * v for r, v in D.items()})
    size, world = world_min_size(half, rnd, cls, ctx, {"sign": 1.0}, 0.002, critical, LEVEL)
    assert world == label and size > 1.5 * base_size

    u = {r: rnd.nuisance.project(rng.normal(size=L)) for r in D}  # the nuisances leave the change whole
    d_t = rnd.nuisance.project(D["train"])
    u["train"] = u["train"] - d_t * (u["train"] @ d_t) / (d_t @ d_t)  # orthogonal to the fitted signature
    u["validation"] = np.zeros(L)  # and nothing of it along the signature on held-out data
    ortho = _Evidence(cfg, D, u)
    size, world = world_min_size(ortho, rnd, cls, ctx, {"sign": 1.0}, 0.002, critical, LEVEL)
    assert size is None and world == label


def test_a_kind_that_moves_the_contact_is_sized_by_the_fine_mesh_s_own_change():
    """A probe radius moves the contact (``Effect.moves_contact``): its fit measures the mesh
    error again at its parameters, so the test fits it as the fine mesh makes it, and its
    size is solved with the fine mesh's change as its signature. Where that change is half
    the coarse replay's, the size is twice the one the whole change needs, and it is the
    kind's own signature that sets it (no separate fine-mesh world is named)."""
    rng = np.random.default_rng(5)
    rnd = _round(rng)
    cls, ctx = EFFECT_KINDS["probe_radius"], PhantomContext(np.array([0.06, 0.04, 0.03]), probe_radius=0.005)
    assert cls.moves_contact and not EFFECT_KINDS["gravity"].moves_contact
    D = {"train": rng.normal(size=L) * 100, "validation": rng.normal(size=L) * 100}
    cfg = DiagnosisConfig()
    assert cfg.fine_grid and cfg.contact_relinearisations > 0
    whole, _ = world_min_size(_Evidence(cfg, D, D), rnd, cls, ctx, {"sign": 1.0}, 0.002, 50.0, LEVEL)
    half_ev = _Evidence(cfg, D, {r: 0.5 * v for r, v in D.items()})
    half, world = world_min_size(half_ev, rnd, cls, ctx, {"sign": 1.0}, 0.002, 50.0, LEVEL)
    assert whole is not None and half == pytest.approx(2.0 * whole, rel=0.06)
    assert world == "" and half_ev.fine_runs > 0


def test_the_fine_mesh_of_a_phantom_stl_is_named_by_its_element_size():
    """An STL phantom's fine mesh is its own at half the mean edge, not the box's 25x9x9
    grid: the world is named by its element size, and runs at the fine fits' time step."""
    cfg = DiagnosisConfig()
    label, fields = mesh_world(SimpleNamespace(cfg=cfg, fine_element_size=0.0035))
    assert label == "the finer mesh (3.5 mm elements)"
    assert fields == {"simulation": (("dt", cfg.fine_fit_dt),)}
    assert mesh_world(SimpleNamespace(cfg=replace(cfg, nuisances=tuple(n for n in cfg.nuisances if n != "mesh")))) is None


def test_the_law_world_is_the_other_law_of_the_base_model():
    """A base model replayed with the stable neo-Hookean law (``--law``, against the
    corotational law's element inversion under deep presses) is held to the corotational
    law's world, not to a copy of itself; the other worlds do not change."""
    cfg = DiagnosisConfig()
    worlds = dict(model_form_worlds(SimpleNamespace(cfg=cfg)))
    assert worlds["law stable_neo_hookean"] == {"law": "stable_neo_hookean"}
    assert worlds["law stable_yeoh k=1"] == {"law": "stable_yeoh", "stiffening": 1.0}
    nh = dict(model_form_worlds(SimpleNamespace(cfg=replace(cfg, law="stable_neo_hookean"))))
    assert nh.pop("law corotational") == {"law": "corotational"} and "law stable_neo_hookean" not in nh
    worlds.pop("law stable_neo_hookean")
    assert nh == worlds and len(nh) == 7
    # a base model that already stiffens has no stiffened world of itself
    yeoh = dict(model_form_worlds(SimpleNamespace(cfg=replace(cfg, law="stable_yeoh"))))
    assert not any(k.startswith("law stable_yeoh") for k in yeoh) and "law stable_neo_hookean" in yeoh
