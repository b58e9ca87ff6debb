"""Self-training of the 3D Consistency Network, its checkpoint, and inference (docs/METHOD.md stage C.2-3).

Training sees each scan in its own LiDAR frame (XYZ; remission only if the backbone config asks for it).
Only the selected reliable points carry a loss; the other points of the scan still feed the spatial mixing
as context. One epoch by default, seeded, AdamW with a linear warm-up and cosine decay.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch.nn import functional as F_

from leap_core.consistency.backbone import CloudTensors, PointSegmenter
from leap_core.consistency.config import BackboneConfig, ConsistencyConfig
from leap_core.consistency.data import (
    PreparedCloud,
    TensorCloud,
    augment_points,
    collate,
    inference_view,
    prepare_input,
)
from leap_core.errors import ModelLoadError
from leap_core.heap import release_free_memory, reusing_heap
from leap_core.io_utils import atomic_write, file_digest
from leap_core.prefetch import prefetched
from leap_core.progress import ProgressFn, report
from leap_core.types import UNLABELED

CHECKPOINT_FORMAT = "leap-3dcn"
CHECKPOINT_VERSION = 1
RELEASE_EVERY = 8
"""Training steps between two hand-backs of freed heap pages (:func:`~leap_core.heap.release_free_memory`):
each costs about 30 ms and makes the next step fault its pages in again."""
_IGNORE = -100
"""``ignore_index`` of the cross-entropy (torch's default) for points without a selected label."""

ScanLoader = Callable[[int], tuple[npt.NDArray[np.float32], npt.NDArray[np.integer]]]
"""``load(i) -> (points (N, 4) float32, target (N,) int class or UNLABELED)`` for scan i."""


@dataclass
class TrainStats:
    """What one training run did."""

    steps: int = 0
    """Optimisation steps taken (steps whose scans had no selected point are skipped)."""
    losses: list[float] = field(default_factory=list)
    """Cross-entropy of every step, in order."""
    points_seen: int = 0
    """Points fed through the network (context + labeled) over all steps."""
    labeled_seen: int = 0
    """Points that carried a loss over all steps."""
    seconds: float = 0.0
    """Wall time of the training loop."""


def resolve_device(cfg: ConsistencyConfig) -> torch.device:
    """``cfg.device``, with ``auto`` → CUDA when available, else CPU."""
    if cfg.device == "cuda" or (cfg.device == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise ModelLoadError("consistency.device is 'cuda' but torch sees no CUDA device")
        return torch.device("cuda")
    return torch.device("cpu")


def native_bfloat16(device: torch.device) -> bool:
    """Whether ``device`` computes in bfloat16 natively: a CUDA GPU that supports it, or a CPU with
    AVX512-BF16 or AMX instructions (elsewhere torch emulates it, slower than float32)."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    cpu = torch.cpu
    # Private probes, the only ones torch has; a torch without them counts as "no".
    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(bool(getattr(cpu, name, lambda: False)()) for name in probes)


def resolve_precision(cfg: ConsistencyConfig, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of the network's passes for ``cfg.precision`` on ``device``: ``torch.bfloat16``,
    or None for plain float32 (``auto``: bfloat16 where :func:`native_bfloat16`)."""
    if cfg.precision == "bfloat16" or (cfg.precision == "auto" and native_bfloat16(device)):
        return torch.bfloat16
    return None


def autocast(device: torch.device, dtype: torch.dtype | None) -> contextlib.AbstractContextManager[None]:
    """Mixed precision in ``dtype`` for the block on ``device``'s type; nothing when ``dtype`` is None."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device_type=device.type, dtype=dtype)


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Set ``torch.set_num_threads(n)`` for the block (``n = 0``: leave it alone)."""
    if n <= 0:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def class_counts(targets: npt.ArrayLike, num_classes: int) -> npt.NDArray[np.int64]:
    """(C,) ``counts[c] = #{i : targets[i] = c}``; ``UNLABELED`` (−1) targets are not counted."""
    t = np.asarray(targets).reshape(-1)
    t = t[t != UNLABELED].astype(np.int64)
    return np.bincount(t, minlength=num_classes).astype(np.int64)


def class_weights(counts: npt.ArrayLike, enabled: bool = True, power: float = 0.5) -> torch.Tensor:
    """Cross-entropy class weights ``w_c ∝ n_c^(-power)`` (``power`` 0.5: ``1 / sqrt(n_c)``), normalised to
    mean 1 over present classes.

    Absent classes (``n_c = 0``) get weight 1 (they never occur as targets). ``enabled=False`` gives all 1.
    Example: counts [100, 1, 0], power 0.5 → raw [0.1, 1] → [2/11, 20/11, 1].
    """
    n = np.asarray(counts, dtype=np.float64)
    w = np.ones_like(n)
    present = n > 0
    if enabled and present.any():
        # The default keeps the former expression bit for bit (1/sqrt and pow(-0.5) can differ in the last
        # bit), so a 3D-CN retrained after this setting appeared gives the same weights and labels.
        w[present] = 1.0 / np.sqrt(n[present]) if power == 0.5 else n[present] ** -power
        w[present] /= w[present].mean()
    return torch.as_tensor(w, dtype=torch.float32)


def lr_factor(step: int, total: int) -> float:
    """Learning-rate multiplier: linear warm-up over the first 5% of steps (≥ 1), then cosine to 0.

    ``f(s) = (s + 1) / W`` for ``s < W``, else ``½ (1 + cos(π (s - W) / max(1, total - W)))``.
    """
    warm = max(1, round(0.05 * total))
    if step < warm:
        return (step + 1) / warm
    return 0.5 * (1.0 + math.cos(math.pi * (step - warm) / max(1, total - warm)))


def num_train_steps(num_scans: int, cfg: ConsistencyConfig, finetune: bool = False) -> int:
    """Optimisation steps of :func:`train_model`: ``max(epochs · ceil(S / scans_per_step), m)`` with
    ``m = min_steps``, or ``finetune_min_steps`` when the network starts from a source (0 without scans)."""
    if num_scans <= 0:
        return 0
    floor = cfg.finetune_min_steps if finetune else cfg.min_steps
    return max(cfg.epochs * math.ceil(num_scans / cfg.scans_per_step), floor)


def draw_points(
    target: npt.NDArray[np.integer], budget: int, labeled_share: float, rng: np.random.Generator
) -> npt.NDArray[np.int64]:
    """Sorted indices of the points of one scan fed to a training step.

    ``min(#labeled, round(labeled_share · budget))`` points are drawn from those with a target, the rest of
    the ``budget`` from the other points; all points when ``budget`` is 0 or at least the scan size.

    Args:
        target: (N,) class per point, ``UNLABELED`` where there is no training label.
        budget: points to draw.
        labeled_share: share of the budget reserved for labeled points.
        rng: random source.
    """
    n = target.shape[0]
    if budget <= 0 or n <= budget:
        return np.arange(n, dtype=np.int64)
    labeled = np.flatnonzero(target != UNLABELED)
    n_lab = min(len(labeled), round(labeled_share * budget))
    picked = rng.choice(labeled, n_lab, replace=False) if n_lab else np.zeros(0, np.int64)
    rest = np.ones(n, dtype=bool)
    rest[picked] = False
    others = rng.choice(np.flatnonzero(rest), budget - n_lab, replace=False)
    return np.sort(np.concatenate([picked, others])).astype(np.int64)


def _seed_all(seed: int) -> np.random.Generator:
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


def train_model(
    load_scan: ScanLoader,
    scan_indices: Sequence[int],
    num_classes: int,
    cfg: ConsistencyConfig,
    progress: ProgressFn | None = None,
    class_counts: npt.ArrayLike | None = None,
    *,
    init: PointSegmenter | None = None,
) -> tuple[PointSegmenter, TrainStats]:
    """Train a :class:`PointSegmenter` on the selected labels of the given scans: a fresh one, or a copy
    of ``init`` fine-tuned (``finetune_lr``, ``finetune_min_steps`` instead of ``lr``, ``min_steps``).

    Per pass the scans are visited in a seeded random order, ``cfg.scans_per_step`` per step, for
    :func:`num_train_steps` steps (``epochs`` passes, more if ``min_steps`` asks for it). From every
    scan ``cfg.points_per_scan`` points are drawn uniformly (all when 0 or fewer are available); the loss is
    the (class-weighted) cross-entropy over the drawn points that carry a target, the rest are context.

    Args:
        load_scan: returns ``(points (N, 4), target (N,))`` of scan i; target ``UNLABELED`` = no loss.
        scan_indices: scans to train on.
        num_classes: C.
        cfg: training parameters (``epochs``, ``lr``, ``seed``, backbone sizes, ...).
        progress: ``progress(step, total_steps)`` after every step.
        class_counts: (C,) selected-label count per class, for the class weights and to mark the classes
            without any label (``model.trained_classes``); None = unweighted, every class kept.
        init: a source network (:func:`load_source`) whose weights the network starts from; it is not
            modified. None = random weights (seeded).

    Returns:
        The trained model (in eval mode, on CPU) and its :class:`TrainStats`.
    """
    device = resolve_device(cfg)
    indices = list(scan_indices)
    per_epoch = math.ceil(len(indices) / cfg.scans_per_step) if indices else 0
    total = num_train_steps(len(indices), cfg, finetune=init is not None)
    stats = TrainStats()
    t0 = time.perf_counter()
    with torch.random.fork_rng(devices=[]), torch_threads(cfg.num_threads):
        rng = _seed_all(cfg.seed)
        # Built (and its random init drawn) either way, so sampling and augmentation draw the same numbers
        # whether or not a source replaces the weights.
        model = PointSegmenter(cfg.backbone, num_classes)
        if init is not None:
            model.load_state_dict(init.state_dict())
        model = model.to(device)
        weights = None
        if class_counts is not None:
            weights = class_weights(class_counts, cfg.class_balance, cfg.class_balance_power).to(device)
            model.trained_classes.copy_(torch.as_tensor(np.asarray(class_counts) > 0))
        lr = cfg.lr if init is None else cfg.finetune_lr
        opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, total))
        model.train()
        # The kd-tree queries leave one thread to the training step they overlap with.
        workers = max(1, torch.get_num_threads() - 1)
        # The next step's scans are read, sampled and prepared (kd-tree, features, grid cells) on a
        # background thread while this step trains; the sampling draws in the same order either way.
        # On a GPU the features and grid cells are computed there, so the thread's share stays small.
        prep_device = device if device.type == "cuda" else None
        batches = _step_batches(load_scan, indices, per_epoch, total, cfg, rng, workers, prep_device)
        amp = resolve_precision(cfg, device)
        with reusing_heap():
            for step, batch in enumerate(prefetched(batches), start=1):
                if batch is not None:
                    _train_step(model, opt, batch, weights, cfg, device, amp, stats)
                del batch
                # The steps' batches, activations and gradients are freed by now; hand their pages back
                # so they do not add up step after step (leap_core.heap).
                if step % RELEASE_EVERY == 0 or step == total:
                    release_free_memory()
                sched.step()
                report(progress, step, total)
    model.eval()
    stats.seconds = time.perf_counter() - t0
    return model.cpu(), stats


