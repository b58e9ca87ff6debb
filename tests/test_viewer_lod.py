"""Level of detail of big voxel maps (app/viewer/lod.py): Morton codes and blocks on hand-placed voxels,
majority class and mean score on hand-computed blocks, the budget and the full-resolution area, exact culled
selection and picking; then a real session (viser server, SQLite store) on a map larger than its budget."""

from __future__ import annotations

import math

import numpy as np
import pytest
from runhelpers import run_params

from app.viewer import lod, lod_cull, lod_plan
from app.viewer import view_logic as vl
from app.viewer.data import matrix_to_wxyz
from leap_core import selection as sel
from leap_core.fusion import VoxelGrid, key_centres, voxel_keys
from leap_core.io_utils import atomic_save_npz
from leap_core.picking import pick_voxel


def _morton_reference(x: int, y: int, z: int) -> int:
    """Bit by bit: bit b of x, y, z goes to bit 3b, 3b + 1, 3b + 2."""
    code = 0
    for b in range(21):
        code |= ((x >> b) & 1) << (3 * b) | ((y >> b) & 1) << (3 * b + 1) | ((z >> b) & 1) << (3 * b + 2)
    return code


def test_morton_codes_interleave_bits() -> None:
    ijk = np.array(
        [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [3, 5, 6], [(1 << 21) - 1, 12345, 777777]]
    )
    codes = lod.morton3(ijk)
    assert codes.dtype == np.uint64
    assert codes[:5].tolist() == [1, 2, 4, 7, 8]
    assert [int(c) for c in codes] == [_morton_reference(*map(int, v)) for v in ijk]
    with pytest.raises(ValueError, match="must lie in"):
        lod.morton3([[1 << 21, 0, 0]])
    with pytest.raises(ValueError, match="must lie in"):
        lod.morton3([[-1, 0, 0]])


def _hand_index() -> tuple[lod.LodIndex, np.ndarray]:
    # Voxel edge 1 m; level-1 blocks (2 voxels per edge): {row 0, row 1} share block (0,0,0); row 2 is in
    # (1,0,0), row 3 in (1,1,1), row 4 in (0,0,2).
    ijk = np.array([[0, 0, 0], [1, 1, 1], [2, 0, 0], [3, 3, 3], [0, 0, 4]])
    centres = (ijk + 0.5).astype(np.float32)
    return lod.build_index(centres, 1.0), centres


def test_blocks_group_the_voxels_of_each_cube() -> None:
    index, _ = _hand_index()
    blocks = index.blocks(1)
    assert blocks.count == 4 and blocks.edge == 2.0
    groups = {tuple(sorted(index.order[blocks.starts[b] : blocks.starts[b + 1]].tolist())) for b in range(4)}
    assert groups == {(0, 1), (2,), (3,), (4,)}
    b01 = blocks.of_row[0]
    assert blocks.of_row[1] == b01 and len(set(blocks.of_row.tolist())) == 4
    np.testing.assert_allclose(blocks.mean[b01], [1.0, 1.0, 1.0])  # mean of (0.5,0.5,0.5) and (1.5,1.5,1.5)
    np.testing.assert_allclose(
        blocks.lower[blocks.of_row[[0, 2, 3, 4]]], [[0, 0, 0], [2, 0, 0], [2, 2, 2], [0, 0, 4]]
    )
    assert index.blocks(1) is blocks  # built once
    assert index.blocks(3).count == 1  # one 8-voxel cube holds them all
    assert lod.block_counts(index.codes, 1) == 4 and lod.block_counts(index.codes, 0) == 5
    assert lod.choose_level(index.codes, 4) == 1 and lod.choose_level(index.codes, 3) == 2
    assert index.overview_level(6, 0.5) == 2  # ⌊0.5 · 6⌋ = 3 blocks at most


def test_segment_rows_concatenates_the_blocks_in_order() -> None:
    order = np.array([7, 5, 3, 1, 0, 2])
    starts = np.array([0, 2, 3, 6])
    assert lod.segment_rows(order, starts, np.array([2, 0])).tolist() == [1, 0, 2, 7, 5]
    assert lod.segment_rows(order, starts, np.array([1])).tolist() == [3]
    assert lod.segment_rows(order, starts, np.array([], np.int64)).size == 0


