"""3D Consistency Network: selection, backbone, training, checkpoint, fusion back, and the whole stage."""

from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from leap_core.consistency.backbone import CloudTensors, KnnEmbedding, PlaneIndex, PointSegmenter
from leap_core.consistency.config import BackboneConfig, ConsistencyConfig, fingerprint_form
from leap_core.consistency.data import (
    LOCAL_SCALE,
    collate,
    inference_view,
    neighbours,
    prepare_cloud,
    prepare_cloud_tensors,
)
from leap_core.consistency.selection import (
    lookup_counts,
    per_class_quota,
    select_reliable,
    select_reliable_scans,
    view_counts,
)
from leap_core.consistency.stage import (
    RoundPart,
    TargetFile,
    checkpoint_path,
    fuse_back,
    iter_3dcn_round,
    iter_reliable_targets,
    iteration_config,
    keep_known_or_sure,
    reliable_targets,
    run_3dcn_iteration,
    targets_path,
    training_fingerprint,
    voxel_mean_log_probs,
    without_rows,
)
from leap_core.consistency.train import (
    _training_batch,
    class_weights,
    config_from_dict,
    config_to_dict,
    draw_points,
    load_checkpoint,
    load_source,
    lr_factor,
    native_bfloat16,
    num_train_steps,
    predict_log_probs,
    resolve_precision,
    save_checkpoint,
    train_model,
)
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import ConfigError, LeapError, ModelLoadError
from leap_core.fusion import FusionConfig, VoxelGrid, voxel_keys, world_points
from leap_core.types import UNLABELED