TrainingBatch = tuple[CloudTensors, torch.Tensor]
"""One step's collated clouds and its (N,) int64 loss targets (``_IGNORE`` where a point has no label)."""


def _train_step(  # noqa: PLR0917  one step's model, optimiser, batch and its settings
    model: PointSegmenter,
    opt: torch.optim.Optimizer,
    batch_data: TrainingBatch,
    weights: torch.Tensor | None,
    cfg: ConsistencyConfig,
    device: torch.device,
    amp: torch.dtype | None,
    stats: TrainStats,
) -> None:
    """One optimisation step on one batch (:func:`_training_batch`), counted in ``stats``, with the
    network's passes in ``amp`` mixed precision (None: float32). Its own function so that the step's
    tensors are gone when it returns."""
    clouds, targets = batch_data
    batch = clouds.to(device)
    tgt = targets.to(device)
    with autocast(device, amp):
        logits = model(batch)
    loss = F_.cross_entropy(
        logits.float(), tgt, weight=weights, ignore_index=_IGNORE, label_smoothing=cfg.label_smoothing
    )
    opt.zero_grad(set_to_none=True)
    torch.autograd.backward(loss)  # loss.backward(), which torch leaves unannotated
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    stats.steps += 1
    stats.losses.append(float(loss.detach()))
    stats.points_seen += batch.num_points
    stats.labeled_seen += int((tgt != _IGNORE).sum())