def test_majority_class_and_mean_score_by_hand() -> None:
    # Block 0: classes 0, 0, 1, unlabeled; block 1: 2, 2, unlabeled, unlabeled, 1.
    of_row = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1], np.int32)
    label = np.array([0, 0, 1, -1, 2, 2, -1, -1, 1], np.int16)
    score = np.array([0.9, 0.7, 0.2, 0.5, 0.6, 0.8, 0.1, 0.3, 1.0], np.float32)
    hist, ssum = lod.block_tables(of_row, 2, label, 3, score=score)
    assert hist.tolist() == [[1, 2, 1, 0], [2, 0, 1, 2]]
    all_on = lod_plan.enabled_columns((), 3)
    assert all_on.tolist() == [1, 1, 1, 1]
    blocks = np.array([0, 1])
    assert lod_plan.visible_counts(hist, all_on).tolist() == [4, 5]
    # Block 1: class 2 and unlabeled tie (2 each): the lower index, unlabeled, wins.
    assert lod_plan.majority_class(hist, all_on, blocks).tolist() == [0, -1]
    assert ssum is not None
    np.testing.assert_allclose(lod_plan.mean_score(hist, ssum, all_on, blocks), [2.3 / 4, 2.8 / 5], rtol=1e-6)
    # Class 0 hidden: block 0 is class 1 vs unlabeled (1 each) -> unlabeled; mean of 0.2 and 0.5.
    no0 = lod_plan.enabled_columns((False, True, True), 3)
    assert no0.tolist() == [1, 0, 1, 1]
    assert lod_plan.majority_class(hist, no0, blocks).tolist() == [-1, -1]
    np.testing.assert_allclose(lod_plan.mean_score(hist, ssum, no0, blocks), [0.35, 2.8 / 5], rtol=1e-6)
    # Threshold 0.5 keeps rows 0, 1, 3, 4, 5, 8: block 1 becomes class 2 (2) over class 1 (1).
    kept, _ = lod.block_tables(of_row, 2, label, 3, keep=score >= 0.5)
    assert kept.tolist() == [[1, 2, 0, 0], [0, 0, 1, 2]]
    assert lod_plan.majority_class(kept, all_on, blocks).tolist() == [0, 2]
    # A block with no visible voxel has mean 0 (not NaN).
    only2 = lod_plan.enabled_columns((False, False, True), 3)
    assert lod_plan.mean_score(kept, ssum, only2 * np.array([0, 1, 1, 1], np.float32), blocks)[0] == 0.0


@pytest.mark.parametrize("threshold", [0.0, 0.5])
def test_update_tables_equals_a_recount(threshold: float) -> None:
    rng = np.random.default_rng(8)
    n, nb, c = 5000, 300, 4
    of_row = rng.integers(0, nb, n).astype(np.int32)
    label = rng.integers(-1, c, n).astype(np.int16)
    score = rng.random(n).astype(np.float32)
    keep = score >= threshold
    hist, ssum = lod.block_tables(of_row, nb, label, c, keep=keep, score=score)
    assert ssum is not None
    rows = rng.choice(n, 200, replace=False)
    label2, score2 = label.copy(), score.copy()
    label2[rows] = rng.integers(-1, c, rows.size)
    score2[rows] = rng.random(rows.size)
    keep2 = score2 >= threshold
    lod_plan.update_tables(
        hist,
        ssum,
        of_row[rows],
        c,
        (label[rows], score[rows], keep[rows]),
        (label2[rows], score2[rows], keep2[rows]),
    )
    want_h, want_s = lod.block_tables(of_row, nb, label2, c, keep=keep2, score=score2)
    np.testing.assert_array_equal(hist, want_h)
    np.testing.assert_allclose(ssum, want_s, atol=1e-5)