TINY_BACKBONE = BackboneConfig(channels=16, layers=2, grid_cells=(1.0, 1.0, 1.0), knn=4)
TINY = ConsistencyConfig(
    enabled=True,
    backbone=TINY_BACKBONE,
    points_per_scan=0,
    min_steps=0,
    lr=1e-2,
    augment=False,
    device="cpu",
    num_threads=1,
    # float32 on every machine: these tests pin exact numbers, and ``auto`` resolves by the CPU.
    precision="float32",
)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Tiny tensors run fastest on one thread, and the shared test machine is often oversubscribed (where
    multi-threaded torch waits on descheduled threads)."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def synthetic_scan(seed: int, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """A scan with three geometrically distinct classes: ground plane 0, wall 1, pole 2. (N, 4), (N,)."""
    rng = np.random.default_rng(seed)
    ng, nw = n // 2, n // 3
    npole = n - ng - nw
    ground = np.column_stack([rng.uniform(-8, 8, ng), rng.uniform(-8, 8, ng), np.full(ng, -1.7)])
    wall = np.column_stack([rng.uniform(-8, 8, nw), np.full(nw, 6.0), rng.uniform(-1.7, 2.0, nw)])
    pole = np.column_stack(
        [rng.normal(2, 0.05, npole), rng.normal(-3, 0.05, npole), rng.uniform(-1.7, 2, npole)]
    )
    xyz = np.concatenate([ground, wall, pole]) + rng.normal(0, 0.01, (n, 3))
    pts = np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)
    labels = np.repeat(np.arange(3), [ng, nw, npole]).astype(np.int16)
    return pts, labels


# --------------------------------------------------------------------------------------------- selection
def test_per_class_quota_rounds_up_but_not_on_float_noise() -> None:
    assert per_class_quota(10, 0.2) == 2  # 0.2 * 10 = 2.0000000000000004 in floats
    assert per_class_quota(3, 0.2) == 1
    assert per_class_quota(11, 0.2) == 3
    assert per_class_quota(0, 0.2) == 0
    assert per_class_quota(5, 1.0) == 5


def test_select_reliable_keeps_top_share_per_class_exactly() -> None:
    # class 0: 10 points, confidences 0.0 .. 0.9 in shuffled order; class 1: 3 points; class 2: none;
    # 4 unlabeled points with the highest confidences of all.
    lab0_conf = np.array([0.5, 0.9, 0.1, 0.8, 0.3, 0.0, 0.7, 0.2, 0.6, 0.4])
    labels = np.array([0] * 10 + [1] * 3 + [UNLABELED] * 4, dtype=np.int16)
    conf = np.concatenate([lab0_conf, [0.3, 0.2, 0.31], [1.0, 1.0, 1.0, 1.0]]).astype(np.float32)
    sel = select_reliable(labels, conf, num_classes=3, share=0.2)
    # class 0 keeps ceil(0.2·10) = 2: confidences 0.9 (index 1) and 0.8 (index 3); class 1 keeps 1 (0.31).
    assert np.flatnonzero(sel).tolist() == [1, 3, 12]
    assert not sel[labels == UNLABELED].any()


def test_select_reliable_ties_break_by_index_and_share_one_keeps_all_labeled() -> None:
    labels = np.array([2, 2, 2, 2, 2], dtype=np.int16)
    conf = np.full(5, 0.5, np.float32)
    assert np.flatnonzero(select_reliable(labels, conf, 3, 0.4)).tolist() == [0, 1]
    labels2 = np.array([0, UNLABELED, 1, 1], dtype=np.int16)
    assert select_reliable(labels2, np.ones(4, np.float32), 2, 1.0).tolist() == [True, False, True, True]


def test_support_breaks_confidence_ties_before_the_tie_order() -> None:
    # Five saturated points of class 0 (ties) and one less confident: support decides among the ties only.
    labels = np.zeros(6, np.int16)
    conf = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 0.9], np.float32)
    support = np.array([1, 7, 3, 7, 2, 99])
    # share 0.5 keeps 3: the two with support 7 (indices 1, 3, in index order), then support 3 (index 2);
    # index 5 has the most support but a lower confidence, which ranks first.
    assert np.flatnonzero(select_reliable(labels, conf, 1, 0.5, support=support)).tolist() == [1, 2, 3]
    assert np.flatnonzero(select_reliable(labels, conf, 1, 0.5)).tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="support"):
        select_reliable(labels, conf, 1, 0.5, support=support[:3])
    # Per scan, each scan's own support array is used.
    masks = select_reliable_scans([labels, labels], [conf, conf], 1, 0.5, support=[support, support[::-1]])
    assert np.flatnonzero(masks[0]).tolist() == [1, 2, 3]
    assert np.flatnonzero(masks[1]).tolist() == [0, 2, 4]  # reversed support: 99, 2, 7, 3, 7 (+ 1 at 0.9)


def test_per_scan_tie_order_is_seeded_by_the_frame_number() -> None:
    """Scan s breaks ties with ``seed + scan_numbers[s]``: frame 13's selection is the same whether it is
    the first scan of a run over frames 13.. or the fourteenth of a run over 0.."""
    labels = np.zeros(40, np.int16)
    conf = np.full(40, 0.5, np.float32)  # all tied: the seeded order alone decides
    alone = select_reliable(labels, conf, 1, 0.25, 7 + 13)
    masks = select_reliable_scans([labels, labels], [conf, conf], 1, 0.25, seed=7, scan_numbers=[13, 14])
    np.testing.assert_array_equal(masks[0], alone)
    np.testing.assert_array_equal(masks[1], select_reliable(labels, conf, 1, 0.25, 7 + 14))
    assert not np.array_equal(masks[0], masks[1])
    # Without frame numbers, scan s uses seed + s.
    default = select_reliable_scans([labels], [conf], 1, 0.25, seed=7)
    np.testing.assert_array_equal(default[0], select_reliable(labels, conf, 1, 0.25, 7))


def test_view_counts_count_frames_not_points() -> None:
    keys, counts = view_counts([np.array([5, 5, 7]), np.array([7]), np.array([9, 7, 7, 7])])
    assert keys.tolist() == [5, 7, 9] and counts.tolist() == [1, 3, 1]
    assert lookup_counts(np.array([7, 8, 5, 10, 9, 0]), keys, counts).tolist() == [3, 0, 1, 0, 1, 0]
    empty_keys, empty_counts = view_counts([])
    assert len(empty_keys) == 0
    assert lookup_counts(np.array([1, 2]), empty_keys, empty_counts).tolist() == [0, 0]


def test_view_counts_and_lookup_counts_are_int64_even_when_empty() -> None:
    # Callers index and concatenate these arrays: float64 keys or counts would silently change hashing and
    # comparisons (a float key loses bits above 2^53).
    keys, counts = view_counts([np.array([3, 1], np.int32), np.array([1], np.int32)])
    assert (keys.dtype, counts.dtype) == (np.int64, np.int64)
    assert counts.tolist() == [2, 1]
    empty_keys, empty_counts = view_counts([])
    assert (empty_keys.shape, empty_counts.shape) == ((0,), (0,))
    assert (empty_keys.dtype, empty_counts.dtype) == (np.int64, np.int64)
    assert lookup_counts(np.array([1, 2]), keys, counts).dtype == np.int64


def test_per_scan_tie_order_uses_seed_plus_scan_index() -> None:
    # Ten tied points of one class per scan, share 0.3 keeps 3: which 3 depends on the tie order only, and
    # scan s draws it from seed + s (so equal scans do not all keep the same indices).
    labels = np.zeros(10, np.int16)
    conf = np.ones(10, np.float32)
    masks = select_reliable_scans([labels, labels], [conf, conf], 1, 0.3, scope="scan", seed=5)
    for s in range(2):
        np.testing.assert_array_equal(masks[s], select_reliable(labels, conf, 1, 0.3, seed=5 + s))
    assert not np.array_equal(masks[0], masks[1])
    # Over the sequence the concatenated points use the seed itself.
    seq = select_reliable_scans([labels, labels], [conf, conf], 1, 0.3, scope="sequence", seed=5)
    whole = select_reliable(np.concatenate([labels, labels]), np.concatenate([conf, conf]), 1, 0.3, seed=5)
    np.testing.assert_array_equal(np.concatenate(seq), whole)
    assert not np.array_equal(whole, select_reliable(np.zeros(20, np.int16), np.ones(20, np.float32), 1, 0.3))
    with pytest.raises(ValueError):  # one confidence array for two scans
        select_reliable_scans([labels, labels], [conf], 1, 0.3, scope="scan")


def test_quota_rounds_share_times_count_to_9_decimals_only() -> None:
    # 0.20000000003 · 10 = 2.0000000003: rounded to 9 decimals it is 2 (keep 2), not a count above 2.
    assert per_class_quota(10, 0.20000000003) == 2
    assert per_class_quota(10, 0.2000000003) == 3  # 2.000000003 survives the rounding: ceil → 3


def test_select_reliable_returns_a_bool_mask_and_ranks_nan_last() -> None:
    labels = np.zeros(2, np.int16)
    # A NaN confidence ranks below every number (even 0), a NaN support below every support (even 0).
    sel = select_reliable(labels, np.array([np.nan, 0.0], np.float32), 1, 0.5)
    assert sel.dtype == np.bool_ and sel.tolist() == [False, True]
    ties = np.ones(2, np.float32)
    assert select_reliable(labels, ties, 1, 0.5, support=np.array([np.nan, 0.0])).tolist() == [False, True]
    # Unsigned supports (frame counts) rank by value: negating them must not wrap 0 to the top.
    frames = np.array([0, 3], np.uint32)
    assert select_reliable(labels, ties, 1, 0.5, support=frames).tolist() == [False, True]


def test_seeded_tie_order_is_the_seeds_permutation() -> None:
    # lexsort ranks tied points by the permutation's value: the kept ones are the k smallest.
    n, k = 10, 3
    perm = np.random.default_rng(5).permutation(n)
    sel = select_reliable(np.zeros(n, np.int16), np.ones(n, np.float32), 1, 0.3, seed=5)
    assert np.flatnonzero(sel).tolist() == sorted(np.argsort(perm)[:k].tolist())
    assert np.flatnonzero(sel).tolist() != [0, 1, 2]  # differs from the index order of seed=None


def test_select_reliable_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="labels must lie"):
        select_reliable(np.array([3], np.int16), np.ones(1, np.float32), 3, 0.2)
    with pytest.raises(ValueError, match="share"):
        select_reliable(np.array([0], np.int16), np.ones(1, np.float32), 3, 0.0)
    with pytest.raises(ValueError, match="share"):
        select_reliable(np.array([0], np.int16), np.ones(1, np.float32), 3, 1.5)
    with pytest.raises(ValueError, match="must both be"):
        select_reliable(np.array([0, 1], np.int16), np.ones(1, np.float32), 3, 0.5)


def test_selection_on_a_hand_made_grid_per_scan_and_per_sequence() -> None:
    # Four voxels on a line at 0.2 m: labels 0, 0, 1, 1 with known confidences.
    centres = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [0.5, 0.1, 0.1], [0.7, 0.1, 0.1]])
    keys = voxel_keys(centres, 0.2)
    # logp rows: conf = 1 / Σ exp(logp) → voxel 0: 1/(1+e^-1), voxel 1: 1/(1+e^-3), voxel 2/3 for class 1.
    logp = np.array([[0, -1], [0, -3], [-2, 0], [-0.5, 0]], dtype=np.float16)
    order = np.argsort(keys)
    grid = VoxelGrid(keys[order], logp[order], 0.2)
    # Scan A: 5 points in voxel 0, 5 in voxel 1, 2 in voxel 2, 1 point in no voxel.
    pts_a = np.concatenate(
        [
            np.repeat(centres[[0]], 5, 0),
            np.repeat(centres[[1]], 5, 0),
            np.repeat(centres[[2]], 2, 0),
            [[5.0, 5.0, 5.0]],
        ]
    )
    lab_a, conf_a = grid.labels_at(voxel_keys(pts_a, 0.2))
    assert lab_a.tolist() == [0] * 10 + [1] * 2 + [UNLABELED]
    np.testing.assert_allclose(
        conf_a[[0, 5, 10]],
        [1 / (1 + math.exp(-1)), 1 / (1 + math.exp(-3)), 1 / (1 + math.exp(-2))],
        rtol=1e-3,
    )
    assert conf_a[12] == 0.0
    # Scan B: 5 points in voxel 3 (class 1, conf 1/(1+e^-0.5)).
    pts_b = np.repeat(centres[[3]], 5, 0)
    lab_b, conf_b = grid.labels_at(voxel_keys(pts_b, 0.2))

    per_scan = select_reliable_scans([lab_a, lab_b], [conf_a, conf_b], 2, 0.2, scope="scan")
    # Scan A class 0: ceil(2) = 2 points, from voxel 1 (most confident), lowest indices 5, 6;
    # class 1: ceil(0.4) = 1 point (index 10). Scan B class 1: 1 point (index 0).
    assert np.flatnonzero(per_scan[0]).tolist() == [5, 6, 10]
    assert np.flatnonzero(per_scan[1]).tolist() == [0]
    per_seq = select_reliable_scans([lab_a, lab_b], [conf_a, conf_b], 2, 0.2, scope="sequence")
    # Over the sequence class 1 has 7 points → ceil(1.4) = 2, both from voxel 2 (scan A), none from B.
    assert np.flatnonzero(per_seq[0]).tolist() == [5, 6, 10, 11]
    assert not per_seq[1].any()


# ---------------------------------------------------------------------------------------------- backbone
def test_plane_index_averages_the_points_of_each_cell() -> None:
    # Points 0, 1 in cell 2, point 2 in cell 0 of a (1, 2, 2) grid.
    plane = PlaneIndex.from_cells(torch.tensor([2, 2, 0]), (1, 2, 2))
    assert plane.occupied.tolist() == [0, 2] and plane.inverse.tolist() == [1, 1, 0]
    values = torch.tensor([[1.0, 2.0], [3.0, 4.0], [10.0, 0.0]])
    assert torch.equal(torch.sparse.mm(plane.mean, values), torch.tensor([[10.0, 0.0], [2.0, 3.0]]))


def test_prepare_cloud_cells_and_neighbours_from_the_full_scan() -> None:
    pts = np.array([[0, 0, 0, 0], [0.1, 0, 0, 0], [2.5, 0, 0, 0], [2.5, 1.5, 0.5, 0]], dtype=np.float32)
    cfg = BackboneConfig(channels=8, layers=1, grid_cells=(1.0, 1.0, 0.5), knn=2)
    cloud = prepare_cloud(pts, cfg, subset=np.array([0, 2]))
    # Point 0's nearest other point is point 1, which is not in the subset but still its neighbour.
    np.testing.assert_allclose(cloud.local[0, 1, :3], np.array([0.1, 0, 0]) / LOCAL_SCALE, rtol=1e-5)
    np.testing.assert_allclose(cloud.local[0, 0], 0.0)  # itself first
    # xy plane, 1 m cells over the subset's extent x ∈ [0, 2.5]: u = 0 and 2, v = 0; grid 3 × 1.
    assert cloud.cell_uv[0].tolist() == [[0, 0], [2, 0]]
    assert cloud.grid_hw[0].tolist() == [3, 1]
    batch = collate([cloud, prepare_cloud(pts, cfg)])
    assert batch.grid_shapes[0] == (2, 3, 2)
    # Second cloud, point 3: (u, v) = (2, 1) in a 3 × 2 grid, batch offset 6 → 6 + 2·2 + 1 = 11.
    xy = batch.planes[0]
    assert int(xy.occupied[xy.inverse[-1]]) == 11


def test_without_position_inputs_the_features_do_not_depend_on_the_sensor_height() -> None:
    pts, _ = synthetic_scan(4, 200)
    full_cfg = BackboneConfig(channels=8, layers=1, knn=4)
    cfg = replace(full_cfg, position_inputs=False)
    assert (full_cfg.in_features, cfg.in_features) == (11, 7)
    full, rel = prepare_cloud(pts, full_cfg), prepare_cloud(pts, cfg)
    # The same features without x, y, z and range (the first four) ...
    np.testing.assert_array_equal(rel.feats, full.feats[:, 4:])
    np.testing.assert_array_equal(rel.local, full.local)
    # ... so a scan seen from 25 m higher gives the same inputs, where z and range change.
    higher = pts.copy()
    higher[:, 2] -= 25.0
    np.testing.assert_allclose(prepare_cloud(higher, cfg).feats, rel.feats, atol=1e-5)
    assert not np.allclose(prepare_cloud(higher, full_cfg).feats[:, :4], full.feats[:, :4])
    # The network is built for the narrower input.
    model = PointSegmenter(cfg, num_classes=3)
    assert model(collate([rel])).shape == (200, 3)


def test_backbone_forward_shape_gradients_and_point_order() -> None:
    torch.manual_seed(0)
    pts, _ = synthetic_scan(0, 300)
    model = PointSegmenter(TINY_BACKBONE, num_classes=5)
    batch = collate([prepare_cloud(pts, TINY_BACKBONE)])
    logits = model(batch)
    assert logits.shape == (300, 5) and torch.isfinite(logits).all()
    logits.logsumexp(dim=1).sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        if name != "head.bias":  # logsumexp's gradient w.r.t. the bias sums to a constant
            assert p.grad.abs().sum() > 0, name
    # Shuffling the points shuffles the output the same way (scatter-mean and kNN max are order-free).
    perm = np.random.default_rng(1).permutation(300)
    model.eval()
    with torch.no_grad():
        a = model(collate([prepare_cloud(pts, TINY_BACKBONE)]))
        b = model(collate([prepare_cloud(pts[perm], TINY_BACKBONE)]))
    torch.testing.assert_close(b, a[perm], rtol=1e-4, atol=1e-5)


def test_backbone_batch_of_two_equals_each_alone() -> None:
    torch.manual_seed(0)
    model = PointSegmenter(TINY_BACKBONE, 3).eval()
    c1 = prepare_cloud(synthetic_scan(1, 200)[0], TINY_BACKBONE)
    c2 = prepare_cloud(synthetic_scan(2, 150)[0], TINY_BACKBONE)
    with torch.no_grad():
        both = model(collate([c1, c2]))
        torch.testing.assert_close(both[:200], model(collate([c1])), rtol=1e-4, atol=1e-5)
        torch.testing.assert_close(both[200:], model(collate([c2])), rtol=1e-4, atol=1e-5)


def test_cloud_tensors_to_keeps_shapes() -> None:
    c = collate([prepare_cloud(synthetic_scan(3, 50)[0], TINY_BACKBONE)])
    moved = c.to("cpu")
    assert isinstance(moved, CloudTensors) and moved.num_points == 50


# ------------------------------------------------------------------------------------ config + training
def test_config_validation_names_the_field() -> None:
    assert ConsistencyConfig.paper_scale().backbone.channels == 256
    assert ConsistencyConfig.paper_scale(temperature=1.0).temperature == 1.0
    for bad, field in [
        (lambda: ConsistencyConfig(iterations=3), ("iterations",)),
        (lambda: ConsistencyConfig(temperature=0.0), ("temperature",)),
        (lambda: ConsistencyConfig(test_time_views=0), ("test_time_views",)),
        (lambda: ConsistencyConfig(new_voxel_margin=-1.0), ("new_voxel_margin",)),
        (lambda: ConsistencyConfig(network_evidence="point"), ("new_voxel_margin",)),
        (
            lambda: ConsistencyConfig(network_evidence="pixel"),  # type: ignore[arg-type]  # invalid on purpose
            ("network_evidence",),
        ),
        (lambda: ConsistencyConfig(min_steps=-1), ("min_steps",)),
        (lambda: BackboneConfig(kernel_size=2), ("kernel_size",)),
    ]:
        with pytest.raises(ConfigError) as err:
            bad()
        assert err.value.field == field and str(err.value).startswith(f"{field[0]}: must")
    paper = ConsistencyConfig.paper_scale()
    assert config_from_dict(config_to_dict(paper)) == paper


def test_lr_schedule_warms_up_then_decays_to_zero() -> None:
    assert lr_factor(0, 100) == pytest.approx(0.2)  # 5 warm-up steps
    assert lr_factor(4, 100) == pytest.approx(1.0)
    assert lr_factor(5, 100) == pytest.approx(1.0)
    assert lr_factor(100, 100) == pytest.approx(0.0, abs=1e-12)


def _scans(n: int = 4, share_labeled: float = 0.5) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for i in range(n):
        pts, lab = synthetic_scan(10 + i)
        lab = lab.copy()
        lab[np.random.default_rng(i).random(len(lab)) > share_labeled] = UNLABELED
        out[i] = (pts, lab)
    return out


def test_tiny_training_reduces_the_loss_and_is_deterministic() -> None:
    scans = _scans()
    cfg = replace(TINY, epochs=8)
    model, stats = train_model(scans.__getitem__, list(scans), 3, cfg)
    assert stats.steps == 32 and len(stats.losses) == 32
    assert np.mean(stats.losses[-4:]) < 0.5 * np.mean(stats.losses[:4])
    # The trained network separates the three shapes on a scan it has not seen.
    pts, lab = synthetic_scan(99)
    pred = predict_log_probs(model, pts).argmax(axis=1)
    assert (pred == lab).mean() > 0.9
    _, stats2 = train_model(scans.__getitem__, list(scans), 3, cfg)
    assert stats2.losses == stats.losses


@pytest.mark.slow
def test_bfloat16_training_learns_is_deterministic_and_is_mixed_precision() -> None:
    scans = _scans()
    cfg = replace(TINY, epochs=8, precision="bfloat16")
    model, stats = train_model(scans.__getitem__, list(scans), 3, cfg)
    assert np.mean(stats.losses[-4:]) < 0.5 * np.mean(stats.losses[:4])
    pts, lab = synthetic_scan(99)
    logp = predict_log_probs(model, pts, precision=torch.bfloat16)
    assert (logp.argmax(axis=1) == lab).mean() > 0.9
    _, again = train_model(scans.__getitem__, list(scans), 3, cfg)
    assert again.losses == stats.losses
    # The passes ran in bfloat16 (float32's losses differ), the weights stayed float32, and float32
    # inference of the same weights agrees to bfloat16's rounding.
    _, full = train_model(scans.__getitem__, list(scans), 3, replace(cfg, precision="float32", epochs=1))
    assert full.losses[0] != stats.losses[0]  # the same weights and batch, another arithmetic
    assert all(p.dtype == torch.float32 for p in model.parameters())
    prob32, prob16 = np.exp(predict_log_probs(model, pts)), np.exp(logp)
    assert not np.array_equal(prob32, prob16) and np.abs(prob32 - prob16).max() < 0.1


def test_precision_resolves_by_the_hardware_only_for_auto() -> None:
    cpu = torch.device("cpu")
    assert resolve_precision(replace(TINY, precision="float32"), cpu) is None
    assert resolve_precision(replace(TINY, precision="bfloat16"), cpu) is torch.bfloat16
    auto = resolve_precision(replace(TINY, precision="auto"), cpu)
    assert auto is (torch.bfloat16 if native_bfloat16(cpu) else None)
    with pytest.raises(ConfigError, match="precision"):
        replace(TINY, precision="float16")


@pytest.mark.parametrize(("n", "subset"), [(600, True), (600, False), (3, False)])
def test_the_device_preparation_agrees_with_the_kd_tree_one(n: int, subset: bool) -> None:
    pts, _ = synthetic_scan(5, n)
    pts[:, 3] = np.random.default_rng(1).uniform(0, 1, n)
    cfg = replace(TINY_BACKBONE, knn=8, grid_cells=(0.7, 0.9, 1.1))
    sub = np.sort(np.random.default_rng(2).choice(n, n // 2, replace=False)) if subset else None
    want = prepare_cloud(pts, cfg, sub)
    nbr = neighbours(pts[:, :3], pts[sub if subset else slice(None), :3], cfg.knn)
    got = prepare_cloud_tensors(
        torch.from_numpy(pts), cfg, torch.from_numpy(nbr), None if sub is None else torch.from_numpy(sub)
    )
    np.testing.assert_allclose(got.feats.numpy(), want.feats, atol=2e-5)
    np.testing.assert_allclose(got.local.numpy(), want.local, atol=2e-5)
    assert np.array_equal(got.cell_uv.numpy(), want.cell_uv) and np.array_equal(got.grid_hw, want.grid_hw)
    a, b = collate([want, want]), collate([got, got])
    assert all(torch.equal(p.occupied, q.occupied) for p, q in zip(a.planes, b.planes, strict=True))


def test_a_training_batch_prepared_on_the_device_matches_the_cpu_one() -> None:
    scans = _scans()
    cfg = replace(TINY, points_per_scan=200, augment=True, scans_per_step=2)
    on_cpu = _training_batch(scans.__getitem__, [0, 1], cfg, np.random.default_rng(4), 1)
    on_dev = _training_batch(scans.__getitem__, [0, 1], cfg, np.random.default_rng(4), 1, torch.device("cpu"))
    assert on_cpu is not None and on_dev is not None
    assert torch.equal(on_cpu[1], on_dev[1])  # the same points drawn, the same targets
    assert on_cpu[0].num_points == on_dev[0].num_points == 400
    torch.testing.assert_close(on_dev[0].feats, on_cpu[0].feats, atol=2e-5, rtol=0)
    torch.testing.assert_close(on_dev[0].local, on_cpu[0].local, atol=2e-5, rtol=0)


def test_a_checkpoints_fingerprint_outlives_new_fields_at_their_former_value() -> None:
    def fp(cfg: ConsistencyConfig) -> str:
        return training_fingerprint(cfg, 3, range(2), [np.zeros(2, np.int16), np.ones(2, np.int16)])

    # The hash these inputs had before test_time_views and backbone.position_inputs existed (and still
    # have): a checkpoint trained then is reused now. A field added without an entry in ADDED_FIELDS
    # changes it and fails here.
    assert fp(TINY) == "2294347dae8d1c79d40245986403d4c8e1ed76f7ff315bf0bf17ef940f6bb912"
    # The form of a round over several sequences (frames per named sequence) is pinned too: changing it
    # retrains every saved checkpoint of a run of several sequences.
    joint = training_fingerprint(TINY, 3, [("a", range(2))], [np.zeros(2, np.int16), np.ones(2, np.int16)])
    assert joint == "b66c14e93b1ee4ad502e141e0cf97bd81ff92e12c9f6d3766997be2e613c372d"
    assert fp(replace(TINY, backbone=replace(TINY_BACKBONE, position_inputs=False))) != fp(TINY)
    plain = config_to_dict(TINY)
    form = fingerprint_form(plain)
    assert set(form) == set(plain) - {"test_time_views", "finetune_lr", "finetune_min_steps", "precision"}
    assert set(form["backbone"]) == set(plain["backbone"]) - {"position_inputs"}
    assert plain["test_time_views"] == 1 and plain["backbone"]["position_inputs"] is True  # not written to
    other = fingerprint_form(
        config_to_dict(
            replace(TINY, test_time_views=2, backbone=replace(TINY_BACKBONE, position_inputs=False))
        )
    )
    assert other["test_time_views"] == 2 and other["backbone"]["position_inputs"] is False
    # new_voxel_margin: 0 computes what was computed before it existed, so stage fingerprints leave it out
    # there; the default (4) is in them (a finished run fuses its network again); never in the training
    # fingerprint (it acts after training).
    assert "new_voxel_margin" not in fingerprint_form(config_to_dict(replace(TINY, new_voxel_margin=0.0)))
    assert form["new_voxel_margin"] == 4.0
    assert fp(replace(TINY, new_voxel_margin=0.0)) == fp(TINY) == fp(replace(TINY, new_voxel_margin=6.0))


def test_test_time_views_by_hand() -> None:
    p = np.array([[1.0, 2.0, 3.0, 0.5]], np.float32)
    # View j of 4: mirror y when j is odd, then turn by j · 90° about z; z and remission stay.
    expected = [[1, 2], [2, 1], [-1, -2], [-2, -1]]
    for j, xy in enumerate(expected):
        v = inference_view(p, j, 4)
        np.testing.assert_allclose(v, [[*xy, 3.0, 0.5]], atol=1e-6)
    assert inference_view(p, 0, 1) is not p
    with pytest.raises(ValueError, match="view 4 of 4"):
        inference_view(p, 4, 4)


def test_predictions_are_averaged_over_test_time_views() -> None:
    scans = _scans()
    model, _ = train_model(
        scans.__getitem__, list(scans), 3, replace(TINY, epochs=2), class_counts=[100, 10, 0]
    )
    pts = synthetic_scan(99)[0]
    one = predict_log_probs(model, pts)
    assert np.array_equal(predict_log_probs(model, pts, views=1), one)
    views = [predict_log_probs(model, inference_view(pts, j, 3)) for j in range(3)]
    mean = predict_log_probs(model, pts, views=3)
    # log of the mean probability; the untrained class stays -inf
    np.testing.assert_allclose(
        np.exp(mean[:, :2]), np.mean([np.exp(v[:, :2]) for v in views], axis=0), rtol=1e-5, atol=1e-7
    )
    assert np.isneginf(mean[:, 2]).all()
    assert not np.allclose(mean, one)
    with pytest.raises(ValueError, match="views must be >= 1"):
        predict_log_probs(model, pts, views=0)


def test_training_with_subsampling_augmentation_and_class_weights_runs() -> None:
    scans = _scans(3)
    cfg = replace(TINY, points_per_scan=200, augment=True, scans_per_step=2, epochs=2)
    calls: list[tuple[int, int]] = []
    model, stats = train_model(
        scans.__getitem__,
        list(scans),
        3,
        cfg,
        progress=lambda d, t: calls.append((d, t)),
        class_counts=[100, 10, 0],
    )
    # Class 2 had no selected label: the model gives it probability 0, the others still sum to 1.
    assert model.trained_classes.tolist() == [True, True, False]
    logp = predict_log_probs(model, synthetic_scan(5)[0])
    assert np.isneginf(logp[:, 2]).all()
    np.testing.assert_allclose(np.exp(logp[:, :2]).sum(axis=1), 1.0, rtol=1e-5)
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    # Each epoch: one step of 2 scans and one of 1 scan, 200 points drawn from each.
    assert stats.points_seen == 2 * 3 * 200
    assert 0 < stats.labeled_seen < stats.points_seen


def test_draw_points_reserves_a_share_for_labeled_points() -> None:
    target = np.full(1000, UNLABELED, np.int16)
    target[:50] = 1
    idx = draw_points(target, 100, 0.3, np.random.default_rng(0))
    assert len(idx) == 100 and len(np.unique(idx)) == 100 and np.all(np.diff(idx) > 0)
    assert (idx < 50).sum() == 30
    idx = draw_points(target, 200, 0.5, np.random.default_rng(0))
    assert (idx < 50).sum() == 50  # only 50 labeled points exist; the other 150 are context
    assert draw_points(target, 0, 0.5, np.random.default_rng(0)).tolist() == list(range(1000))
    assert (draw_points(target, 100, 0.0, np.random.default_rng(0)) < 50).sum() < 30


def test_checkpoint_reloads_to_identical_predictions(tmp_path: Path) -> None:
    scans = _scans(2)
    model, stats = train_model(scans.__getitem__, [0, 1], 3, TINY)
    path = tmp_path / "ck.pt"
    save_checkpoint(path, model, TINY, meta={"fingerprint": "abc", "losses": stats.losses})
    ck = load_checkpoint(path)
    assert ck.config == TINY and ck.num_classes == 3 and ck.meta["fingerprint"] == "abc"
    pts, _ = synthetic_scan(7)
    assert np.array_equal(predict_log_probs(ck.model, pts), predict_log_probs(model, pts))


def _weights(model: PointSegmenter) -> dict[str, torch.Tensor]:
    """The learned parameters (not the buffers: batch-norm statistics move in training whatever the lr)."""
    return {k: v.detach().clone() for k, v in model.named_parameters()}


def test_fine_tuning_starts_from_the_source_and_takes_its_own_schedule() -> None:
    scans = _scans()
    source, _ = train_model(scans.__getitem__, list(scans), 3, replace(TINY, epochs=2))
    before = _weights(source)
    # finetune_lr (not lr) drives the optimiser: at 1e-12 the network stays the source's weights.
    frozen = replace(TINY, lr=1e-2, finetune_lr=1e-12, min_steps=9, seed=5)
    tuned, stats = train_model(scans.__getitem__, list(scans), 3, frozen, init=source)
    for k, v in _weights(tuned).items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=1e-7)
    # One epoch over the 4 scans: finetune_min_steps (0) replaces min_steps (9).
    assert stats.steps == 4 == num_train_steps(4, frozen, finetune=True)
    assert num_train_steps(4, frozen) == 9
    assert num_train_steps(4, replace(frozen, finetune_min_steps=6), finetune=True) == 6
    # The source itself is not trained further.
    for k, v in _weights(source).items():
        assert torch.equal(v, before[k])
    # From random weights (same seed, same steps) the network is not the source.
    fresh, _ = train_model(scans.__getitem__, list(scans), 3, replace(frozen, min_steps=4))
    assert any(not torch.allclose(v, before[k]) for k, v in _weights(fresh).items())
    # A real fine-tune moves the weights and keeps what the source predicts on an unseen scan.
    moved, _ = train_model(scans.__getitem__, list(scans), 3, replace(TINY, finetune_lr=1e-3), init=source)
    assert any(not torch.allclose(v, before[k]) for k, v in _weights(moved).items())
    pts, lab = synthetic_scan(99)
    assert (predict_log_probs(moved, pts).argmax(axis=1) == lab).mean() > 0.9


def test_load_source_checks_backbone_and_classes_and_names_the_file(tmp_path: Path) -> None:
    scans = _scans(2)
    model, _ = train_model(scans.__getitem__, [0, 1], 3, TINY)
    path = tmp_path / "src.pt"
    save_checkpoint(path, model, TINY)
    src = load_source(path, TINY_BACKBONE, 3)
    assert src.digest == hashlib.sha256(path.read_bytes()).hexdigest()
    pts = synthetic_scan(7)[0]
    assert np.array_equal(predict_log_probs(src.model, pts), predict_log_probs(model, pts))
    with pytest.raises(ModelLoadError, match=r"src\.pt: .*has 3 classes, this run's schema 4"):
        load_source(path, TINY_BACKBONE, 4)
    with pytest.raises(ModelLoadError, match=r"src\.pt: .*backbone differs .*channels 16 \(run: 32\)"):
        load_source(path, replace(TINY_BACKBONE, channels=32), 3)
    with pytest.raises(ModelLoadError, match="not found"):
        load_source(tmp_path / "none.pt", TINY_BACKBONE, 3)


def test_a_source_is_part_of_the_training_fingerprint() -> None:
    targets = [np.zeros(2, np.int16), np.ones(2, np.int16)]
    plain = training_fingerprint(TINY, 3, range(2), targets)
    a = training_fingerprint(TINY, 3, range(2), targets, "a" * 64)
    assert len({plain, a, training_fingerprint(TINY, 3, range(2), targets, "b" * 64)}) == 3
    assert training_fingerprint(TINY, 3, range(2), targets, None) == plain
    # The schedule's fields count once set away from their defaults.
    assert training_fingerprint(replace(TINY, finetune_lr=1e-3), 3, range(2), targets, "a" * 64) != a


def test_checkpoint_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ModelLoadError, match="not found"):
        load_checkpoint(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelLoadError, match=r"bad\.pt: unreadable"):
        load_checkpoint(bad)
    other = tmp_path / "other.pt"
    torch.save({"format": "something-else"}, other)
    with pytest.raises(ModelLoadError, match="not a LeAP 3D-CN checkpoint"):
        load_checkpoint(other)


# ------------------------------------------------------------------------------------------- fusion back
def _one_voxel_grid() -> tuple[VoxelGrid, np.ndarray]:
    key = voxel_keys(np.array([[0.1, 0.1, 0.1]]), 0.2)
    return VoxelGrid(key, np.array([[0.0, -1.0, -2.0]], np.float16), 0.2), key


def test_fuse_back_temperature_one_adds_the_log_probs_exactly_once() -> None:
    grid, key = _one_voxel_grid()
    net = np.log(np.array([[0.2, 0.7, 0.1]], np.float32))
    out = fuse_back(grid, [(key, net)], 3, temperature=1.0, fusion_cfg=FusionConfig())
    expected = np.array([0.0, -1.0, -2.0]) + np.log([0.2, 0.7, 0.1])
    expected -= expected.max()
    np.testing.assert_allclose(out.logp[0].astype(np.float64), expected, atol=2e-3)
    # Posterior by hand: prior softmax([0,-1,-2]) × network [0.2, 0.7, 0.1], normalised.
    prior = np.exp([0.0, -1.0, -2.0])
    post = prior * [0.2, 0.7, 0.1]
    np.testing.assert_allclose(out.probs()[0], post / post.sum(), atol=2e-3)


def test_fuse_back_temperature_scales_the_evidence_and_infinity_ignores_the_network() -> None:
    grid, key = _one_voxel_grid()
    net = np.log(np.array([[0.2, 0.7, 0.1]], np.float32))
    out2 = fuse_back(grid, [(key, net)], 3, temperature=2.0, fusion_cfg=FusionConfig())
    expected = np.array([0.0, -1.0, -2.0]) + 0.5 * np.log([0.2, 0.7, 0.1])
    np.testing.assert_allclose(out2.logp[0].astype(np.float64), expected - expected.max(), atol=2e-3)
    new_key = voxel_keys(np.array([[5.0, 5.0, 5.0]]), 0.2)
    out_inf = fuse_back(
        grid, [(np.concatenate([key, new_key]), np.repeat(net, 2, 0))], 3, math.inf, FusionConfig()
    )
    assert out_inf is grid  # unchanged, and no voxel created from zero-weight evidence
    # Finite T creates voxels the camera never saw.
    out_new = fuse_back(grid, [(new_key, net)], 3, 1.0, FusionConfig())
    assert out_new.num_voxels == 2 and out_new.lookup(new_key)[0] >= 0
    assert out_new.labels_and_confidence()[0][out_new.lookup(new_key)[0]] == 1
    np.testing.assert_array_equal(out_new.logp[out_new.lookup(key)[0]], grid.logp[0])


def test_voxel_evidence_is_the_mean_and_point_evidence_the_sum() -> None:
    grid, key = _one_voxel_grid()
    # Two points in the voxel (one per "scan"); the second has a class below the floor (1e-3).
    p1 = np.log(np.array([[0.2, 0.7, 0.1]], np.float32))
    p2 = np.log(np.array([[0.5, 0.4999, 0.0001]], np.float32))
    floor = math.log(1e-3)
    f1, f2 = p1[0].astype(np.float64), np.maximum(p2[0].astype(np.float64), floor)
    keys, means, counts = voxel_mean_log_probs([(key, p1), (key, p2)], 3, prob_floor=1e-3)
    assert keys.tolist() == key.tolist() and counts.tolist() == [2]
    np.testing.assert_allclose(means[0], (f1 + f2) / 2, rtol=1e-6)
    prior = np.array([0.0, -1.0, -2.0])
    for evidence, add in (("voxel", (f1 + f2) / 2), ("point", f1 + f2)):
        out = fuse_back(grid, [(key, p1), (key, p2)], 3, 1.0, FusionConfig(), evidence)
        expected = prior + add
        # float16 storage: half a unit in the last place is 0.004 for |logp| in [8, 16).
        np.testing.assert_allclose(out.logp[0].astype(np.float64), expected - expected.max(), atol=4e-3)
    with pytest.raises(ValueError, match="evidence"):
        fuse_back(grid, [(key, p1)], 3, 1.0, FusionConfig(), "pixel")


def test_voxel_mean_log_probs_of_nothing_bad_shapes_and_foreign_arrays() -> None:
    keys, means, counts = voxel_mean_log_probs([], 3, prob_floor=1e-3)
    assert (keys.dtype, means.dtype, counts.dtype) == (np.int64, np.float32, np.int64)
    assert keys.shape == (0,) and means.shape == (0, 3) and counts.shape == (0,)
    key = np.array([4], np.int64)
    for logp in (np.zeros((1, 4), np.float32), np.zeros((2, 3), np.float32), np.zeros(3, np.float32)):
        with pytest.raises(ValueError, match=r"predictions must be keys \(N,\) and logp \(N, 3\)"):
            voxel_mean_log_probs([(key, logp)], 3, prob_floor=1e-3)
    # A read-only (Ray object store) or float64 prediction is taken as float32, without a warning.
    ro = np.log(np.array([[0.2, 0.7, 0.1]], np.float32))
    ro.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, ro_means, _ = voxel_mean_log_probs([(key, ro), (key, ro.astype(np.float64))], 3, prob_floor=1e-3)
    assert ro_means.dtype == np.float32 and np.array_equal(ro_means, ro)


def test_fuse_back_uses_the_fusion_configs_floor_and_clip() -> None:
    """Floor 0.2 and clip 2: prior [0, -1, -2] + max(log [0.2, 0.7, 0.1], log 0.2) = [-1.609, -1.357,
    -3.609] → minus the max → [-0.252, 0, -2.252] → clipped at -2."""
    grid, key = _one_voxel_grid()
    net = np.log(np.array([[0.2, 0.7, 0.1]], np.float32))
    for evidence, chunk in (("voxel", 10**6), ("point", 10**6), ("point", 1)):
        out = fuse_back(
            grid,
            [(key, net)],
            3,
            1.0,
            FusionConfig(prob_floor=0.2, logp_clip=2.0),
            evidence,
            chunk_points=chunk,
        )
        np.testing.assert_allclose(
            out.logp[0].astype(np.float64), [1 + np.log(0.2 / 0.7), 0.0, -2.0], atol=4e-3
        )


def test_keep_known_or_sure_by_hand() -> None:
    known = np.array([2, 5], np.int64)
    keys = np.array([1, 2, 3, 5, 7], np.int64)
    means = np.array(
        [
            [-0.1, -5.0, -6.9],  # new, margin 4.9: kept
            [-1.0, -1.1, -3.0],  # known, margin 0.1: kept
            [-0.5, -3.0, -6.9],  # new, margin 2.5: dropped
            [-6.9, -6.9, -0.2],  # known: kept
            [-6.5, -3.0, -7.0],  # new, margin 3.5 (class 1 over class 0): dropped
        ],
        np.float32,
    )
    for chunk in (1, 2, 100):
        k, m = keep_known_or_sure(known, keys.copy(), means.copy(), 4.0, chunk=chunk)
        assert k.tolist() == [1, 2, 5] and m.tolist() == means[[0, 1, 3]].tolist()
    k, m = keep_known_or_sure(known, keys.copy(), means.copy(), 3.5, chunk=2)
    assert k.tolist() == [1, 2, 5, 7]  # a margin equal to the threshold is sure enough
    k, m = keep_known_or_sure(known, keys.copy(), means.copy(), 0.0)
    assert k.tolist() == keys.tolist()
    k, _ = keep_known_or_sure(np.zeros(0, np.int64), keys.copy(), means.copy(), 4.0)
    assert k.tolist() == [1, 5]  # an empty grid: only the sure voxels (margins 4.9 and 6.7)
    # The margin applies inside the camera view only: a new voxel outside it is kept however unsure.
    for chunk in (1, 100):
        k, m = keep_known_or_sure(known, keys.copy(), means.copy(), 4.0, np.array([3], np.int64), chunk)
        assert k.tolist() == [1, 2, 5, 7] and m.tolist() == means[[0, 1, 3, 4]].tolist()
    k, _ = keep_known_or_sure(known, keys.copy(), means.copy(), 4.0, keys.copy())
    assert k.tolist() == [1, 2, 5]
    k, _ = keep_known_or_sure(known, keys.copy(), means.copy(), 4.0, np.zeros(0, np.int64))
    assert k.tolist() == keys.tolist()
    # One new voxel alone is filtered too; one class has nothing to confuse it with (kept); two and four
    # classes take the margin between the best two.
    one = np.array([[-0.5, -3.0, -6.9]], np.float32)
    assert keep_known_or_sure(known, np.array([3], np.int64), one.copy(), 4.0)[0].tolist() == []
    k, m = keep_known_or_sure(known, keys.copy(), np.full((5, 1), -2.0, np.float32), 4.0)
    assert k.tolist() == keys.tolist() and m.shape == (5, 1)
    k, _ = keep_known_or_sure(known, keys.copy(), means[:, :2].copy(), 4.0)
    assert k.tolist() == [1, 2, 5]  # margins 4.9, 0.1, 2.5, 0, 3.5
    four = np.array(
        [
            [-6.0, -0.1, -5.0, -4.5],  # new, best two -0.1 and -4.5: margin 4.4, kept
            [-6.0, -6.0, -6.0, -6.0],  # known
            [-0.1, -5.0, -3.0, -6.0],  # new, margin 2.9: dropped
            [-6.0, -6.0, -6.0, -6.0],  # known
            [-1.0, -6.0, -6.5, -6.9],
        ],
        np.float32,
    )  # new, margin 5.0: kept
    k, _ = keep_known_or_sure(known, keys.copy(), four.copy(), 4.0)
    assert k.tolist() == [1, 2, 5, 7]


def test_fuse_back_creates_a_voxel_no_camera_saw_only_where_the_network_is_sure() -> None:
    grid, key = _one_voxel_grid()
    sure_key, unsure_key = voxel_keys(np.array([[5.0, 5.0, 5.0], [9.0, 9.0, 9.0]]), 0.2)[:, None]
    sure = np.log(np.array([[0.998, 0.001, 0.001]], np.float32))  # margin log(998) = 6.9
    unsure = np.log(np.array([[0.05, 0.9, 0.05]], np.float32))  # margin log(18) = 2.9
    known = np.log(np.array([[0.5, 0.3, 0.2]], np.float32))  # the camera's voxel: margin 0.5, still fused
    preds = [(key, known), (sure_key, sure), (unsure_key, unsure)]
    out = fuse_back(grid, preds, 3, 2.0, FusionConfig(), new_voxel_margin=4.0)
    assert sorted(out.keys.tolist()) == sorted([int(key[0]), int(sure_key[0])])
    every = fuse_back(grid, preds, 3, 2.0, FusionConfig())
    assert every.num_voxels == 3
    # Outside the camera view (not in `in_view`) the unsure voxel is created all the same.
    out_of_view = fuse_back(
        grid,
        preds,
        3,
        2.0,
        FusionConfig(),
        new_voxel_margin=4.0,
        in_view=np.sort(np.concatenate([key, sure_key])),
    )
    assert out_of_view.keys.tolist() == every.keys.tolist()
    for k in (key, sure_key):
        np.testing.assert_array_equal(out.logp[out.lookup(k)[0]], every.logp[every.lookup(k)[0]])
    with pytest.raises(ValueError, match="voxel evidence only"):
        fuse_back(grid, preds, 3, 2.0, FusionConfig(), "point", new_voxel_margin=4.0)


def test_fuse_back_in_chunks_equals_one_call() -> None:
    grid, _ = _one_voxel_grid()
    rng = np.random.default_rng(0)
    keys = voxel_keys(rng.uniform(0, 1, (50, 3)), 0.2)
    logp = np.log(rng.dirichlet(np.ones(3), 50)).astype(np.float32)
    preds = [(keys[:20], logp[:20]), (keys[20:], logp[20:])]
    for evidence in ("voxel", "point"):
        one = fuse_back(grid, preds, 3, 2.0, FusionConfig(), evidence, chunk_points=10**9)
        chunked = fuse_back(grid, preds, 3, 2.0, FusionConfig(), evidence, chunk_points=10)
        assert np.array_equal(one.keys, chunked.keys)
        np.testing.assert_allclose(one.logp.astype(np.float32), chunked.logp.astype(np.float32), atol=0.02)


def test_knn_embedding_in_blocks_equals_one_pass() -> None:
    """At evaluation the (N, K, hidden) intermediate is computed in blocks of ``chunk`` points above that
    size; it is per point, so blocks change nothing (to float32 matmul rounding: BLAS may sum a block's
    products in another order)."""
    torch.manual_seed(0)
    emb = KnnEmbedding(4, 3, 8, 6, chunk=10**6).eval()
    feats, local = torch.randn(50, 4), torch.randn(50, 5, 3)
    with torch.no_grad():
        one = emb(feats, local)
        emb.chunk = 7  # 50 points > 7: the block path
        blocks = emb(feats, local)
    torch.testing.assert_close(blocks, one, rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------------------------- stage
def _tiny_stage_inputs(tmp_path: Path, make_tiny_sequence) -> tuple[KittiSequence, VoxelGrid, int]:
    """A 3-frame sequence and a grid that knows only the voxels of points with x < 12 m ("camera view"),
    labeled by height: z < -0.5 → 0, z < 0.3 → 1, else 2."""
    tiny = make_tiny_sequence(tmp_path, n_frames=3, n_points=400)
    seq = KittiSequence(tiny.root)
    keys_list, lab_list = [], []
    for i in range(len(seq)):
        pts = seq.frame(i).points
        seen = pts[:, 0] < 12.0
        keys_list.append(voxel_keys(world_points(pts[seen], seq.poses[i]), 0.2))
        lab_list.append(np.digitize(pts[seen, 2], [-0.5, 0.3]))
    keys, first = np.unique(np.concatenate(keys_list), return_index=True)
    lab = np.concatenate(lab_list)[first]
    logp = np.full((len(keys), 3), -3.0, np.float16)
    logp[np.arange(len(keys)), lab] = 0.0
    return seq, VoxelGrid(keys, logp, 0.2), 3


def _predictions(
    seq: KittiSequence, frames: range, model: PointSegmenter, roll: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, the voxel keys of its points and the model's log-probabilities (classes rolled by
    ``roll``: predictions unlike the round's own)."""
    out = []
    for i in frames:
        pts = seq.frame(i).points
        out.append(
            (
                voxel_keys(world_points(pts, seq.poses[i]), 0.2),
                np.roll(predict_log_probs(model, pts), roll, axis=1),
            )
        )
    return out


