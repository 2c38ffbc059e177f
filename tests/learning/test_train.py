"""Training: deterministic for a seed, and on a session replayed with a wrong E the 2D
network reduces the test error by at least 10 % (Wu et al. 2020, Table 3 reports 15-21 %)."""

import numpy as np
import pytest
import torch

from core.learning import NetworkConfig, TrainConfig, train_and_test, train_correction
from core.learning.config import LearningError

from tests.learning.conftest import SMALL_NET, WRONG_E

FAST = TrainConfig(max_epochs=6, patience=2, batch_size=16, max_points=256, threads=1, seed=0)


def _subset(frames, n):
    """The first n frames of the train and validation sequences (a quick training set)."""
    from dataclasses import replace

    out = {}
    for name, f in frames.items():
        if f.role in ("train", "validation"):
            out[name] = replace(f, times=f.times[:n], positions=f.positions[:n], poses=f.poses[:n], clouds=f.clouds[:n])
    return out


@pytest.mark.parametrize("kind", ["2d", "3d"])
def test_training_is_deterministic_for_a_seed(wrong_e_frames, gravity_prepared, kind):
    frames = _subset(wrong_e_frames, 24)
    cfg = TrainConfig(max_epochs=2, patience=5, batch_size=8, max_points=128, threads=1, seed=7)
    net = NetworkConfig(kind=kind, **SMALL_NET)
    a = train_correction(frames, gravity_prepared.size, net, cfg)
    b = train_correction(frames, gravity_prepared.size, net, cfg)
    c = train_correction(frames, gravity_prepared.size, net, TrainConfig(**{**cfg.to_json(), "seed": 8}))
    assert [h["train_loss"] for h in a.history] == [h["train_loss"] for h in b.history]
    assert [h["validation_loss"] for h in a.history] == [h["validation_loss"] for h in b.history]
    for (k, v), w in zip(a.network.state_dict().items(), b.network.state_dict().values()):
        assert torch.equal(v, w), k
    assert [h["train_loss"] for h in a.history] != [h["train_loss"] for h in c.history]


def test_training_needs_train_and_validation_sequences(wrong_e_frames, gravity_prepared):
    only_train = {n: f for n, f in wrong_e_frames.items() if f.role == "train"}
    with pytest.raises(LearningError, match="no 'validation' sequence"):
        train_correction(only_train, gravity_prepared.size, NetworkConfig(kind="2d", **SMALL_NET), FAST)


def test_2d_network_corrects_a_wrong_youngs_modulus(wrong_e_frames, gravity_prepared, wrong_e_config):
    """Replayed at 1 kPa (truth 5 kPa, with gravity) the mesh sags ~2.7 mm too deep; the
    test error is ~4.2 mm against a ~1.4 mm noise floor. The 2D network must remove at
    least 10 % of it, in the loop (the paper's use) and offline."""
    rep = train_and_test(gravity_prepared, wrong_e_config, NetworkConfig(kind="2d", **SMALL_NET), FAST,
                         frames=wrong_e_frames)
    te = rep.test_error
    report = rep.to_json()
    print(f"\nE = {WRONG_E:g} Pa, 2D: no network {te['no_network'] * 1e3:.3f} mm, in-loop {te['corrected'] * 1e3:.3f} mm "
          f"({report['improvement']:.1%}), offline {te['corrected_offline'] * 1e3:.3f} mm ({report['improvement_offline']:.1%}); "
          f"epochs {len(rep.training.history)}, best {rep.training.best_epoch}, {rep.training.timings['per_epoch']:.2f} s/epoch")
    assert te["no_network"] > 3e-3  # the wrong E is visible (noise floor ~1.4 mm)
    assert report["improvement"] >= 0.10
    assert report["improvement_offline"] >= 0.10
    # in-loop (anchored) may differ from offline only through the nodes the network does not
    # set (sides and interior follow the corrected top layer); measured -1 % (1.473 vs 1.484 mm)
    # since they follow it elastically, +9 % (1.61 vs 1.48 mm) before that, so 15 % tolerance.
    # With corrections stacking (mode "additive") in-loop was 3.4 mm, +130 %.
    assert te["corrected"] <= 1.15 * te["corrected_offline"]
    assert all(s.status == "ok" for s in rep.in_loop.values())
    # the signed column: at 1 kPa the mesh sags below the measured top; the correction
    # removes most of that bias, in the loop and offline
    ts = report["test_signed_residual"]
    print(f"signed residual: no network {ts['no_network'] * 1e3:+.3f} mm, in-loop {ts['corrected'] * 1e3:+.3f} mm, "
          f"offline {ts['corrected_offline'] * 1e3:+.3f} mm; unobserved nodes within {report['max_unobserved_offset'] * 1e3:.2f} mm")
    assert ts["no_network"] > 1e-3
    assert abs(ts["corrected"]) < 0.5 * ts["no_network"] and abs(ts["corrected_offline"]) < 0.5 * ts["no_network"]
    # validation loss at the kept epoch is below the uncorrected one
    best = rep.training.history[rep.training.best_epoch - 1]["validation_loss"]
    assert best < 0.9 * rep.training.baseline["validation"]
    # only the top layer moved, within the bound
    seq = next(iter(rep.offline.values()))
    from core.learning import top_layer_nodes

    top = top_layer_nodes(seq.positions.shape and wrong_e_frames[seq.name].grid)
    others = np.setdiff1d(np.arange(seq.positions.shape[1]), top)
    np.testing.assert_array_equal(seq.positions[:, others], wrong_e_frames[seq.name].positions[:, others])
    bound = 0.5 * gravity_prepared.size / (np.array(wrong_e_frames[seq.name].grid) - 1)
    assert np.all(np.abs(seq.corrections) <= bound * (1 + 1e-6))


def test_frame_stride_trains_on_every_kth_train_frame_only(wrong_e_frames, gravity_prepared):
    frames = _subset(wrong_e_frames, 24)
    cfg = TrainConfig(max_epochs=1, patience=1, batch_size=8, max_points=64, threads=1, seed=0, frame_stride=3)
    res = train_correction(frames, gravity_prepared.size, NetworkConfig(kind="2d", **SMALL_NET), cfg)
    n_train = sum(int(f.finite[::3].sum()) for f in frames.values() if f.role == "train")
    n_val = sum(int(f.finite.sum()) for f in frames.values() if f.role == "validation")
    assert res.n_frames == {"train": n_train, "validation": n_val} and n_train == 8 * 2
    with pytest.raises(LearningError, match="frame_stride must be >= 1"):
        TrainConfig(frame_stride=0)