def test_full_blocks_take_the_nearest_within_the_budget() -> None:
    distance = np.array([0.0, 5.0, 10.0, 100.0, 5.0])
    counts = np.array([3, 4, 0, 2, 1])
    # Shown blocks: 0, 1, 3, 4 (4 points). Block 0 at full resolution: 3 + 3 = 6 points; then block 1 (tie
    # at 5 m with block 4: the lower id first): 3 + 4 + 2 = 9; then block 4: 3 + 4 + 1 + 1 = 9.
    assert lod_plan.full_blocks(distance, counts, 20.0, 9).tolist() == [0, 1, 4]
    assert lod_plan.full_blocks(distance, counts, 20.0, 8).tolist() == [0]
    assert lod_plan.full_blocks(distance, counts, 20.0, 6).tolist() == [0]
    assert lod_plan.full_blocks(distance, counts, 20.0, 5).tolist() == []
    assert lod_plan.full_blocks(distance, counts, 2.0, 100).tolist() == [0]
    assert lod_plan.full_blocks(distance, counts, 200.0, 100).tolist() == [0, 1, 3, 4]


def test_footprint_distance_is_horizontal_and_zero_inside() -> None:
    lower = np.array([[0.0, 0.0, 50.0], [10.0, 0.0, 0.0], [-8.0, -8.0, 0.0]])
    d = lod_plan.footprint_distance(lower, 4.0, [2.0, 1.0, 0.0])
    np.testing.assert_allclose(d, [0.0, 8.0, math.hypot(6.0, 5.0)])


def _street(seed: int = 0, n: int = 30_000) -> tuple[np.ndarray, np.ndarray, float]:
    """A ground plane 160 m × 24 m with walls along both sides, at 0.25 m (voxels of a random share kept)."""
    rng = np.random.default_rng(seed)
    vs = 0.25
    gx, gy = np.meshgrid(np.arange(640), np.arange(96), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size, np.int64)], 1)
    wx, wz = np.meshgrid(np.arange(640), np.arange(1, 30), indexing="ij")
    walls = [np.stack([wx.ravel(), np.full(wx.size, y), wz.ravel()], 1) for y in (0, 95)]
    ijk = np.concatenate([ground, *walls])
    ijk = ijk[rng.choice(ijk.shape[0], n, replace=False)]
    keys = np.unique(voxel_keys((ijk + 0.5) * vs, vs))
    label = np.where(key_centres(keys, vs)[:, 2] > vs, 2, rng.integers(0, 2, keys.size)).astype(np.int16)
    return keys, label, vs


def test_sorted_tables_count_what_block_tables_count_and_follow_new_arrays() -> None:
    """The index's counting in sorted order (its sorted copies of label and score kept between calls) gives
    :func:`lod.block_tables` of the rows in grid order, for every threshold and after the arrays change."""
    keys, label, vs = _street()
    rng = np.random.default_rng(7)
    index = lod.build_index(key_centres(keys, vs), vs)
    blocks = index.blocks(index.overview_level(3000, 0.5))
    score = rng.random(keys.size).astype(np.float32)
    for lab, sc in ((label, score), (label, score), ((label + 1) % 3, score), (label, score[::-1].copy())):
        for thr in (0.0, 0.3, 0.9):
            want_h, want_s = lod.block_tables(
                blocks.of_row, blocks.count, lab, 3, keep=sc >= np.float32(thr) if thr > 0 else None, score=sc
            )
            for chunk in (1 << 16, 7, 1):  # one chunk, several, one block each
                got_h, got_s = index.sorted_tables(
                    blocks, lab, 3, threshold=thr, score=sc, chunk_blocks=chunk
                )
                assert got_s is not None and want_s is not None
                np.testing.assert_array_equal(got_h, want_h)
                np.testing.assert_allclose(got_s, want_s, rtol=1e-5)
    assert blocks.count > 7
    with pytest.raises(ValueError, match="threshold needs the score"):
        index.sorted_tables(blocks, label, 3, threshold=0.5)
    with pytest.raises(ValueError, match="chunk_blocks must be"):
        index.sorted_tables(blocks, label, 3, chunk_blocks=0)