def _tie_views(grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray]:
    """View counts that rank the tiny grid's equally confident voxels unlike the seeded random order."""
    return grid.keys, (np.arange(grid.num_voxels, dtype=np.int64) * 7) % 5


def test_run_3dcn_iteration_labels_points_outside_the_camera_view(tmp_path: Path, make_tiny_sequence) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    # The fused grid (evidence goes here) and the smoothed one (labels are read here) differ: the fused one
    # has every label moved to the next class, so a mix-up of the two shows in the result.
    fused = VoxelGrid(grid.keys, np.roll(grid.logp, 1, axis=1), grid.voxel_size)
    # Margin 0: every voxel the network predicts is created (the default margin is checked below).
    cfg = replace(TINY, epochs=2, temperature=1.0, new_voxel_margin=0.0)
    calls: list[tuple[int, int]] = []
    out = run_3dcn_iteration(
        seq,
        fused,
        grid,
        c,
        cfg,
        FusionConfig(),
        tmp_path / "work",
        1,
        progress=lambda d, t: calls.append((d, t)),
    )
    # Trained on the smoothed grid's labels (the checkpoint's fingerprint hashes them) ...
    ck = load_checkpoint(checkpoint_path(tmp_path / "work", 1))
    frames = range(len(seq))
    targets = reliable_targets(seq, grid, c, cfg, 0.2, frames, None)
    assert ck.meta["fingerprint"] == training_fingerprint(cfg, c, frames, targets)
    other = reliable_targets(seq, fused, c, cfg, 0.2, frames, None)
    assert training_fingerprint(cfg, c, frames, other) != ck.meta["fingerprint"]
    # ... and its predictions fused into the fused grid.
    preds = _predictions(seq, frames, ck.model)
    expected = fuse_back(
        fused,
        preds,
        c,
        cfg.temperature,
        FusionConfig(),
        cfg.network_evidence,
        new_voxel_margin=cfg.new_voxel_margin,
    )
    assert np.array_equal(out.keys, expected.keys) and np.array_equal(out.logp, expected.logp)
    assert calls[-1] == (3 + 2 * 3 + 3, 3 + 2 * 3 + 3)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert checkpoint_path(tmp_path / "work", 1).is_file()
    unseen = 0
    for i in range(len(seq)):
        pts = seq.frame(i).points
        keys = voxel_keys(world_points(pts, seq.poses[i]), 0.2)
        assert (out.lookup(keys) >= 0).all()  # every point of every scan now has a voxel
        unseen += int((grid.lookup(keys) < 0).sum())
    assert unseen > 100  # ... including the many points the "camera" never saw
    assert out.num_voxels > grid.num_voxels

    # A second call with the same inputs reuses the checkpoint (same fingerprint) and gives the same grid.
    mtime = checkpoint_path(tmp_path / "work", 1).stat().st_mtime_ns
    again = run_3dcn_iteration(seq, fused, grid, c, cfg, FusionConfig(), tmp_path / "work", 1)
    assert checkpoint_path(tmp_path / "work", 1).stat().st_mtime_ns == mtime
    assert np.array_equal(again.keys, out.keys) and np.array_equal(again.logp, out.logp)
    # Test-time views change the predictions, not the weights: the checkpoint is reused, and the grid takes
    # the view-averaged predictions.
    cfg4 = replace(cfg, test_time_views=4)
    four = run_3dcn_iteration(seq, fused, grid, c, cfg4, FusionConfig(), tmp_path / "work", 1)
    assert checkpoint_path(tmp_path / "work", 1).stat().st_mtime_ns == mtime
    preds4 = [
        (k, predict_log_probs(ck.model, seq.frame(i).points, views=4))
        for i, (k, _) in zip(frames, preds, strict=True)
    ]
    expected4 = fuse_back(fused, preds4, c, cfg.temperature, FusionConfig(), cfg.network_evidence)
    assert np.array_equal(four.keys, expected4.keys) and np.array_equal(four.logp, expected4.logp)
    assert not np.array_equal(four.logp, out.logp)
    # The margin for new voxels is applied after training too (checkpoint reused): the grid keeps every
    # camera voxel and creates fewer new ones, each one of margin 0's.
    vkeys, means, _ = voxel_mean_log_probs(preds, c, FusionConfig().prob_floor)
    top = np.sort(means, axis=1)
    margin = float(np.median((top[:, -1] - top[:, -2])[~np.isin(vkeys, fused.keys)]))  # half the new ones
    sure = run_3dcn_iteration(
        seq, fused, grid, c, replace(cfg, new_voxel_margin=margin), FusionConfig(), tmp_path / "work", 1
    )
    assert checkpoint_path(tmp_path / "work", 1).stat().st_mtime_ns == mtime
    expected_sure = fuse_back(fused, preds, c, cfg.temperature, FusionConfig(), new_voxel_margin=margin)
    assert np.array_equal(sure.keys, expected_sure.keys) and np.array_equal(sure.logp, expected_sure.logp)
    assert np.isin(fused.keys, sure.keys).all() and np.isin(sure.keys, out.keys).all()
    assert fused.num_voxels < sure.num_voxels < out.num_voxels
    # T = ∞ ignores the network entirely.
    assert (
        run_3dcn_iteration(
            seq, fused, grid, c, replace(cfg, temperature=math.inf), FusionConfig(), tmp_path / "work", 1
        )
        is fused
    )


