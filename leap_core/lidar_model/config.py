"""Typed settings of a LiDAR-only model trained on a project's labels (:mod:`leap_core.lidar_model`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from leap_core.bounds import SEED_MAX, check_bounds, within
from leap_core.consistency.config import BackboneConfig
from leap_core.errors import ConfigError


@dataclass(frozen=True)
class LidarModelConfig:
    """How ``leap train`` trains the 3D backbone on labeled scans (docs/METHOD.md "A LiDAR-only model").

    Every scan of the training data is a cloud of its own LiDAR frame (no pose, no camera). A step draws
    ``points_per_scan`` points of ``scans_per_step`` scans (labeled points first), and the loss is the
    class-weighted cross-entropy over the drawn points that carry a label.
    """

    steps: int = field(default=1000, metadata=within(1, 10_000_000))
    """Optimisation steps (the scans are visited in a seeded random order, pass after pass)."""
    lr: float = field(default=2e-3, metadata=within(0, 1, low_open=True))
    """Peak AdamW learning rate from random weights (linear warm-up over 5 % of the steps, cosine decay)."""
    finetune_lr: float = field(default=5e-4, metadata=within(0, 1, low_open=True))
    """Peak learning rate instead of ``lr`` when training starts from a checkpoint (``--init``): a
    quarter of ``lr``, so fine-tuning adapts what the network knows rather than overwriting it."""
    weight_decay: float = field(default=1e-3, metadata=within(0, 1))
    """AdamW decoupled weight decay."""
    scans_per_step: int = field(default=1, metadata=within(1, 64))
    """Scans in one step (gradients over their points together)."""
    points_per_scan: int = field(default=16384, metadata=within(0, 10_000_000))
    """Points drawn from a scan per step (0: all); bounds the time and memory of a step."""
    labeled_share: float = field(default=0.9, metadata=within(0, 1))
    """Share of the draw taken from the scan's labeled points first; the rest is context."""
    augment: bool = True
    """Random turn about z, mirror of y and scale in [0.95, 1.05] of every training scan."""
    class_balance_power: float = field(default=0.5, metadata=within(0, 1))
    """Class weights ``w_c ∝ n_c^(-p)`` of the training labels (0: unweighted)."""
    seed: int = field(default=0, metadata=within(0, SEED_MAX))
    """Seed of the initial weights, the scan order, the point draws and the augmentation: same seed, data
    and settings give the same checkpoint on the CPU, interrupted and resumed or not."""
    checkpoint_every: int = field(default=100, metadata=within(1, 10_000_000))
    """Steps between the resumable training states written beside the model (``<model>.state.pt``)."""
    val_block: int = field(default=10, metadata=within(0, 100_000))
    """Validation by frame block: each sequence's frames are cut into blocks of this many frames and every
    ``val_every``-th block is held apart (never trained on). 0: no block split (validation only on the
    sequences given apart, if any)."""
    val_every: int = field(default=5, metadata=within(2, 1000))
    """Every this-many-th block is a validation block (5: 20 % of the frames)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Torch device; ``auto`` takes CUDA when available."""
    num_threads: int = field(default=0, metadata=within(0, 1024))
    """``torch.set_num_threads`` during training and prediction; 0 leaves torch's setting alone."""
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    """The network's sizes: the 3D-CN's WaffleIron-style backbone (CPU-sized defaults)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        if self.device not in ("auto", "cpu", "cuda"):
            raise ConfigError(f"must be 'auto', 'cpu' or 'cuda', got {self.device!r}", field=("device",))


def model_config_to_dict(cfg: LidarModelConfig) -> dict[str, Any]:
    """Plain-data form (tuples become lists), for checkpoints and model cards."""
    d = asdict(cfg)
    d["backbone"]["grid_cells"] = list(d["backbone"]["grid_cells"])
    return d


def model_config_from_dict(d: dict[str, Any]) -> LidarModelConfig:
    """Inverse of :func:`model_config_to_dict`.

    Raises:
        ConfigError: an unknown field (named), or a value out of its range.
    """
    d = dict(d)
    bb = dict(d.pop("backbone", {}))
    if "grid_cells" in bb:
        bb["grid_cells"] = tuple(float(c) for c in bb["grid_cells"])
    known = set(LidarModelConfig.__dataclass_fields__)
    for key in d:
        if key not in known:
            raise ConfigError("unknown setting", field=(key,))
    for key in bb:
        if key not in BackboneConfig.__dataclass_fields__:
            raise ConfigError("unknown setting", field=("backbone", key))
    try:
        backbone = BackboneConfig(**bb)
    except ConfigError as exc:
        raise exc.within("backbone") from None
    return LidarModelConfig(**d, backbone=backbone)


__all__ = ["LidarModelConfig", "model_config_from_dict", "model_config_to_dict"]