def test_plan_respects_the_budget_and_keeps_every_voxel_near_the_focus() -> None:
    keys, label, vs = _street()
    centres = key_centres(keys, vs)
    index = lod.build_index(centres, vs)
    for budget, radius, focus, room in (
        (8000, 10.0, (20.0, 12.0, 0.0), True),
        (14000, 25.0, (150.0, 2.0, 0.0), True),
        (1500, 60.0, (80.0, 12.0, 0.0), False),
    ):
        blocks = index.blocks(index.overview_level(budget, 0.5))
        assert blocks.count <= budget // 2
        hist, _ = lod.block_tables(blocks.of_row, blocks.count, label, 3)
        counts = lod_plan.visible_counts(hist, lod_plan.enabled_columns((), 3))
        plan = lod_plan.plan_view(blocks, index.order, counts, focus, radius, budget)
        assert plan.rows.shape[0] + plan.blocks.shape[0] <= budget
        assert not np.isin(plan.blocks, plan.full).any()
        near = np.flatnonzero(np.hypot(*(centres[:, :2] - focus[:2]).T) <= radius)
        covered = np.isin(near, plan.rows)
        assert room == (near.size + blocks.count <= budget)
        if room:  # the whole disc fits: it is all at full resolution
            assert covered.all()
        else:  # the budget stops the disc: the nearest voxels still come first
            assert 0 < covered.mean() < 1
            d = np.hypot(*(centres[near, :2] - focus[:2]).T)
            assert d[covered].max() <= d[~covered].min() + blocks.edge * math.sqrt(2)
        # Every voxel is drawn exactly once: at full resolution or through its block.
        drawn_blocks = np.concatenate([plan.full, plan.blocks])
        assert np.unique(drawn_blocks).size == drawn_blocks.size
        assert set(drawn_blocks.tolist()) == set(range(blocks.count))


def _looking_at(target: np.ndarray, position: np.ndarray) -> tuple[float, ...]:
    fwd = (target - position) / np.linalg.norm(target - position)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return tuple(matrix_to_wxyz(np.stack([right, np.cross(fwd, right), fwd], axis=1)))


@pytest.mark.parametrize("depth_mode", ["front", "through"])
def test_culled_selection_equals_the_full_selection(depth_mode: str) -> None:
    keys, label, vs = _street(seed=1)
    centres = key_centres(keys, vs)
    index = lod.build_index(centres, vs)
    cubes = index.blocks(index.query_level(4.0))
    assert cubes.edge >= 4.0 and cubes.count > 10
    rng = np.random.default_rng(2)
    visible = rng.random(keys.size) < 0.9
    eligible = label == 2
    sizes = []
    for trial in range(6):
        target = np.array([rng.uniform(10, 150), rng.uniform(0, 24), 0.0])
        position = target + np.array([rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(8, 40)])
        camera = sel.PinholeCamera(tuple(position), _looking_at(target, position), math.radians(60), 320, 200)
        t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
        c, r = rng.uniform(0.3, 0.7, 2), rng.uniform(0.05, 0.25)
        mask = sel.polygon_mask(np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], 1), 320, 200)
        rows = np.flatnonzero(visible)
        filt = eligible[rows] if trial % 2 else None
        full = rows[
            sel.select_points(
                centres[rows], camera, mask, depth_mode=depth_mode, distance=0.5, splat_size=vs, eligible=filt
            )
        ]
        got = lod_cull.select_culled(
            index,
            cubes,
            camera,
            mask,
            visible=visible,
            eligible=eligible if trial % 2 else None,
            depth_mode=depth_mode,
            distance=0.5,
            splat_size=vs,
        )
        sizes.append(full.size)
        np.testing.assert_array_equal(got, full)
    assert sum(n > 0 for n in sizes) >= 4  # the lassos mostly catch something


def test_culled_selection_keeps_the_occluders_beside_the_lasso() -> None:
    # Ground at z = 0 seen from 60 m straight above (a voxel is 6.2 px wide, so is a z-buffer cell), a
    # platform 10 m high from x = 0.5 m: its first column projects to pixel 211, in the cell next to the
    # lasso's last ground column (pixel 203, rectangle edge 204), so the z-buffer's 3×3 erosion lets it
    # hide that column; culling must keep the platform although it lies farther outside the lasso's
    # rectangle (7.2 px) than the bounding spheres of its one-voxel cubes reach (6.5 px).
    vs = 0.5
    gx, gy = np.meshgrid(np.arange(-40, 40), np.arange(-40, 40), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size, np.int64)], 1)
    px, py = np.meshgrid(np.arange(1, 6), np.arange(-40, 40), indexing="ij")
    platform = np.stack([px.ravel(), py.ravel(), np.full(px.size, 20)], 1)
    centres = ((np.concatenate([ground, platform]) + 0.5) * vs).astype(np.float32)
    index = lod.build_index(centres, vs)
    from viser.transforms import SO3

    down = SO3.from_matrix(np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])).wxyz
    camera = sel.PinholeCamera((0.0, 0.0, 60.0), tuple(down), math.radians(30), 400, 400)
    mask = sel.rect_mask((0.3, 0.3), (0.51, 0.7), 400, 400)
    visible = np.ones(centres.shape[0], bool)
    full = sel.select_points(centres, camera, mask, depth_mode="front", distance=0.5, splat_size=vs)
    got = lod_cull.select_culled(
        index, index.blocks(0), camera, mask, visible=visible, depth_mode="front", distance=0.5, splat_size=vs
    )
    in_rect = sel.select_points(centres, camera, mask, depth_mode="through")
    assert 0 < full.sum() < in_rect.sum()  # the platform hides some of the ground the lasso covers
    np.testing.assert_array_equal(got, np.flatnonzero(full))