def test_run_3dcn_iteration_never_trains_on_erased_voxels(tmp_path: Path, make_tiny_sequence) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    with pytest.raises(ValueError, match="no point of any scan has a voxel label"):
        run_3dcn_iteration(seq, grid, grid, c, TINY, FusionConfig(), tmp_path / "w", 1, erased=grid.keys)


def test_run_3dcn_iteration_needs_labels(tmp_path: Path, make_tiny_sequence) -> None:
    seq, _, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    empty = VoxelGrid.empty(c, 0.2)
    with pytest.raises(ValueError, match="no point of any scan has a voxel label"):
        run_3dcn_iteration(seq, empty, empty, c, TINY, FusionConfig(), tmp_path / "w", 1)


def test_reliable_targets_ticks_per_scan_and_never_labels_erased_voxels(
    tmp_path: Path, make_tiny_sequence
) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    erased = grid.keys[::3]
    ticks: list[int] = []
    targets = reliable_targets(
        seq,
        grid,
        c,
        replace(TINY, share=1.0),
        0.2,
        range(3),
        None,
        progress=lambda: ticks.append(1),
        erased=erased,
    )
    assert len(ticks) == 3
    for i, t in enumerate(targets):
        keys = voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), 0.2)
        hit = np.isin(keys, erased)
        assert hit.any() and (t[hit] == UNLABELED).all()
        # share 1: every other point with a voxel is a label, its voxel's class
        rows = grid.lookup(keys)
        keep = ~hit & (rows >= 0)
        assert np.array_equal(t[keep], grid.logp[rows[keep]].argmax(axis=1))
        assert (t[rows < 0] == UNLABELED).all()