def _step_batches(  # noqa: PLR0917  the loop's scans, its lengths and the sampling's settings
    load_scan: ScanLoader,
    indices: Sequence[int],
    per_epoch: int,
    total: int,
    cfg: ConsistencyConfig,
    rng: np.random.Generator,
    workers: int,
    prep_device: torch.device | None,
) -> Iterator[TrainingBatch | None]:
    """The ``total`` steps' batches in order: per pass over the scans a seeded permutation of
    ``indices``, ``cfg.scans_per_step`` scans per step, ``per_epoch`` steps per pass; None for a step
    none of whose scans has a drawn labeled point (the step is skipped, the schedule still advances)."""
    step = 0
    while step < total:
        order = rng.permutation(len(indices))
        for s in range(min(per_epoch, total - step)):
            batch_ids = [indices[j] for j in order[s * cfg.scans_per_step : (s + 1) * cfg.scans_per_step]]
            yield _training_batch(load_scan, batch_ids, cfg, rng, workers, prep_device)
            step += 1


def _training_batch(
    load_scan: ScanLoader,
    batch_ids: Sequence[int],
    cfg: ConsistencyConfig,
    rng: np.random.Generator,
    workers: int,
    prep_device: torch.device | None = None,
) -> TrainingBatch | None:
    """The collated clouds of one step and their loss targets (``_IGNORE`` where a drawn point has no
    selected label); a scan none of whose drawn points carries a label is left out, and a step without
    any such scan is None. Prepared by :func:`~leap_core.consistency.data.prepare_input` on
    ``prep_device`` (None: the CPU), its kd-tree queried on ``workers`` threads."""
    clouds: list[PreparedCloud | TensorCloud] = []
    targets = []
    for i in batch_ids:
        points, target = load_scan(i)
        target = np.asarray(target)
        if target.shape != (points.shape[0],):
            raise ValueError(f"scan {i}: target {target.shape} does not match points {points.shape}")
        subset = draw_points(target, cfg.points_per_scan, cfg.labeled_share, rng)
        pts = augment_points(points, rng) if cfg.augment else points
        t = target[subset].astype(np.int64)
        if not (t != UNLABELED).any():
            continue
        clouds.append(prepare_input(pts, cfg.backbone, subset, prep_device, workers))
        targets.append(np.where(t == UNLABELED, _IGNORE, t))
    if not clouds:
        return None
    return collate(clouds), torch.from_numpy(np.concatenate(targets))