def test_frustum_culling_never_drops_a_point_in_the_rectangle() -> None:
    rng = np.random.default_rng(4)
    keys, _, vs = _street(seed=3)
    centres = key_centres(keys, vs)
    index = lod.build_index(centres, vs)
    cubes = index.blocks(index.query_level(4.0))
    for _ in range(10):
        target = np.array([rng.uniform(0, 160), rng.uniform(0, 24), 0.0])
        position = target + rng.uniform(-40, 40, 3) + [0, 0, 45]
        camera = sel.PinholeCamera(tuple(position), _looking_at(target, position), 1.0, 400, 300)
        lo, hi = tuple(rng.uniform(0, 0.5, 2)), tuple(rng.uniform(0.5, 1, 2))
        uv, front = sel.project_to_screen(centres, camera.position, camera.wxyz, camera.fov_y, camera.aspect)
        inside = front & (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1)
        kept = lod_cull.frustum_blocks(cubes.cube_centres, cubes.edge, camera, lo, hi)
        rows = lod.segment_rows(index.order, cubes.starts, np.flatnonzero(kept))
        assert np.isin(np.flatnonzero(inside), rows).all()
        assert rows.size < keys.size  # it culls something


def test_ray_rows_hold_the_voxel_a_click_picks() -> None:
    keys, _, vs = _street(seed=5)
    centres = key_centres(keys, vs)
    index = lod.build_index(centres, vs)
    cubes = index.blocks(index.query_level(4.0))
    rng = np.random.default_rng(6)
    for _ in range(10):
        origin = np.array([rng.uniform(0, 160), rng.uniform(-20, 40), 30.0])
        direction = centres[rng.integers(keys.size)] - origin
        full = pick_voxel(origin, direction, centres, vs)
        rows = lod_cull.ray_rows(index, cubes, origin, direction)
        assert rows.size < keys.size and np.all(np.diff(rows) > 0)
        culled = pick_voxel(origin, direction, centres[rows], vs)
        assert full is not None and culled is not None
        assert rows[culled.index] == full.index and culled.distance == full.distance


def test_thin_rows_marks_overview_voxels_by_their_block() -> None:
    index, centres = _hand_index()
    blocks = index.blocks(1)
    full = np.sort(blocks.of_row[[0]].astype(np.int64))  # the block of rows 0 and 1 is at full resolution
    pts = lod_cull.thin_rows(blocks, full, centres, np.array([0, 1, 2, 3]))
    # Rows 0 and 1 as themselves; rows 2 and 3 by their (one-voxel) blocks' means.
    np.testing.assert_allclose(pts, centres[[0, 1, 2, 3]])
    assert lod_cull.thin_rows(blocks, np.zeros(0, np.int64), centres, np.array([0, 1])).shape == (1, 3)


def test_lod_config_names_the_bad_field() -> None:
    with pytest.raises(ValueError, match="budget"):
        lod.LodConfig(budget=1)
    with pytest.raises(ValueError, match="overview_share"):
        lod.LodConfig(overview_share=1.0)


# ------------------------------------------------------------------ a real session on a big map
SCHEMA3 = {
    "name": "street",
    "classes": [
        {"name": "road", "color": [255, 0, 255], "prompts": ["road"], "export_id": 40},
        {"name": "sidewalk", "color": [75, 0, 75], "prompts": ["sidewalk"], "export_id": 48},
        {"name": "building", "color": [255, 200, 0], "prompts": ["building"], "export_id": 50},
    ],
}


