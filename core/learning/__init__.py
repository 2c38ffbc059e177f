"""Learned per-node correction of the FEM replay (Wu et al. 2020, Sec. 3.3, Table 3).

Public surface::

    frames = build_frames(prepared, ReplayConfig(youngs_modulus=E))     # per-frame arrays
    result = train_correction(frames, prepared.size, NetworkConfig(kind="2d"))
    save_checkpoint(path, result.network, session=prepared.path, replay_config=config)
    ck = load_checkpoint(path)
    field = correction_field(ck, frames["seq01"])                       # (F, K, 3) m of ck.network.corrected_nodes
    corrected = replay_in_loop(ck, prepared, "seq01", reference=frames["seq01"])  # the paper's use (anchored)
    report = train_and_test(prepared, config, NetworkConfig(kind="3d"))   # + test errors

On a ``phantom.stl`` (an unstructured mesh) the same calls work: the frames carry the
replay's mesh and the networks run on a voxel grid around it (:mod:`core.learning.voxels`).

Importing this package imports torch.
"""

from core.learning.apply import (
    IN_LOOP_MODES,
    CorrectedSequence,
    correct_offline,
    correction_field,
    elastic_extension,
    mean_error,
    replay_in_loop,
    signed_residual,
)
from core.learning.checkpoint import CHECKPOINT_FORMAT, Checkpoint, load_checkpoint, save_checkpoint
from core.learning.config import MODEL_KINDS, LearningError, NetworkConfig, TrainConfig
from core.learning.data import SequenceFrames, build_frames, frames_from_replay, probe_poses, top_layer_nodes
from core.learning.experiment import EvaluationResult, TrainReport, evaluate_networks, train_and_test, write_evaluation
from core.learning.loss import chamfer_loss, point_to_mesh_distances_torch, supersample_matrix
from core.learning.networks import CorrectionNetwork, UNet2D, UNet3D, build_network
from core.learning.train import TrainResult, train_correction
from core.learning.voxels import VoxelMap, corrected_nodes, voxel_map

__all__ = [
    "CorrectedSequence",
    "correct_offline",
    "correction_field",
    "mean_error",
    "replay_in_loop",
    "signed_residual",
    "elastic_extension",
    "IN_LOOP_MODES",
    "CHECKPOINT_FORMAT",
    "Checkpoint",
    "load_checkpoint",
    "save_checkpoint",
    "MODEL_KINDS",
    "LearningError",
    "NetworkConfig",
    "TrainConfig",
    "SequenceFrames",
    "build_frames",
    "frames_from_replay",
    "probe_poses",
    "top_layer_nodes",
    "EvaluationResult",
    "TrainReport",
    "evaluate_networks",
    "train_and_test",
    "write_evaluation",
    "chamfer_loss",
    "point_to_mesh_distances_torch",
    "supersample_matrix",
    "CorrectionNetwork",
    "UNet2D",
    "UNet3D",
    "build_network",
    "TrainResult",
    "train_correction",
    "VoxelMap",
    "corrected_nodes",
    "voxel_map",
]