def prepare_views(
    points: npt.NDArray[np.float32], cfg: BackboneConfig, views: int, device: torch.device, workers: int = 1
) -> list[PreparedCloud | TensorCloud]:
    """The network inputs of ``views`` test-time views of one scan
    (:func:`~leap_core.consistency.data.inference_view`; ``views = 1``: the scan as it is), prepared on
    ``device`` when it is a GPU, else on the CPU (:func:`~leap_core.consistency.data.prepare_input`)."""
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    on = device if device.type == "cuda" else None
    return [
        prepare_input(points if views == 1 else inference_view(points, j, views), cfg, None, on, workers)
        for j in range(views)
    ]


@torch.inference_mode()
def predict_prepared(
    model: PointSegmenter,
    clouds: Sequence[PreparedCloud | TensorCloud],
    device: torch.device,
    precision: torch.dtype | None = None,
) -> npt.NDArray[np.float32]:
    """:func:`predict_log_probs` on views :func:`prepare_views` prepared: ``log((1/V) · Σ_j P_j)`` over the
    V clouds, as a log-sum-exp; ``-inf`` for classes without training labels."""
    was_training = model.training
    model.eval()
    try:
        acc: torch.Tensor | None = None
        for cloud in clouds:
            batch = collate([cloud]).to(device)
            with autocast(device, precision):
                logits = model(batch)
            logits = logits.float().masked_fill(~model.trained_classes, -math.inf)
            logp = F_.log_softmax(logits, dim=1)
            acc = logp if acc is None else torch.logaddexp(acc, logp)
        if acc is None:
            raise ValueError("no view to predict")
        if len(clouds) > 1:
            acc -= math.log(len(clouds))
        return acc.cpu().numpy()
    finally:
        model.train(was_training)


def predict_log_probs(
    model: PointSegmenter,
    points: npt.NDArray[np.float32],
    device: torch.device | str = "cpu",
    workers: int = 1,
    views: int = 1,
    precision: torch.dtype | None = None,
) -> npt.NDArray[np.float32]:
    """Per-point class log-probabilities of every point of one scan, averaged over ``views`` views of it.

    With ``P_j = softmax(model(inference_view(scan, j, views)))``: ``log((1/views) · Σ_j P_j)``, computed
    as a log-sum-exp; ``views = 1`` is ``log_softmax(model(scan))`` itself.

    Args:
        model: a trained segmenter (moved to ``device`` by the caller).
        points: (N, 4) float32 scan in its LiDAR frame.
        device: where the forward pass runs (on a GPU the input is prepared there too).
        workers: kd-tree query threads.
        views: test-time views (:func:`~leap_core.consistency.data.inference_view`), ≥ 1.
        precision: the autocast dtype of the forward pass (:func:`resolve_precision`); None = float32.

    Returns:
        (N, C) float32 log-probabilities (rows log-sum-exp to 0); ``-inf`` for classes the model had no
        training label of (``model.trained_classes``).
    """
    dev = torch.device(device)
    return predict_prepared(model, prepare_views(points, model.cfg, views, dev, workers), dev, precision)


# ----------------------------------------------------------------------------------------- checkpoint
def config_to_dict(cfg: ConsistencyConfig) -> dict[str, Any]:
    """Plain-data form of a config (tuples become lists), for checkpoints and fingerprints."""
    d = asdict(cfg)
    d["backbone"]["grid_cells"] = list(d["backbone"]["grid_cells"])
    return d