@pytest.fixture
def big_store(tmp_path, make_tiny_sequence):
    """A project whose finished run's map (a 160 m street, ~30k voxels) is far above an 8000-point budget."""
    from app import crud
    from app.core.config import Settings
    from app.core.db import init_db, open_db

    settings = Settings(work_dir=tmp_path / "work", data_roots=[tmp_path], seed_demo=False)
    init_db(settings.database)
    seq = make_tiny_sequence(tmp_path / "data", n_frames=2, n_points=40)
    keys, label, vs = _street(seed=7)
    probs = np.full((keys.size, 3), 0.1, np.float32)
    probs[np.arange(keys.size), label] = 0.8
    with open_db(settings.database) as db:
        project = crud.create_project(
            db,
            name="street",
            dataset_kind="folder",
            sequences=[("00", str(seq.root))],
            schema=SCHEMA3,
            pipeline={"fusion": {"voxel_size": vs}},
        )
        params = run_params(SCHEMA3, seq.root)
        run = crud.create_run(db, project_id=project.id, params=params, runs_dir=settings.runs_dir)
        crud.update_run(db, run.id, status="done")
    run_dir = run.sequence_layout("00").folder
    run_dir.mkdir(parents=True)
    logp = np.log(probs).astype(np.float16)
    logp -= logp.max(axis=1, keepdims=True)
    VoxelGrid(keys=keys, logp=logp, voxel_size=vs).save(run_dir / "grid.npz")
    atomic_save_npz(run_dir / "grid_smooth.npz", keys=keys, probs=probs.astype(np.float16))
    return settings, project.id, keys, label, vs


