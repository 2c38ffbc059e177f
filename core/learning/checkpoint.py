"""Checkpoints of correction networks: what was trained, on which session, at which E.

A checkpoint is one ``torch.save`` file holding a plain dict (loadable with
``torch.load(..., weights_only=True)``): the format tag, the session path, the network
configuration, the node grid and box size that fix the input encoding and the bound,
the replay settings the training simulation used (E, Poisson's ratio, law, effects,
numerics, element size), the training schedule and history, and the weights.

A network trained on an unstructured mesh (a ``phantom.stl``) also stores that mesh's
arrays under ``"mesh"`` (``nodes`` (N, 3) float64 m phantom frame, ``tets`` (E, 4) int64,
``surface_triangles`` (T, 3) int64, ``size`` (3,) m; torch tensors), from which its
voxel map (:mod:`core.learning.voxels`) is rebuilt on load. The arrays, not the STL's
content hash, because the map is tied to the exact nodes and their order, and those
depend on more than the STL: the element size, the Gmsh version and the meshing recipe
(``core.simulation.meshing.MESH_VERSION``) all change them, and a hash could only say
the mesh no longer matches, not rebuild it. They are small (~20 kB at the default
element size) and make the checkpoint usable without the session or Gmsh. Checkpoints
without ``"mesh"`` (all older ones) are box-grid networks and load as before.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from core.learning.config import LearningError, NetworkConfig
from core.learning.networks import CorrectionNetwork, build_network

__all__ = ["CHECKPOINT_FORMAT", "Checkpoint", "save_checkpoint", "load_checkpoint"]

CHECKPOINT_FORMAT = "tissuetwin-correction/1"


@dataclass
class Checkpoint:
    """A loaded (or just trained) correction network with everything needed to use it.

    Attributes:
        network: the :class:`CorrectionNetwork` in eval mode.
        session: path of the session it was trained on.
        replay: dict of the replay settings of the training simulation (``youngs_modulus``
            Pa, ``poisson_ratio``, ``grid``, ``element_size`` (m or None), ``law``, ``effects``, ``simulation``,
            ``voxel_size`` m, ``supersample``); :meth:`replay_config` rebuilds it.
        extra: anything else stored (training config, history, ...).
    """

    network: CorrectionNetwork
    session: str
    replay: dict
    extra: dict

    @property
    def youngs_modulus(self) -> float:
        """E of the training simulation, Pa."""
        return float(self.replay["youngs_modulus"])

    @property
    def grid(self) -> tuple[int, int, int]:
        """The network's grid: the box's node grid, or the voxel grid of its mesh."""
        return self.network.grid

    @property
    def mesh(self):
        """The unstructured :class:`TetMesh` the network corrects, None for a box-grid network."""
        return self.network.mesh

    def replay_config(self, **overrides):
        """The :class:`core.simulation.replay.ReplayConfig` of the training simulation."""
        from core.simulation import SimulationConfig, effect_from_dict
        from core.simulation.replay import ReplayConfig
        r = dict(self.replay)
        element_size = r.get("element_size")  # absent in checkpoints from before STL phantoms
        cfg = ReplayConfig(
            youngs_modulus=float(r["youngs_modulus"]),
            poisson_ratio=float(r["poisson_ratio"]),
            grid=tuple(int(g) for g in r["grid"]),
            element_size=None if element_size is None else float(element_size),
            law=r["law"],
            simulation=SimulationConfig(**r["simulation"]),
            effects=tuple(effect_from_dict(e) for e in r["effects"]),
            voxel_size=float(r["voxel_size"]),
            supersample=int(r["supersample"]),
        )
        if overrides:
            from dataclasses import replace

            cfg = replace(cfg, **overrides)
        return cfg


def replay_settings(config) -> dict:
    """JSON-ready dict of a :class:`ReplayConfig` as stored in checkpoints."""
    return {
        "youngs_modulus": float(config.youngs_modulus),
        "poisson_ratio": float(config.poisson_ratio),
        "grid": [int(g) for g in config.grid],
        "element_size": None if config.element_size is None else float(config.element_size),
        "law": config.law,
        "simulation": asdict(config.simulation),
        "effects": [e.to_dict() for e in config.effects],
        "voxel_size": float(config.voxel_size),
        "supersample": int(config.supersample),
    }


def save_checkpoint(path, network: CorrectionNetwork, *, session, replay_config, extra: dict | None = None) -> Path:
    """Write a checkpoint file (parents created).

    Args:
        path: file to write (``.pt``).
        network: the trained network.
        session: the session folder it was trained on.
        replay_config: the :class:`ReplayConfig` of the training simulation (E etc.).
        extra: JSON-like extras (training config, losses, timings).

    Returns:
        the path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {
        "format": CHECKPOINT_FORMAT,
        "session": str(session),
        "network": network.config.to_json(),
        "grid": list(network.grid),
        "size": [float(v) for v in network.size.tolist()],
        "normalisation": {
            "positions": "(x - size/2) / (size/2) and (x - rest) / bound, per axis",
            "bound": [float(v) for v in network.bound.tolist()],
        },
        "replay": replay_settings(replay_config),
        "extra": extra or {},
        "state_dict": network.state_dict(),
    }
    if network.mesh is not None:
        blob["mesh"] = _mesh_blob(network.mesh)
        blob["normalisation"]["positions"] = ("(x - centre)/(size/2) and (x - rest)/bound per axis over the mesh's rest "
                                              "bounding box, scattered to the voxel grid (core.learning.voxels)")
    tmp = path.with_name(path.name + ".tmp")
    torch.save(blob, tmp)
    tmp.replace(path)
    return path


