"""The 3D-CN's bounded memory: no autograd graph outlives a training step or exists at inference,
inference and fusion back hold one scan at a time, the streamed voxel means are the same bytes as summing
each chunk's scans concatenated, and freed heap memory goes back to the system (leap_core.heap)."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import weakref
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from leap_core.consistency.backbone import PointSegmenter
from leap_core.consistency.config import BackboneConfig, ConsistencyConfig
from leap_core.consistency.stage import predict_frames, voxel_mean_log_probs
from leap_core.consistency.train import predict_log_probs, train_model
from leap_core.datasets.kitti import KittiSequence
from leap_core.heap import _glibc
from leap_core.types import UNLABELED

TINY = ConsistencyConfig(
    enabled=True,
    backbone=BackboneConfig(channels=8, layers=2, grid_cells=(1.0, 1.0, 1.0), knn=4),
    points_per_scan=0,
    min_steps=0,
    lr=1e-2,
    augment=False,
    device="cpu",
    num_threads=1,
)


def _scan(seed: int, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-5, 5, (n, 3)), rng.uniform(0, 1, n)]).astype(np.float32)
    lab = (pts[:, 2] > 0).astype(np.int16)
    lab[rng.random(n) < 0.5] = UNLABELED
    return pts, lab


def _graph_tensors() -> list[torch.Tensor]:
    """Live tensors that belong to an autograd graph (they keep its saved activations alive)."""
    return [o for o in gc.get_objects() if issubclass(type(o), torch.Tensor) and o.grad_fn is not None]


def test_no_autograd_graph_outlives_a_training_step() -> None:
    """When the next step's scans are loaded, the last step's logits and loss (and through them its graph)
    are gone."""
    scans = {i: _scan(i) for i in range(3)}
    alive_at_load: list[int] = []

    def load(i: int) -> tuple[np.ndarray, np.ndarray]:
        alive_at_load.append(len(_graph_tensors()))
        return scans[i]

    _, stats = train_model(load, [0, 1, 2], 2, TINY)
    assert stats.steps == 3 and len(alive_at_load) == 3
    assert alive_at_load == [0, 0, 0]


def test_inference_runs_under_inference_mode_without_a_graph() -> None:
    torch.manual_seed(0)
    model = PointSegmenter(TINY.backbone, 3)
    seen: list[tuple[bool, bool, bool]] = []

    def hook(_mod: torch.nn.Module, _inp: object, out: torch.Tensor) -> None:
        seen.append((torch.is_inference_mode_enabled(), out.requires_grad, out.grad_fn is not None))

    handle = model.register_forward_hook(hook)
    try:
        logp = predict_log_probs(model, _scan(0)[0])
    finally:
        handle.remove()
    assert logp.shape == (300, 3)
    assert seen == [(True, False, False)]


def test_predict_frames_infers_one_scan_at_a_time(tmp_path: Path, make_tiny_sequence) -> None:
    """A scan is predicted only when asked for, in the configured precision, and the fusion back drops
    each scan's predictions before it asks for the next one."""
    seq = KittiSequence(make_tiny_sequence(tmp_path, n_frames=4, n_points=200).root)
    torch.manual_seed(0)
    model = PointSegmenter(TINY.backbone, 3).eval()
    ticks: list[int] = []
    cfg = replace(TINY, precision="bfloat16")
    scans = predict_frames(model, seq, range(4), cfg, 0.2, lambda: ticks.append(1))
    keys, logp = next(scans)
    assert len(ticks) == 1 and logp.shape == (len(keys), 3)
    pts = seq.frame(0).points
    assert np.array_equal(logp, predict_log_probs(model, pts, precision=torch.bfloat16))
    assert not np.array_equal(logp, predict_log_probs(model, pts))
    del keys, logp

    refs: list[weakref.ref[np.ndarray]] = []
    held_when_asked: list[int] = []

    def watched() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for k, lp in scans:
            held_when_asked.append(sum(r() is not None for r in refs))
            refs.append(weakref.ref(lp))
            yield k, lp
            del k, lp

    voxel_mean_log_probs(watched(), 3, 1e-4)
    assert len(ticks) == 4
    # Scans 1-3 went through the means; when each was asked for, no earlier scan's predictions were held.
    assert held_when_asked == [0, 0, 0]


