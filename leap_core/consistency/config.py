"""Typed configuration of the 3D Consistency Network (docs/METHOD.md stage C).

``ConsistencyConfig`` holds the self-training and fusion-back parameters; it nests ``BackboneConfig``,
the sizes of the WaffleIron-style point backbone. The defaults are sized for a 2-core CPU (the demo
sequence trains and predicts in minutes); :meth:`ConsistencyConfig.paper_scale` gives the WaffleIron
sizes the paper uses, for a GPU.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from leap_core.bounds import SEED_MAX, check_bounds, within
from leap_core.errors import ConfigError

ADDED_FIELDS: dict[tuple[str, ...], Any] = {
    ("test_time_views",): 1,
    ("new_voxel_margin",): 0.0,
    ("backbone", "position_inputs"): True,
    ("finetune_lr",): 5e-4,
    ("finetune_min_steps",): 0,
    ("precision",): "float32",
}
"""Fields added to :class:`ConsistencyConfig` after runs and checkpoints had been written, each with the
value that computes what was computed before the field existed. Fingerprints (the 3D-CN stage's, a
checkpoint's training inputs) leave a field out at that value (:func:`fingerprint_form`), so a new field
does not make every finished run retrain its network."""


def fingerprint_form(plain: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of a :class:`ConsistencyConfig`'s plain form (``train.config_to_dict``, or the
    ``consistency`` section of the pipeline's) without the :data:`ADDED_FIELDS` that hold their former
    value: what fingerprints hash."""
    out = copy.deepcopy(dict(plain))
    for path, former in ADDED_FIELDS.items():
        node: Any = out
        for key in path[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and path[-1] in node and node[path[-1]] == former:
            del node[path[-1]]
    return out


@dataclass(frozen=True)
class BackboneConfig:
    """Sizes of the WaffleIron-style backbone (:mod:`leap_core.consistency.backbone`)."""

    channels: int = field(default=64, metadata=within(4, 1024))
    """Width F of every point token (WaffleIron: 256)."""
    layers: int = field(default=6, metadata=within(1, 128))
    """Number of (channel-mixing MLP + spatial-mixing) layer pairs (WaffleIron: 48 on SemanticKITTI)."""
    grid_cells: tuple[float, float, float] = field(
        default=(0.8, 0.8, 0.8), metadata=within(0.1, 10, unit="m")
    )
    """2D grid cell size in metres for the planes (xy, xz, yz). Layer ``l`` mixes on plane ``l % 3``
    (WaffleIron: 0.4 m on every plane). At least 0.1 m: a plane spans the ±100 m the coordinates are
    clipped to (``consistency.data.GRID_EXTENT``), 2000² cells of ``channels`` features at that size."""
    knn: int = field(default=16, metadata=within(1, 64))
    """Neighbours of each point used by the kNN point embedding (WaffleIron: 16)."""
    embed_channels: int = field(default=32, metadata=within(1, 1024))
    """Hidden width of the per-neighbour layer of the kNN embedding, before the max over neighbours."""
    mlp_ratio: int = field(default=2, metadata=within(1, 16))
    """Hidden width of the channel-mixing MLP as a multiple of ``channels`` (WaffleIron: 2)."""
    kernel_size: int = field(default=3, metadata=within(1, 15))
    """Kernel size of the depth-wise 2D convolutions of the spatial mixing (WaffleIron: 3)."""
    use_intensity: bool = True
    """Also feed the LiDAR remission. The paper trains on XYZ only (``paper_scale`` does); on a CPU budget of
    a few hundred steps, remission is what lets a small network tell road, sidewalk and terrain apart
    (tuning seeds 101-103, camera-view mIoU after one round: 71.9 with remission, 64.7 from XYZ alone;
    docs/METHOD.md, "How defaults were chosen")."""
    position_inputs: bool = True
    """Feed each point's position in the sensor frame (x, y, z and range) to the network, besides its
    height above the ground and neighbourhood shape. On a car the LiDAR rides at a fixed height, so z and
    range place a point relative to the road; on a survey drone flying at 10-40 m they mostly say how high
    it flew, so the same z is ground in one scan and a person's head in another. ``False`` keeps only the
    inputs that do not depend on the sensor's height. Measured on the farm's tuning sequences 101-103
    (one round, camera-view mIoU): 91.6 on the mean either way, so the default keeps them
    (docs/METHOD.md C.5)."""
    drop_path: float = field(default=0.0, metadata=within(0, 1, high_open=True))
    """Stochastic-depth probability at the last layer (linear ramp from 0); 0 disables it."""
    layer_scale: float = field(default=1.0, metadata=within(0, 10))
    """Initial value of the per-channel residual scales (LayerScale). 1 suits a shallow stack; deep ones
    (``paper_scale``: 1e-4) start near identity to train stably."""

    def __post_init__(self) -> None:
        if len(self.grid_cells) != 3:
            raise ConfigError(f"must be 3 sizes (xy, xz, yz), got {self.grid_cells}", field=("grid_cells",))
        check_bounds(self)
        if self.kernel_size % 2 == 0:
            raise ConfigError(f"must be odd, got {self.kernel_size}", field=("kernel_size",))

    @property
    def in_features(self) -> int:
        """Per-point input width: (x, y, z, range,) height above ground, 5 neighbourhood shape descriptors
        (+ remission); see :func:`leap_core.consistency.data.prepare_cloud`."""
        return 6 + 4 * self.position_inputs + self.use_intensity


@dataclass(frozen=True)
class ConsistencyConfig:
    """Self-training of the 3D Consistency Network and the fusion of its predictions back into the grid.

    Fusion back: the network's per-point log-probabilities are added to the voxel grid with weight
    ``1 / temperature`` (a tempered Bayesian update, ``log V(i) += log P_net(i|x) / T``). ``T = 1`` trusts
    a network prediction like one camera observation of that point; ``T → ∞`` ignores the network.
    """

    enabled: bool = False
    """Run stage C at all (``leap run --3dcn`` turns it on)."""
    iterations: int = field(default=1, metadata=within(1, 2))
    """Self-training rounds: 1 (default) or 2 (the paper: the second adds little and can reinforce errors)."""
    share: float = field(default=0.2, metadata=within(0, 1, low_open=True))
    """Per class, the fraction of its labeled points (the most confident ones) used as training labels."""
    selection_scope: Literal["scan", "sequence"] = "scan"
    """Where the per-class top-``share`` ranking happens: within each scan, or over all points of the sequence
    at once. ``scan`` makes every scan contribute labels of every class it shows (a scan whose only "truck"
    is a mislabeled car hands that car to the truck class); ``sequence`` takes a class's labels from the
    voxels where it is surest, wherever they are. Chosen on the tuning seeds 101-103 (30 frames, camera-view
    mIoU after one round, other settings at their former defaults): ``scan`` 73.7, ``sequence`` 71.9
    (docs/METHOD.md, "How defaults were chosen")."""
    rank_by_views: bool = True
    """Among points of equal confidence, select those whose voxel more frames observed first. Smoothed
    confidences saturate, and a voxel one image painted with many points (a moving object's track, a
    mistaken mask) saturates as fast as one many views agreed on. Kept on the tuning seeds 101-103 (a tie:
    camera-view mIoU after one round 71.9 with, 72.1 without; docs/METHOD.md, "How defaults were chosen")."""
    temperature: float = field(default=2.0, metadata=within(0.01, 1000, also=(math.inf,)))
    """Trust in the network when fusing back: its log-probabilities enter with weight ``1/temperature``.
    ``T = 1`` counts the network's view of a voxel like one camera observation; ``T → ∞`` ignores it.
    2.0 (half an observation, up to ½·ln(1/prob_floor) ≈ 3.5 nats) lets the network decide the voxels no
    camera saw and those whose camera evidence is weak, but not overrule confident camera voxels. Chosen on
    the tuning seeds 101-103 (30 frames, camera-view mIoU after one round for T = 0.25 / 0.5 / 1 / 2: 71.9 /
    75.8 / 77.4 / 78.5, voxel labels 83.6; docs/METHOD.md, "How defaults were chosen")."""
    network_evidence: Literal["voxel", "point"] = "voxel"
    """How predictions enter the Bayesian update. ``voxel``: the mean floored log-probability of all points
    in a voxel (over all scans) is one observation, so the network flips only voxels whose camera evidence
    is weaker than its own, and decides voxels no camera saw. ``point``: every point prediction is one
    observation (like each painted camera point); the network's votes then grow with point density and
    sequence length while a fused grid's stored camera evidence is clipped at ``logp_clip``, so it
    overrides almost every voxel unless ``temperature`` is large."""
    new_voxel_margin: float = field(default=4.0, metadata=within(0, 1000, unit="nats"))
    """A voxel inside the camera view that no camera mask labeled is created by the network only where it
    is sure of it: its mean log-probability (``voxel`` evidence: the mean over the voxel's points of
    ``max(log P_net, log prob_floor)``) for its class beats the runner-up class's by at least this many nats
    (at most ``−log prob_floor`` ≈ 6.9); its points stay unlabeled otherwise. Voxels outside every camera
    view are always created (the network is all there is). In view, no camera evidence weighs against the
    network in such a voxel, and where it is wrong it is mostly less sure: on the farm's tuning sequences
    101-103 most of the in-view points no camera mask labeled are ground under tree crowns (depth
    clustering takes them out of the crown's mask), which the network called ground, tree, fence or person.
    0 creates every such voxel (as before this field). Needs ``network_evidence: voxel``; acts after
    training (a changed value reuses the checkpoint). Chosen on those tuning sequences (one round,
    camera-view mIoU, mean of the three, for 0 / 2 / 3 / 4 / 5 / 6: 91.6 / 92.5 / 93.4 / 93.9 / 93.8 /
    93.8; voxel labels 92.3; all points 91.6 → 93.0; docs/METHOD.md C.3, C.5)."""
    test_time_views: int = field(default=1, metadata=within(1, 32))
    """Views of each scan whose predictions are averaged at inference (test-time augmentation): view j of n
    turns the scan by 2πj/n about z and mirrors y when j is odd
    (:func:`~leap_core.consistency.data.inference_view`), and a point's probabilities are the mean over
    the views. 1 predicts the scan as it is. Costs n forward passes per scan; inference only, so changing
    it reuses the trained weights."""
    epochs: int = field(default=1, metadata=within(1, 1000))
    """Passes over the training scans (the paper: one epoch)."""
    min_steps: int = field(default=500, metadata=within(0, 1_000_000))
    """Training takes at least this many steps, cycling over the scans again when ``epochs`` passes are
    fewer. The paper's one epoch covers thousands of SemanticKITTI scans; one pass over a 60-scan demo
    sequence is 60 steps, too few to train a network from scratch. 0 = exactly ``epochs`` passes."""
    lr: float = field(default=5e-3, metadata=within(0, 1, low_open=True))
    """Peak AdamW learning rate (linear warm-up over the first 5% of steps, cosine decay after)."""
    finetune_lr: float = field(default=5e-4, metadata=within(0, 1, low_open=True))
    """Peak learning rate instead of ``lr`` when a round starts from a source network (``leap run
    --3dcn-init CKPT``, :attr:`leap_core.runtime.Runtime.init_3dcn`) rather than from random weights: a
    tenth of ``lr``, so fine-tuning adapts what the source knows instead of overwriting it. On street tuning
    sequence 21 (camera view, the paper's protocol, voxel labels 71.4), a source trained on another
    sequence's ground truth gave 76.8 after 500 steps at ``lr`` and 86.6 after one epoch at 5e-4
    (docs/METHOD.md C.2, C.5). Unused without a source."""
    finetune_min_steps: int = field(default=0, metadata=within(0, 1_000_000))
    """``min_steps`` instead when a round starts from a source network: 0 trains exactly ``epochs``
    passes over the scans, the paper's one epoch of fine-tuning. Unused without a source."""
    weight_decay: float = field(default=1e-3, metadata=within(0, 1))
    """AdamW decoupled weight decay."""
    scans_per_step: int = field(default=1, metadata=within(1, 64))
    """Scans in one optimisation step (each scan is its own point cloud; gradients are averaged)."""
    points_per_scan: int = field(default=16384, metadata=within(0, 10_000_000))
    """Points drawn at random from a scan for a training step (all its selected labels compete for them:
    selected points are drawn first); ``0`` uses every point. Bounds CPU time per step."""
    labeled_share: float = field(default=0.5, metadata=within(0, 1))
    """Share of a scan's ``points_per_scan`` draw reserved for points with a selected label (drawn first, at
    random); the rest is drawn uniformly from the other points as context. 0 draws uniformly from all
    points, which leaves only ~``share`` × labeled fraction of each step with a loss."""
    augment: bool = True
    """Random rotation about z, random flip of y and small scaling during training."""
    label_smoothing: float = field(default=0.0, metadata=within(0, 1, high_open=True))
    """Cross-entropy label smoothing."""
    class_balance: bool = True
    """Weight the cross-entropy by an inverse power of the class frequency of the selected labels
    (``class_balance_power``), so rare classes that survive the per-class selection also keep a voice in
    the loss."""
    class_balance_power: float = field(default=0.5, metadata=within(0, 1))
    """The power p of the class weights ``w_c ∝ n_c^(-p)`` (mean 1 over the classes present): 0.5 weighs
    a class 100× rarer 10× more, 0.25 about 3×, 0 not at all (as ``class_balance: false``)."""
    seed: int = field(default=0, metadata=within(0, SEED_MAX))
    """Seed of weight init, point sampling and augmentation: same seed + same data = same checkpoint on
    CPU."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Torch device; ``auto`` takes CUDA when available."""
    precision: Literal["auto", "float32", "bfloat16"] = "auto"
    """Arithmetic of the network's forward and backward passes. ``bfloat16`` is mixed precision (torch
    autocast): matrix products and convolutions in bfloat16, while weights, optimiser state, normalisations,
    the spatial mixing's cell means and the loss stay float32. ``auto`` takes it where the hardware does
    bfloat16 natively (a CUDA GPU that supports it; a CPU with AVX512-BF16 or AMX, where a training step
    of the default network is about 1.35× faster than in float32, ``benchmarks/bench_3dcn.py``) and
    ``float32`` elsewhere, where bfloat16 would be emulated and slower. Same seed, data and resolved
    precision on the same machine give the same checkpoint; the two precisions give networks that differ
    like two seeds (docs/METHOD.md C.2). Like ``device``, it does not enter the checkpoint's fingerprint:
    changing it reuses trained weights."""
    num_threads: int = field(default=0, metadata=within(0, 1024))
    """``torch.set_num_threads`` during training/inference on CPU; ``0`` leaves torch's setting alone."""
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    """Backbone sizes (CPU-friendly defaults; see :meth:`paper_scale`)."""

    def __post_init__(self) -> None:
        check_bounds(self)
        checks: tuple[tuple[str, bool, str], ...] = (
            ("selection_scope", self.selection_scope in ("scan", "sequence"), "must be 'scan' or 'sequence'"),
            ("network_evidence", self.network_evidence in ("voxel", "point"), "must be 'voxel' or 'point'"),
            (
                "new_voxel_margin",
                self.new_voxel_margin == 0 or self.network_evidence == "voxel",
                "must be 0 with network_evidence 'point' (it applies to voxel evidence only)",
            ),
            ("device", self.device in ("auto", "cpu", "cuda"), "must be 'auto', 'cpu' or 'cuda'"),
            (
                "precision",
                self.precision in ("auto", "float32", "bfloat16"),
                "must be 'auto', 'float32' or 'bfloat16'",
            ),
        )
        for name, ok, rule in checks:
            if not ok:
                raise ConfigError(f"{rule}, got {getattr(self, name)!r}", field=(name,))

    @property
    def network_weight(self) -> float:
        """Weight ``1 / temperature`` of the network's log-probabilities in the Bayesian update."""
        return 1.0 / self.temperature

    @classmethod
    def paper_scale(cls, **overrides: Any) -> ConsistencyConfig:
        """The paper's WaffleIron sizes, for a GPU.

        256 channels, 48 layers, 0.4 m 2D grid cells on the three planes, 16 kNN neighbours, XYZ input only,
        every point of every scan in training, exactly one epoch, stochastic depth 0.2, AdamW at 1e-3,
        temperature 1. ``overrides`` replace any top-level
        field (e.g. ``temperature=1.0``).
        """
        base = cls(
            enabled=True,
            lr=1e-3,
            weight_decay=3e-3,
            points_per_scan=0,
            min_steps=0,
            temperature=1.0,
            device="auto",
            backbone=BackboneConfig(
                channels=256,
                layers=48,
                grid_cells=(0.4, 0.4, 0.4),
                knn=16,
                embed_channels=64,
                mlp_ratio=2,
                kernel_size=3,
                drop_path=0.2,
                layer_scale=1e-4,
                use_intensity=False,
            ),
        )
        return replace(base, **overrides)


__all__ = ["BackboneConfig", "ConsistencyConfig"]