def load_checkpoint(path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` for inference.

    Raises:
        LearningError: the file is missing, not a checkpoint, of another format, or its
            weights do not fit its configuration.
    """
    path = Path(path)
    if not path.is_file():
        raise LearningError(f"{path}: checkpoint file not found")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a corrupt file
        raise LearningError(f"{path}: not a readable torch checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(blob, dict) or blob.get("format") != CHECKPOINT_FORMAT:
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise LearningError(f"{path}: expected a {CHECKPOINT_FORMAT!r} checkpoint, got {got!r}")
    try:
        mesh = _mesh_from_blob(blob["mesh"]) if blob.get("mesh") is not None else None
        net = build_network(NetworkConfig.from_json(blob["network"]), blob["grid"], np.asarray(blob["size"]), mesh)
        net.load_state_dict(blob["state_dict"])
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise LearningError(f"{path}: checkpoint does not match its network configuration: {exc}") from exc
    net.eval()
    return Checkpoint(network=net, session=blob["session"], replay=blob["replay"], extra=blob.get("extra", {}))


def _mesh_blob(mesh) -> dict:
    """The arrays of an unstructured mesh as torch tensors (``weights_only`` loadable)."""
    return {
        "nodes": torch.tensor(np.asarray(mesh.nodes, dtype=np.float64)),
        "tets": torch.tensor(np.asarray(mesh.tets, dtype=np.int64)),
        "surface_triangles": torch.tensor(np.asarray(mesh.surface_triangles, dtype=np.int64)),
        "size": torch.tensor(np.asarray(mesh.size, dtype=np.float64)),
    }


def _mesh_from_blob(d: dict):
    """The read-only :class:`TetMesh` (``grid=None``) of :func:`_mesh_blob`'s dict."""
    from core.simulation.mesh import TetMesh

    arrays = {k: d[k].numpy().copy() for k in ("nodes", "tets", "surface_triangles", "size")}
    for a in arrays.values():
        a.flags.writeable = False
    return TetMesh(nodes=arrays["nodes"], tets=arrays["tets"], surface_triangles=arrays["surface_triangles"], grid=None,
                   size=arrays["size"])