def _chunk_means_reference(
    predictions: list[tuple[np.ndarray, np.ndarray]], c: int, prob_floor: float, chunk_points: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The means as the code before the streaming computed them: each chunk's scans concatenated, summed
    with one index_add_, chunks merged in order."""
    floor = float(np.log(prob_floor))
    keys_acc = np.zeros(0, np.int64)
    sum_acc = np.zeros((0, c), np.float32)
    cnt_acc = np.zeros(0, np.int64)

    def reduce(ks: list[np.ndarray], lps: list[np.ndarray]) -> None:
        nonlocal keys_acc, sum_acc, cnt_acc
        uk, inv = np.unique(np.concatenate(ks), return_inverse=True)
        lp = torch.from_numpy(np.concatenate(lps).astype(np.float32)).clamp_min_(floor)
        sums = torch.zeros((len(uk), c), dtype=torch.float32)
        sums.index_add_(0, torch.from_numpy(inv.reshape(-1)), lp)
        cnt = np.bincount(inv.reshape(-1), minlength=len(uk))
        merged = np.union1d(keys_acc, uk)
        new_sum = np.zeros((len(merged), c), np.float32)
        new_cnt = np.zeros(len(merged), np.int64)
        rows_a, rows_b = np.searchsorted(merged, keys_acc), np.searchsorted(merged, uk)
        new_sum[rows_a] = sum_acc
        new_cnt[rows_a] = cnt_acc
        new_sum[rows_b] += sums.numpy()
        new_cnt[rows_b] += cnt
        keys_acc, sum_acc, cnt_acc = merged, new_sum, new_cnt

    pk: list[np.ndarray] = []
    pl: list[np.ndarray] = []
    pending = 0
    for k, lp in predictions:
        pk.append(k)
        pl.append(lp)
        pending += len(k)
        if pending >= chunk_points:
            reduce(pk, pl)
            pk, pl, pending = [], [], 0
    if pending:
        reduce(pk, pl)
    return keys_acc, sum_acc / np.maximum(cnt_acc, 1)[:, None].astype(np.float32), cnt_acc


@pytest.mark.parametrize("chunk_points", [1, 700, 2500, 10**9])
def test_streamed_voxel_means_are_the_chunk_sums_bit_for_bit(chunk_points: int) -> None:
    """Scans added one by one give the very float32 sums of each chunk's scans concatenated: many points
    per voxel (so rounding depends on the order of the additions), scans of other sizes, an empty one,
    probabilities below the floor."""
    rng = np.random.default_rng(3)
    c = 6
    preds = []
    for n in (400, 0, 900, 1300, 50, 700):
        keys = rng.integers(0, 60, n).astype(np.int64) * 7 - 100
        logp = np.log(rng.dirichlet(np.full(c, 0.3), n) + 1e-12).astype(np.float32)
        preds.append((keys, logp))
    want = _chunk_means_reference(preds, c, 1e-4, chunk_points)
    got = voxel_mean_log_probs(iter(preds), c, 1e-4, chunk_points)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert g.tobytes() == w.tobytes()


_HEAP_CHILD = """
import json, sys
import numpy as np, psutil
from leap_core import heap
proc = psutil.Process()
cap = sys.argv[1] == "cap"
# Raise glibc's rising mmap threshold first, as a run's earlier stages do: a 24 MiB block mapped and freed.
big = np.ones(3 << 20)
del big
if cap:
    heap.cap_heap_growth()
rss0 = proc.memory_info().rss
blocks, pins = [], []
for _ in range(40):
    blocks.append(np.ones(1 << 18))  # 2 MiB each, 80 MiB in all
    pins.append(np.ones(1024))       # a small block after each, so the freed ones are holes, not the top
del blocks
freed = proc.memory_info().rss
released = heap.release_free_memory()
after = proc.memory_info().rss
mib = 2**20
print(json.dumps({"held": (freed - rss0) / mib, "after_trim": (after - rss0) / mib, "released": released}))
"""


_REUSE_CHILD = """
import json
import numpy as np, psutil
from leap_core import heap
proc = psutil.Process()
mib = 2**20
heap.cap_heap_growth()  # as the 3D-CN stage does before training


def churn():
    # 80 MiB of 2 MiB blocks, freed with a small block pinned after each (holes, not the heap's top).
    blocks, pins = [], []
    for _ in range(40):
        blocks.append(np.ones(1 << 18))
        pins.append(np.ones(1024))
    del blocks
    return pins


rss0 = proc.memory_info().rss
with heap.reusing_heap():
    pins = churn()
    inside = proc.memory_info().rss
after = proc.memory_info().rss
pins += churn()
heap.release_free_memory()  # what inference does after each scan
trimmed = proc.memory_info().rss
held = {"inside": inside, "after": after, "trimmed": trimmed}
print(json.dumps({k: (v - rss0) / mib for k, v in held.items()}))
"""


@pytest.mark.skipif(_glibc() is None, reason="mallopt / malloc_trim are glibc's")
def test_training_reuses_its_freed_blocks_and_gives_them_back_at_the_end() -> None:
    """Inside ``reusing_heap`` freed 2 MiB blocks stay on the heap for the next step; at its end they go
    back to the system. Blocks served later from the heap's free room go back at the next hand-back."""
    out = subprocess.run(
        [sys.executable, "-c", _REUSE_CHILD],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parent.parent,
    )
    held = json.loads(out.stdout)
    assert held["inside"] > 60, held
    assert held["after"] < 20 and held["trimmed"] < 20, held


def _heap_child(mode: str) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", _HEAP_CHILD, mode],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parent.parent,
    )
    result: dict[str, float] = json.loads(out.stdout)
    return result


@pytest.mark.skipif(_glibc() is None, reason="mallopt / malloc_trim are glibc's")
def test_freed_blocks_go_back_to_the_system() -> None:
    """In a fresh process (the settings are process-wide): without the cap, 80 MiB of freed 2 MiB blocks
    stay resident once the threshold has risen, and malloc_trim gives them back; with the cap they are
    unmapped as they are freed."""
    plain = _heap_child("plain")
    assert plain["held"] > 60, plain
    assert plain["after_trim"] < 20 and plain["released"], plain
    capped = _heap_child("cap")
    assert capped["held"] < 20, capped