def test_session_sends_at_most_the_budget_and_corrects_the_full_grid(big_store) -> None:
    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.records import SessionConfig
    from app.viewer.session import ReviewSession

    settings, pid, keys, _, _ = big_store
    budget = 8000
    config = SessionConfig(lod=lod.LodConfig(budget=budget, radius=6.0, refine_distance=5.0))
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel, config=config)
    try:
        assert session.renderer.wait_drawn() and session.renderer.lod_index is not None
        voxels, overview = session.scene.voxels.handle, session.scene.overview.handle
        assert voxels is not None and overview is not None

        def sent() -> int:
            assert voxels.points.shape[0] == voxels.colors.shape[0]
            assert overview.points.shape[0] == overview.colors.shape[0]
            return int(voxels.points.shape[0] + overview.points.shape[0])

        assert voxels.points.shape[0] > 0 and overview.points.shape[0] > 0 and sent() <= budget
        # The camera's look-at point moves far down the street: the full resolution follows it.
        far = np.array([150.0, 12.0, 0.0])
        session.renderer.camera_moved(far)
        assert session.renderer.wait_drawn() and sent() <= budget
        centres = session.grid.centres
        near = np.flatnonzero(np.hypot(*(centres[:, :2] - far[:2]).T) <= 6.0)
        assert 0 < near.size < budget / 2  # room for the whole disc beside the overview
        drawn = {tuple(p) for p in np.asarray(voxels.points).tolist()}
        assert all(tuple(centres[r].tolist()) in drawn for r in near)
        # Class toggle and colour switch keep the budget and the handles (updated in place).
        session.renderer.set_class_enabled(0, False)
        session.set_state(mode="confidence")
        assert session.renderer.wait_drawn() and sent() <= budget
        assert session.scene.voxels.handle is voxels and session.scene.overview.handle is overview
        session.renderer.set_class_enabled(0, True)
        session.set_state(mode="class")
        assert session.renderer.wait_drawn()

        # A box looking straight down at the street's other end, drawn only as overview blocks there.
        from viser.transforms import SO3

        area = np.array([20.0, 12.0, 0.0])
        down = SO3.from_matrix(np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])).wxyz
        fov = 2 * math.atan(15.0 / 100.0)
        above = area + np.array([0, 0, 100.0])
        uv, front = vl.project_to_screen(centres, above, down, fov, 1.0)
        expected = np.flatnonzero(front & (uv >= 0).all(axis=1) & (uv <= 1).all(axis=1))
        plan = session.renderer.lod_plan
        assert not np.isin(expected, plan.rows).any()  # nothing there is at full resolution
        overview_pts = np.asarray(overview.points)
        shown_there = int((np.abs(overview_pts[:, 0] - area[0]) <= 16).sum())
        session.tools.set_tools(depth_mode="through")
        n = session.tools.select_rect(above, down, fov, 1.0, (0.0, 0.0), (1.0, 1.0))
        assert n == expected.size > 10 * shown_there  # every voxel under the box, not the drawn blocks
        np.testing.assert_array_equal(session.tools.selection.rows, expected)
        assert session.scene.selection.count <= budget
        cid = session.corrections.assign_selection("building")
        assert cid is not None and session.renderer.wait_drawn()
        with open_db(settings.database) as db:
            (corr,) = crud.list_corrections(db, pid)
        np.testing.assert_array_equal(corr.keys, keys[expected])
        assert (session.label[expected] == 2).all() and session.corrected.sum() == expected.size
        assert sent() <= budget
        # The overview shows the correction too: the blocks under the box are now building-coloured.
        bcols = np.asarray(overview.colors)[np.abs(np.asarray(overview.points)[:, 0] - area[0]) <= 12]
        assert bcols.size and (bcols == SCHEMA3["classes"][2]["color"]).all()
        # A small correction moves its voxels in the block tables instead of recounting: same tables.
        fov_small = 2 * math.atan(3.0 / 100.0)
        beside = above + np.array([40.0, 0, 0])
        n_small = session.tools.select_rect(beside, down, fov_small, 1.0, (0.0, 0.0), (1.0, 1.0))
        assert 0 < n_small < keys.size // 20
        # With a threshold the corrected voxels (confidence 0.8 -> 1) also enter the count.
        session.set_state(threshold=0.9)
        assert session.renderer.wait_drawn()
        session.corrections.assign_selection("sidewalk")
        assert session.renderer.wait_drawn()
        cached = session.renderer.cache.tables
        assert cached is not None
        blocks = cached[0][0]
        want_h, want_s = lod.block_tables(
            blocks.of_row, blocks.count, session.label, 3, keep=session.conf >= 0.9, score=session.conf
        )
        np.testing.assert_array_equal(cached[1], want_h)
        np.testing.assert_allclose(cached[2], want_s, atol=1e-3)
        # With the overview drawn (threshold 0), a small correction recolours only the blocks it touched:
        # the kept overview colours are a recount's.
        session.set_state(threshold=0.0)
        assert session.renderer.wait_drawn()
        assert (
            0
            < session.tools.select_rect(
                beside + np.array([-8.0, 0, 0]), down, fov_small, 1.0, (0.0, 0.0), (1.0, 1.0)
            )
            < keys.size // 20
        )
        session.corrections.assign_selection("road")
        assert session.renderer.wait_drawn()
        tables, kept = session.renderer.cache.tables, session.renderer.cache.colors
        assert tables is not None and kept is not None and kept[0][0] is tables[1]
        want_h, _ = lod.block_tables(blocks.of_row, blocks.count, session.label, 3)
        np.testing.assert_array_equal(tables[1], want_h)
        columns = lod_plan.enabled_columns(session.state.enabled, 3)
        want_colors = vl.class_colors(lod_plan.majority_class(want_h, columns), session.palette)
        np.testing.assert_array_equal(kept[1], want_colors)
        # "Limit points" below the budget: the full-resolution disc shrinks to what fits.
        session.set_state(max_points=1000, threshold=0.0)
        assert session.renderer.wait_drawn() and 900 < sent() <= 1000
        assert session.scene.voxels.count > 0 and session.scene.overview.count > 0
    finally:
        session.close()


def test_small_map_is_drawn_exactly(big_store) -> None:
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.records import SessionConfig
    from app.viewer.session import ReviewSession

    settings, pid, keys, label, _ = big_store
    config = SessionConfig(lod=lod.LodConfig(budget=keys.size))
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel, config=config)
    try:
        assert session.renderer.wait_drawn() and session.renderer.lod_index is None
        assert session.scene.voxels.count == keys.size and session.scene.overview.handle is None
        rows, colors = session.renderer.compute_view()
        np.testing.assert_array_equal(session.scene.voxels.handle.points, session.grid.centres[rows])
        np.testing.assert_array_equal(
            colors, vl.class_colors(label, np.array([c["color"] for c in SCHEMA3["classes"]], np.uint8))
        )
    finally:
        session.close()