def test_reliable_targets_are_the_selection_of_each_scans_voxel_labels_in_both_scopes(
    tmp_path: Path, make_tiny_sequence
) -> None:
    """Per scan: the points' voxel labels and confidences (``voxel_labels().at``), selected per scan
    (seed + frame number, view counts as support) or over the frames together."""
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    views, frames = _tie_views(grid), range(1, 3)  # frames 1, 2: their numbers seed the tie order
    at = grid.voxel_labels().at
    scans = [at(voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), 0.2)) for i in frames]
    support = [
        lookup_counts(voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), 0.2), *views)
        for i in frames
    ]
    cfg = replace(TINY, share=0.3, seed=11)
    for scope in ("scan", "sequence"):
        for v in (views, None):
            got = list(
                iter_reliable_targets(seq, grid, c, replace(cfg, selection_scope=scope), 0.2, frames, v)
            )
            masks = select_reliable_scans(
                [lab for lab, _ in scans],
                [conf for _, conf in scans],
                c,
                0.3,
                scope,
                seed=11,
                support=support if v is not None else None,
                scan_numbers=[1, 2],
            )
            assert len(got) == 2
            for t, m, (lab, _) in zip(got, masks, scans, strict=True):
                assert t.dtype == np.int16 and np.array_equal(t, np.where(m, lab, UNLABELED))
                assert (t >= 0).sum() > 10

    # the scope, the view counts and the seed each change what is selected here
    def run(v: tuple[np.ndarray, np.ndarray] | None = views, **kw: object) -> np.ndarray:
        return np.concatenate(list(iter_reliable_targets(seq, grid, c, replace(cfg, **kw), 0.2, frames, v)))

    base = run()
    assert not np.array_equal(base, run(selection_scope="sequence"))
    assert not np.array_equal(base, run(None))
    assert not np.array_equal(base, run(seed=12))


