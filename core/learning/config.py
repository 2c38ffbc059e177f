"""Configuration of the learned correction: network shape and training schedule.

Frozen dataclasses with one docstring per field (``../shared/STYLE.md``). The defaults
are the paper's network (Wu et al. 2020, Sec. 3.3: feature sizes 64, 128, 256; 4
fusion convolutions after the robot pose joins at the bottleneck); tests use narrower
widths through :class:`NetworkConfig` so that they run in seconds on a CPU.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from core.errors import TissueTwinError

__all__ = ["LearningError", "NetworkConfig", "TrainConfig", "MODEL_KINDS"]

MODEL_KINDS = ("2d", "3d")
"""``"3d"``: the 3D UNet over the whole node grid; ``"2d"``: the 2D UNet over its top layer."""


class LearningError(TissueTwinError, ValueError):
    """Bad input to the learned correction: an unknown model kind, a bad checkpoint
    file, a session without train/validation/test sequences, data of the wrong shape."""


@dataclass(frozen=True)
class NetworkConfig:
    """Shape of a correction network (Wu et al. 2020, Sec. 3.3, Fig. 3)."""

    kind: str = "3d"
    """``"3d"`` (3D UNet on the (nx, ny, nz) node grid) or ``"2d"`` (2D UNet on the top layer)."""
    widths: tuple[int, int, int] = (64, 128, 256)
    """Features of the three encoder blocks (two 3x3(x3) convolutions each; paper: 64, 128, 256)."""
    fusion_convs: int = 4
    """Convolutions after the pose is concatenated at the bottleneck (paper: 4); the
    last one brings the features back to ``widths[-1]``."""
    pose: str = "position_quaternion"
    """Robot pose fed at the bottleneck: ``"position_quaternion"`` (probe centre and tool
    orientation xyzw, phantom frame; 7 values) or ``"position"`` (3 values)."""
    bound_fraction: float = 0.5
    """Correction bound as a fraction of the voxel (node spacing) per axis; the paper
    uses half the voxel length "to prevent vertices from crossing"."""

    def __post_init__(self):
        if self.kind not in MODEL_KINDS:
            raise LearningError(f"model kind must be one of {MODEL_KINDS}, got {self.kind!r}")
        if len(self.widths) != 3 or any(int(w) < 1 for w in self.widths):
            raise LearningError(f"widths must be 3 positive feature counts, got {self.widths}")
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        if int(self.fusion_convs) < 1:
            raise LearningError(f"fusion_convs must be >= 1, got {self.fusion_convs}")
        if self.pose not in ("position_quaternion", "position"):
            raise LearningError(f"pose must be 'position_quaternion' or 'position', got {self.pose!r}")
        if not (0.0 < float(self.bound_fraction) <= 1.0):
            raise LearningError(f"bound_fraction must be in (0, 1], got {self.bound_fraction}")

    @property
    def pose_dim(self) -> int:
        """Number of pose values per frame (7 or 3)."""
        return 7 if self.pose == "position_quaternion" else 3

    def to_json(self) -> dict:
        return {**asdict(self), "widths": list(self.widths)}

    @classmethod
    def from_json(cls, d: dict) -> "NetworkConfig":
        d = dict(d)
        if "widths" in d:
            d["widths"] = tuple(d["widths"])
        return cls(**d)


@dataclass(frozen=True)
class TrainConfig:
    """How a correction network is trained (Wu et al. 2020, Sec. 3.3 and 5.1)."""

    max_epochs: int = 40
    """Upper bound on epochs (passes over the train frames)."""
    patience: int = 5
    """Early stopping: stop after this many epochs without a lower validation loss;
    the weights of the best validation epoch are kept (paper: "until the loss on the
    validation data flattens or goes up")."""
    batch_size: int = 16
    """Frames per Adam step."""
    learning_rate: float = 1e-3
    """Adam step size."""
    max_points: int = 1024
    """Measured points drawn per frame and step for the loss (a fresh random subset each
    epoch; a fixed subset for validation); all points are used for the reported errors."""
    seed: int = 0
    """Seeds network initialisation, batch order and point subsets (torch.manual_seed)."""
    threads: int | None = None
    """torch intra-op threads during training (None: leave torch's setting)."""
    deterministic: bool = True
    """torch.use_deterministic_algorithms(True) while training (CPU kernels are)."""
    supersample: int = 3
    """Mesh super-sampling of the Chamfer loss (paper: 3, linear interpolation)."""
    frame_stride: int = 1
    """Train on every ``frame_stride``-th frame of each train sequence (1: all, the
    paper's); validation always uses every frame. For cheaper runs at paper size."""

    def __post_init__(self):
        for name in ("max_epochs", "patience", "batch_size", "max_points", "supersample", "frame_stride"):
            if int(getattr(self, name)) < 1:
                raise LearningError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (float(self.learning_rate) > 0):
            raise LearningError(f"learning_rate must be positive, got {self.learning_rate}")

    def to_json(self) -> dict:
        return asdict(self)