def config_from_dict(d: dict[str, Any]) -> ConsistencyConfig:
    """Inverse of :func:`config_to_dict`; raises ``TypeError``/``KeyError`` on unknown or missing fields."""
    d = dict(d)
    bb = dict(d.pop("backbone"))
    bb["grid_cells"] = tuple(float(c) for c in bb["grid_cells"])
    return ConsistencyConfig(**d, backbone=BackboneConfig(**bb))


@dataclass
class Checkpoint:
    """A loaded 3D-CN checkpoint."""

    model: PointSegmenter
    """The network, in eval mode, on the device it was loaded to."""
    config: ConsistencyConfig
    """The config it was trained with."""
    num_classes: int
    """C."""
    meta: dict[str, Any]
    """Free-form extras saved with it (fingerprint, training statistics, ...)."""


def save_checkpoint(
    path: str | Path,
    model: PointSegmenter,
    cfg: ConsistencyConfig,
    meta: dict[str, Any] | None = None,
) -> None:
    """Write config + state_dict + ``meta`` with ``torch.save``, atomically."""
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": config_to_dict(cfg),
        "num_classes": int(model.num_classes),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "meta": dict(meta or {}),
    }
    with atomic_write(path, "wb") as fh:
        torch.save(payload, fh)


def load_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only``: no code is unpickled).

    Raises:
        ModelLoadError: naming the file, when it is missing, unreadable, of another format or does not
            match the network its config describes.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelLoadError(f"{path}: 3D-CN checkpoint not found (run the 3D-CN stage to train one)")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for corrupt files
        raise ModelLoadError(f"{path}: unreadable 3D-CN checkpoint ({type(exc).__name__}: {exc})") from exc
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ModelLoadError(f"{path}: not a LeAP 3D-CN checkpoint (missing format '{CHECKPOINT_FORMAT}')")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise ModelLoadError(
            f"{path}: 3D-CN checkpoint version {payload.get('version')} != supported {CHECKPOINT_VERSION}"
        )
    try:
        cfg = config_from_dict(payload["config"])
        num_classes = int(payload["num_classes"])
        model = PointSegmenter(cfg.backbone, num_classes)
        model.load_state_dict(payload["state_dict"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise ModelLoadError(f"{path}: 3D-CN checkpoint does not match its config ({exc})") from exc
    model.eval()
    return Checkpoint(model=model.to(device), config=cfg, num_classes=num_classes, meta=dict(payload["meta"]))


@dataclass(frozen=True)
class SourceNetwork:
    """A network that 3D-CN rounds start from instead of random weights (:func:`load_source`)."""

    model: PointSegmenter
    """Its weights, on the CPU (never trained further itself: :func:`train_model` copies them)."""
    digest: str
    """SHA-256 of its checkpoint file: part of the training fingerprint of each network fine-tuned from it."""


def load_source(path: str | Path, backbone: BackboneConfig, num_classes: int) -> SourceNetwork:
    """The network of a checkpoint that a round is to start from (fine-tuning), with its file's digest.

    Raises:
        ModelLoadError: naming the file, when :func:`load_checkpoint` refuses it, or when its backbone or
            class count differs from the run's (the weights would not fit; the message names the fields).
    """
    ck = load_checkpoint(path)
    if ck.num_classes != num_classes:
        raise ModelLoadError(
            f"{path}: the 3D-CN source network has {ck.num_classes} classes, this run's "
            f"schema {num_classes}; start from a network trained with the same classes"
        )
    if ck.config.backbone != backbone:
        mine, theirs = asdict(backbone), asdict(ck.config.backbone)
        diff = ", ".join(f"{k} {theirs[k]!r} (run: {mine[k]!r})" for k in mine if mine[k] != theirs[k])
        raise ModelLoadError(
            f"{path}: the 3D-CN source network's backbone differs from consistency.backbone: {diff}"
        )
    return SourceNetwork(ck.model, file_digest(path))


__all__ = [
    "Checkpoint",
    "ScanLoader",
    "SourceNetwork",
    "TrainStats",
    "class_counts",
    "class_weights",
    "config_from_dict",
    "config_to_dict",
    "draw_points",
    "load_checkpoint",
    "load_source",
    "lr_factor",
    "native_bfloat16",
    "num_train_steps",
    "predict_log_probs",
    "predict_prepared",
    "prepare_views",
    "resolve_device",
    "resolve_precision",
    "save_checkpoint",
    "torch_threads",
    "train_model",
]