def test_iteration_config_offsets_the_seed_by_1000_per_later_round() -> None:
    cfg = replace(TINY, seed=5)
    assert iteration_config(cfg, 1) is cfg
    assert iteration_config(cfg, 2) == replace(cfg, seed=1005)
    assert iteration_config(cfg, 3).seed == 2005


def test_target_file_round_trip(tmp_path: Path) -> None:
    """Any integer targets are stored as int16 (2 bytes per point) and read back one scan at a time; the
    work folder is made as needed and closing twice is fine."""
    path = tmp_path / "a" / "b" / "t.i16"
    store = TargetFile.write(
        path, [np.array([3, -1, 0], np.int64), np.zeros(0, np.int16), np.array([7], np.int32)]
    )
    assert path.stat().st_size == 2 * 4 and len(store) == 3 and store.offsets == [0, 3, 3, 4]
    assert [t.tolist() for t in store] == [[3, -1, 0], [], [7]]
    assert store.read(2).dtype == np.int16
    store.close()
    store.close()
    assert not path.exists()


def test_fuse_back_refuses_a_bad_temperature_and_a_margin_on_point_evidence() -> None:
    grid = VoxelGrid.empty(3, 0.2)
    for t in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="temperature must be > 0"):
            fuse_back(grid, [], 3, t, FusionConfig())
    with pytest.raises(ValueError, match="voxel evidence only"):
        fuse_back(grid, [], 3, 1.0, FusionConfig(), "point", new_voxel_margin=0.5)
    with pytest.raises(ValueError, match="'voxel' or 'point'"):
        fuse_back(grid, [], 3, 1.0, FusionConfig(), "points")


