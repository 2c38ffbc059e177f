"""Checkpoints: a write-then-read round trip gives identical outputs and metadata."""

import pytest
import torch

from core.learning import NetworkConfig, build_network, load_checkpoint, save_checkpoint
from core.learning.config import LearningError
from core.simulation import Gravity
from core.simulation.replay import ReplayConfig
from tests.learning.test_networks import SIZE, _inputs


@pytest.mark.parametrize("kind", ["2d", "3d"])
def test_round_trip_gives_identical_outputs(tmp_path, kind):
    grid = (13, 5, 5)
    torch.manual_seed(5)
    net = build_network(NetworkConfig(kind=kind, widths=(4, 8, 16), pose="position"), grid, SIZE).eval()
    with torch.no_grad():  # move away from the initialisation so that weights matter
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    config = ReplayConfig(youngs_modulus=1234.5, poisson_ratio=0.45, effects=(Gravity(),))
    path = save_checkpoint(tmp_path / "net.pt", net, session="/data/s1", replay_config=config, extra={"note": [1, 2]})
    ck = load_checkpoint(path)
    x, pose = _inputs(grid, batch=4)
    with torch.no_grad():
        assert torch.equal(net(x, pose), ck.network(x, pose))
    assert ck.session == "/data/s1"
    assert ck.youngs_modulus == 1234.5
    assert ck.grid == grid
    assert ck.network.config == net.config
    assert ck.replay_config() == config
    assert ck.extra == {"note": [1, 2]}
    assert not ck.network.training


def test_bad_checkpoint_files_name_the_file(tmp_path):
    with pytest.raises(LearningError, match="missing.pt: checkpoint file not found"):
        load_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(LearningError, match="junk.pt: not a readable torch checkpoint"):
        load_checkpoint(junk)
    other = tmp_path / "other.pt"
    torch.save({"format": "something-else/2"}, other)
    with pytest.raises(LearningError, match="other.pt: expected a 'tissuetwin-correction/1' checkpoint"):
        load_checkpoint(other)