def test_run_3dcn_iteration_hands_frames_views_and_in_view_to_its_round(
    tmp_path: Path, make_tiny_sequence
) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    views, frames = _tie_views(grid), range(1, 3)
    # Margin 100: no voxel the network creates inside the camera view survives; in_view = the camera's own
    # voxels, so every new voxel is outside it and created.
    cfg = replace(TINY, temperature=1.0, new_voxel_margin=100.0)
    work = tmp_path / "work"
    work.mkdir()
    checkpoint_path(work, 1).write_bytes(b"not a checkpoint")  # unreadable: trained again, replaced
    out = run_3dcn_iteration(
        seq, grid, grid, c, cfg, FusionConfig(), work, 1, frames=frames, views=views, in_view=grid.keys
    )
    ck = load_checkpoint(checkpoint_path(work, 1))
    targets = reliable_targets(seq, grid, c, cfg, 0.2, frames, views)
    assert not all(
        np.array_equal(a, b)
        for a, b in zip(targets, reliable_targets(seq, grid, c, cfg, 0.2, frames, None), strict=True)
    )
    assert ck.meta["fingerprint"] == training_fingerprint(cfg, c, frames, targets)
    assert ck.meta["frames"] == [1, 3, 1] and ck.meta["iteration"] == 1
    preds = _predictions(seq, frames, ck.model)
    expected = fuse_back(
        grid, preds, c, 1.0, FusionConfig(), cfg.network_evidence, new_voxel_margin=100.0, in_view=grid.keys
    )
    assert np.array_equal(out.keys, expected.keys) and np.array_equal(out.logp, expected.logp)
    assert out.num_voxels > grid.num_voxels
    every_voxel_in_view = fuse_back(
        grid, preds, c, 1.0, FusionConfig(), cfg.network_evidence, new_voxel_margin=100.0
    )
    assert every_voxel_in_view.num_voxels == grid.num_voxels
    # The camera view applies at margins below 1 nat too, and point evidence reaches fuse_back (the
    # checkpoint is reused: neither acts before training).
    half = run_3dcn_iteration(
        seq,
        grid,
        grid,
        c,
        replace(cfg, new_voxel_margin=0.5),
        FusionConfig(),
        work,
        1,
        frames=frames,
        views=views,
        in_view=grid.keys,
    )
    assert np.array_equal(half.keys, out.keys) and np.array_equal(half.logp, out.logp)
    assert fuse_back(grid, preds, c, 1.0, FusionConfig(), new_voxel_margin=0.5).num_voxels < out.num_voxels
    by_point = replace(cfg, new_voxel_margin=0.0, network_evidence="point")
    point = run_3dcn_iteration(
        seq, grid, grid, c, by_point, FusionConfig(), work, 1, frames=frames, views=views
    )
    expected_point = fuse_back(grid, preds, c, 1.0, FusionConfig(), "point")
    assert np.array_equal(point.keys, expected_point.keys) and np.array_equal(point.logp, expected_point.logp)
    assert not np.array_equal(point.logp, fuse_back(grid, preds, c, 1.0, FusionConfig()).logp)


def test_a_round_leaves_moving_points_out_of_its_labels_and_its_evidence(
    tmp_path: Path, make_tiny_sequence
) -> None:
    """``RoundPart.moving`` (the motion stage's movers, which the fusion left out): their points are never
    training labels and their predictions are not fused back."""
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    frames = range(3)

    def moving(i: int) -> np.ndarray:
        return np.arange(i, len(seq.frame(i).points), 3, dtype=np.int32)

    targets = reliable_targets(seq, grid, c, replace(TINY, share=1.0), 0.2, frames, None, moving=moving)
    for i, t in enumerate(targets):
        assert (t[moving(i)] == UNLABELED).all()
        rows = grid.lookup(voxel_keys(world_points(seq.frame(i).points, seq.poses[i]), 0.2))
        keep = rows >= 0
        keep[moving(i)] = False
        assert keep.any() and np.array_equal(t[keep], grid.logp[rows[keep]].argmax(axis=1))

    def predict(s: KittiSequence, fr: range, ckpt: Path):
        yield from _predictions(s, fr, load_checkpoint(ckpt).model, roll=1)

    work = tmp_path / "work"
    cfg = replace(TINY, temperature=1.0, new_voxel_margin=0.0)
    part = RoundPart(seq, grid, grid, frames, moving=moving)
    (out,) = iter_3dcn_round([part], c, cfg, FusionConfig(), work, 1, None, predict)
    cfg1 = iteration_config(cfg, 1)
    trained_on = reliable_targets(seq, grid, c, cfg1, 0.2, frames, None, moving=moving)
    fingerprint = load_checkpoint(checkpoint_path(work, 1)).meta["fingerprint"]
    assert fingerprint == training_fingerprint(cfg1, c, frames, trained_on)
    every = list(predict(seq, frames, checkpoint_path(work, 1)))
    expected = fuse_back(grid, without_rows(frames, every, moving), c, 1.0, FusionConfig())
    assert np.array_equal(out.keys, expected.keys) and np.array_equal(out.logp, expected.logp)
    assert not np.array_equal(out.logp, fuse_back(grid, every, c, 1.0, FusionConfig()).logp)


def test_a_joint_round_trains_one_network_on_every_part_and_fuses_each_part_back(
    tmp_path: Path, make_tiny_sequence
) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    other = VoxelGrid(grid.keys, np.roll(grid.logp, 1, axis=1), grid.voxel_size)
    fa, fb = range(0, 2), range(1, 3)
    erased = grid.keys[::4]
    parts = [
        RoundPart(seq, grid, grid, fa, _tie_views(grid), name="a"),
        RoundPart(seq, other, lambda: grid, fb, erased=erased, name="b"),
    ]
    cfg = replace(TINY, temperature=1.0, new_voxel_margin=0.0)
    work = tmp_path / "work"
    calls: list[tuple[int, int, bool]] = []
    predicted: list[tuple[list[int], Path]] = []

    def predict(s: KittiSequence, frames: range, ckpt: Path):
        predicted.append((list(frames), ckpt))
        yield from _predictions(s, frames, load_checkpoint(ckpt).model, roll=1)

    out = list(
        iter_3dcn_round(
            parts,
            c,
            cfg,
            FusionConfig(),
            work,
            2,
            lambda d, t: calls.append((d, t, targets_path(work, 2).is_file())),
            predict,
        )
    )
    # One network, trained on both parts' reliable labels (round 2's seed) ...
    cfg2 = iteration_config(cfg, 2)
    targets = reliable_targets(seq, grid, c, cfg2, 0.2, fa, _tie_views(grid)) + reliable_targets(
        seq, grid, c, cfg2, 0.2, fb, None, erased=erased
    )
    ck = load_checkpoint(checkpoint_path(work, 2))
    assert ck.meta["fingerprint"] == training_fingerprint(cfg2, c, [("a", fa), ("b", fb)], targets)
    assert ck.meta["fingerprint"] != training_fingerprint(cfg2, c, [("b", fa), ("a", fb)], targets)
    assert ck.meta["iteration"] == 2 and ck.meta["frames"] == [["a", 0, 2, 1], ["b", 1, 3, 1]]
    counts = sum(np.bincount(t[t >= 0], minlength=c) for t in targets)
    assert counts.min() > 0 and ck.meta["class_counts"] == counts.tolist()
    assert all(type(n) is int for n in ck.meta["class_counts"])
    # the weights are train_model's on the scans of a then b, class weights from both parts' counts
    scans = list(zip([*fa, *fb], targets, strict=True))
    model, stats = train_model(
        lambda j: (seq.frame(scans[j][0]).points, scans[j][1]), range(4), c, cfg2, class_counts=counts
    )
    for name, value in model.state_dict().items():
        assert torch.equal(value, ck.model.state_dict()[name]), name
    assert ck.meta["steps"] == stats.steps and ck.meta["losses"] == pytest.approx(stats.losses)
    assert ck.meta["seconds"] >= 0
    # ... each part's predictions (from the round's predict, here unlike local inference) fused into its own
    # grid.
    assert predicted == [([0, 1], checkpoint_path(work, 2)), ([1, 2], checkpoint_path(work, 2))]
    for grid_in, frames, got in zip([grid, other], [fa, fb], out, strict=True):
        expected = fuse_back(
            grid_in,
            _predictions(seq, frames, ck.model, roll=1),
            c,
            1.0,
            FusionConfig(),
            cfg.network_evidence,
            new_voxel_margin=0.0,
        )
        assert np.array_equal(got.keys, expected.keys) and np.array_equal(got.logp, expected.logp)
    # Progress: every step of selection (4 scans), training and inference (4 scans) once, in order; the
    # targets are spilled to round 2's file while the network trains, and the file is gone after.
    total = calls[-1][1]
    steps = total - 8
    assert steps >= 2 and [d for d, _, _ in calls] == sorted(d for d, _, _ in calls)
    assert {d for d, _, _ in calls} == set(range(1, total + 1))
    assert all(spilled for d, _, spilled in calls if 4 < d < 4 + steps)
    assert not targets_path(work, 2).exists()


def test_a_round_names_the_grid_and_sequence_of_another_class_count(
    tmp_path: Path, make_tiny_sequence
) -> None:
    seq, grid, c = _tiny_stage_inputs(tmp_path, make_tiny_sequence)
    two = VoxelGrid(grid.keys, grid.logp[:, :2], 0.2)
    cfg = replace(TINY, temperature=1.0)
    never = replace(cfg, temperature=math.inf)
    cases = [
        ([RoundPart(seq, two, grid)], never, "the fused grid has 2 classes, schema has 3"),
        (
            [RoundPart(seq, grid, grid, name="a"), RoundPart(seq, two, grid, name="b")],
            never,
            "the fused grid of sequence b has 2 classes",
        ),
        ([RoundPart(seq, grid, two, name="a")], cfg, "the smoothed grid of sequence a has 2 classes"),
        ([RoundPart(seq, two, grid)], cfg, "the fused grid has 2 classes"),  # checked after training
        ([], cfg, "a round needs at least one sequence"),
    ]
    for parts, c_cfg, message in cases:
        with pytest.raises(LeapError, match=f"^3D-CN: {message}"):
            list(iter_3dcn_round(parts, c, c_cfg, FusionConfig(), tmp_path / "w", 1))


def test_class_weights_by_hand() -> None:
    """w_c ∝ n_c^(-p), mean 1 over the present classes, 1 for absent ones; p = 0 or disabled: all 1."""
    assert class_weights([100, 1, 0]).tolist() == pytest.approx([2 / 11, 20 / 11, 1.0])
    # p = 0.25: raw 100^-0.25 = 1/sqrt(10) and 1; mean (1/sqrt(10) + 1) / 2
    m = (10**-0.5 + 1) / 2
    assert class_weights([100, 1, 0], power=0.25).tolist() == pytest.approx([10**-0.5 / m, 1 / m, 1.0])
    assert class_weights([100, 1, 0], power=0.0).tolist() == [1.0, 1.0, 1.0]
    assert class_weights([100, 1, 0], enabled=False).tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(ConfigError, match="must be in"):
        ConsistencyConfig(class_balance_power=1.5)
