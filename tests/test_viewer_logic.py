"""View logic of the review viewer: hand-computed colour maps, thresholds, corrections, selection,
review regions, label overlays, undo/redo, run loading, and the scene facade on a real viser server."""

from __future__ import annotations

import math
import socket
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from runhelpers import run_params

from app.viewer import region_logic as rl
from app.viewer import view_logic as vl
from app.viewer.data import ReviewGrid, RunOutputs, matrix_to_wxyz
from app.viewer.panel import legend_html
from leap_core.fusion import VoxelGrid, key_centres, voxel_keys
from leap_core.io_utils import atomic_save_npz


# ------------------------------------------------------------------------------------------ colours
def test_make_lut_interpolates_between_anchors() -> None:
    lut = vl.make_lut([(0, 0, 0), (200, 100, 50)], size=3)
    assert lut.tolist() == [[0, 0, 0], [100, 50, 25], [200, 100, 50]]
    lut3 = vl.make_lut([(0, 0, 0), (100, 0, 0), (100, 100, 0)], size=5)
    # t = 0, .5, 1, 1.5, 2 anchor units.
    assert lut3.tolist() == [[0, 0, 0], [50, 0, 0], [100, 0, 0], [100, 50, 0], [100, 100, 0]]


def test_make_lut_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="anchors"):
        vl.make_lut([(0, 0, 0)])
    with pytest.raises(ValueError, match="size"):
        vl.make_lut(size=1)


def test_scalar_colors_rounds_clips_and_maps_nan_low() -> None:
    lut = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2]], np.uint8)
    v = np.array([0.0, 0.24, 0.26, 0.5, 0.74, 0.76, 1.0, 2.0, -1.0, np.nan])
    # index = floor(v * 2 + 0.5), clipped to [0, 2]
    assert vl.scalar_colors(v, lut)[:, 0].tolist() == [0, 0, 1, 1, 1, 2, 2, 2, 0, 0]
    assert vl.scalar_colors([5.0], lut, vmin=4.0, vmax=6.0)[:, 0].tolist() == [1]
    with pytest.raises(ValueError, match="vmax"):
        vl.scalar_colors([0.0], lut, vmin=1.0, vmax=1.0)


def test_class_colors_maps_unlabeled_to_grey() -> None:
    palette = np.array([[255, 0, 0], [0, 255, 0]], np.uint8)
    out = vl.class_colors(np.array([1, -1, 0], np.int16), palette)
    assert out.tolist() == [[0, 255, 0], list(vl.UNLABELED_RGB), [255, 0, 0]]
    with pytest.raises(ValueError, match="labels must lie"):
        vl.class_colors(np.array([2]), palette)


def test_legend_escapes_class_names() -> None:
    palette = np.array([[1, 2, 3]], np.uint8)
    html = legend_html("class", ["<b>car</b>"], palette)
    assert "&lt;b&gt;car&lt;/b&gt;" in html and "<b>car" not in html
    assert "#010203" in html
    assert "P(&lt;x&gt;)" in legend_html("class_probability", ["a"], palette, "<x>")


# ----------------------------------------------------------------------------------- visibility
def test_visible_mask_threshold_and_toggles() -> None:
    label = np.array([0, 1, 2, -1, 1], np.int16)
    score = np.array([0.9, 0.4, 0.6, 0.8, 0.5], np.float32)
    assert vl.visible_mask(label, score, 0.0).all()
    assert vl.visible_mask(label, score, 0.5).tolist() == [True, False, True, True, True]
    some_on = vl.visible_mask(label, score, 0.5, (True, False, True))
    assert some_on.tolist() == [True, False, True, True, False]
    all_off = vl.visible_mask(label, score, 0.0, (False, False, False))
    assert all_off.tolist() == [False, False, False, True, False]


def test_decimate_indices_is_an_even_stride() -> None:
    idx = np.arange(10, 20)
    assert vl.decimate_indices(idx, None).tolist() == idx.tolist()
    assert vl.decimate_indices(idx, 20).tolist() == idx.tolist()
    assert vl.decimate_indices(idx, 5).tolist() == [10, 12, 14, 16, 18]
    assert vl.decimate_indices(idx, 0).tolist() == []


def test_view_colors_and_score_per_mode() -> None:
    label = np.array([0, 1], np.int16)
    conf = np.array([1.0, 0.0], np.float32)
    prob = np.array([0.0, 1.0], np.float32)
    palette = np.array([[10, 20, 30], [40, 50, 60]], np.uint8)
    rows = np.array([1, 0])
    assert vl.view_colors(vl.ViewState("class"), label, conf, None, palette, rows).tolist() == [
        [40, 50, 60],
        [10, 20, 30],
    ]
    conf_cols = vl.view_colors(vl.ViewState("confidence"), label, conf, None, palette, rows)
    assert conf_cols.tolist() == [vl.CONFIDENCE_LUT[0].tolist(), vl.CONFIDENCE_LUT[-1].tolist()]
    st_p = vl.ViewState("class_probability", class_index=1)
    prob_cols = vl.view_colors(st_p, label, conf, prob, palette, rows)
    assert prob_cols[0].tolist() == vl.CONFIDENCE_LUT[-1].tolist()
    assert vl.view_score(st_p, conf, prob) is prob
    assert vl.view_score(vl.ViewState("class"), conf, prob) is conf
    with pytest.raises(ValueError, match="class_probability"):
        vl.view_score(st_p, conf, None)


# ---------------------------------------------------------------------------------- corrections
def test_apply_corrections_latest_wins_and_inputs_untouched() -> None:
    keys = np.array([3, 5, 9, 12], np.int64)
    label = np.array([0, 0, 1, 1], np.int16)
    conf = np.array([0.5, 0.6, 0.7, 0.8], np.float32)
    new_label, new_conf, corrected = vl.apply_corrections(keys, label, conf, [9, 4, 5, 9], [2, 1, 1, 0])
    assert new_label.tolist() == [0, 1, 0, 1]  # key 9: 2 then 0 → 0; key 4 is not in the grid
    assert new_conf.tolist() == pytest.approx([0.5, 1.0, 1.0, 0.8])
    assert corrected.tolist() == [False, True, True, False]
    assert label.tolist() == [0, 0, 1, 1] and conf.tolist() == pytest.approx([0.5, 0.6, 0.7, 0.8])
    empty = vl.apply_corrections(keys, label, conf, [], [])
    assert not empty[2].any()
    with pytest.raises(ValueError, match="same length"):
        vl.apply_corrections(keys, label, conf, [1, 2], [0])


# ---------------------------------------------------------------------------- camera and selection
@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1
    )
)
def test_quat_to_matrix_matches_viser(q: list[float]) -> None:
    from viser.transforms import SO3

    wxyz = np.asarray(q) / np.linalg.norm(q)
    np.testing.assert_allclose(vl.quat_to_matrix(wxyz), SO3(wxyz).as_matrix(), atol=1e-9)
    back = matrix_to_wxyz(vl.quat_to_matrix(wxyz))
    assert min(np.abs(back - wxyz).max(), np.abs(back + wxyz).max()) < 1e-9


def test_project_to_screen_identity_camera() -> None:
    fov = math.radians(90.0)  # tan(fov/2) = 1
    pts = np.array([[0, 0, 5], [10, 0, 5], [0, -5, 5], [0, 0, -5], [2.5, 2.5, 5]], np.float64)
    uv, front = vl.project_to_screen(pts, (0, 0, 0), (1, 0, 0, 0), fov, aspect=2.0)
    assert front.tolist() == [True, True, True, False, True]
    # u = .5 + .5·(x/z)/(aspect·1), v = .5 + .5·(y/z)
    np.testing.assert_allclose(
        uv[[0, 1, 2, 4]], [[0.5, 0.5], [1.0, 0.5], [0.5, 0.0], [0.625, 0.75]], atol=1e-12
    )


def test_select_in_rect_from_a_look_at_camera() -> None:
    """A camera built the way viser builds it from look_at (OpenCV axes) sees points where expected."""
    from viser.transforms import SO3

    position = np.array([0.0, -10.0, 0.0])
    forward = np.array([0.0, 1.0, 0.0])  # looking along +y, z up → screen up is +z
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, forward)
    wxyz = SO3.from_matrix(np.stack([right, down, forward], axis=1)).wxyz
    pts = np.array([[0, 0, 0], [3, 0, 0], [0, 0, 3], [0, -20, 0]], np.float64)
    uv, front = vl.project_to_screen(pts, position, wxyz, math.radians(90), 1.0)
    np.testing.assert_allclose(uv[:3], [[0.5, 0.5], [0.65, 0.5], [0.5, 0.35]], atol=1e-12)
    assert front.tolist() == [True, True, True, False]
    fov = math.radians(90)
    sel = vl.select_in_rect(pts, position, wxyz, fov, 1.0, rect_min=(0.6, 0.6), rect_max=(0.4, 0.4))
    assert sel.tolist() == [True, False, False, False]
    sel = vl.select_in_rect(pts, position, wxyz, fov, 1.0, rect_min=(0.55, 0.4), rect_max=(0.7, 0.6))
    assert sel.tolist() == [False, True, False, False]


def test_orbit_view() -> None:
    pos, tgt = vl.orbit_view((1, 2, 3), 2.0, elevation_deg=90.0)
    np.testing.assert_allclose(pos, [1, 2, 5], atol=1e-12)
    assert tgt.tolist() == [1, 2, 3]


# ------------------------------------------------------------------------------------ review queue
def test_rank_regions_orders_cells_by_mean_score() -> None:
    centres = np.array(
        [[0.5, 0.5, 0], [1.5, 0.5, 0], [10.5, 0, 0], [11, 1, 0], [11.5, 0.5, 0], [30, 30, 0]], np.float32
    )
    score = np.array([0.25, 0.75, 0.0, 1.0, 0.5, 0.0], np.float32)
    cand = np.array([True, True, True, True, True, False])
    regions = rl.rank_regions(centres, score, cand, cell_size=4.0)
    assert [r.count for r in regions] == [3, 2]  # both cells average 0.5: the larger one first
    assert regions[0].score == 0.5 and regions[1].score == 0.5
    regions = rl.rank_regions(centres, score, cand, cell_size=4.0, min_count=3)
    assert len(regions) == 1 and regions[0].centre == pytest.approx((11.0, 0.5, 0.0))
    assert regions[0].extent == pytest.approx(math.hypot(0.5, 0.5))
    cand2 = np.array([True, True, True, False, False, False])
    lowest = rl.rank_regions(centres, score, cand2, 4.0)
    assert [r.score for r in lowest] == [0.0, 0.5]
    highest = rl.rank_regions(centres, score, cand2, 4.0, ascending=False)
    assert [r.score for r in highest] == [0.5, 0.0]
    assert rl.rank_regions(centres, score, np.zeros(6, bool), 4.0) == []
    with pytest.raises(ValueError, match="cell_size"):
        rl.rank_regions(centres, score, cand, 0.0)


def test_lowest_share() -> None:
    s = np.array([0.5, 0.1, 0.9, 0.3, 0.7], np.float32)
    assert rl.lowest_share(s, 0.4).tolist() == [False, True, False, True, False]
    assert rl.lowest_share(s, 0.01).tolist() == [False, True, False, False, False]
    assert rl.lowest_share(s, 1.0).all()
    with pytest.raises(ValueError, match="share"):
        rl.lowest_share(s, 0.0)


def test_disagreement_rate() -> None:
    rows = np.array([0, 0, 0, 1, 1, -1, 2], np.int64)
    cam = np.array([1, 1, -1, 2, 2, 1, -1], np.int16)
    fin = np.array([1, 0, 0, 2, 2, 0, 1], np.int16)
    rate, observed = rl.disagreement_rate(rows, cam, fin, 4)
    assert observed.tolist() == [2, 2, 0, 0]
    np.testing.assert_allclose(rate, [0.5, 0.0, 0.0, 0.0])


# ------------------------------------------------------------------------------------------ overlay
def test_draw_label_overlay_nearest_wins_and_unlabeled_skipped() -> None:
    img = np.zeros((5, 5, 3), np.uint8)
    palette = np.array([[100, 0, 0], [0, 200, 0]], np.uint8)
    uv = np.array([[2, 2], [2.4, 1.6], [0, 0], [4, 4]])
    out = vl.draw_label_overlay(
        img, uv, [0, 1, -1, 1], palette, radius=0, alpha=1.0, depth=[5.0, 3.0, 1.0, 9.0]
    )
    assert img.sum() == 0  # input untouched
    assert out[2, 2].tolist() == [0, 200, 0]  # both land on (2, 2): the nearer (depth 3) wins
    assert out[0, 0].tolist() == [0, 0, 0]  # unlabeled is not drawn
    assert out[4, 4].tolist() == [0, 200, 0]
    assert int((out.sum(axis=2) > 0).sum()) == 2
    # Without depth the later point wins; radius 1 paints a clipped 3×3 square; alpha blends.
    grey = np.full((5, 5, 3), 100, np.uint8)
    out = vl.draw_label_overlay(grey, [[0, 0]], [1], palette, radius=1, alpha=0.5)
    assert out[0, 0].tolist() == [50, 150, 50] and out[1, 1].tolist() == [50, 150, 50]
    assert out[2, 2].tolist() == [100, 100, 100]


# ------------------------------------------------------------------------------------ undo / redo
def test_edit_history() -> None:
    h: vl.EditHistory[int] = vl.EditHistory(limit=3)
    assert h.undo() is None and h.redo() is None and not h.can_undo
    for e in (1, 2, 3):
        h.push(e)
    assert h.undo() == 3 and h.undo() == 2
    assert h.can_redo and h.redo() == 2
    h.push(4)  # a new edit drops the redo stack
    assert not h.can_redo and h.redo() is None
    assert [h.undo(), h.undo(), h.undo()] == [4, 2, 1]
    h.push(5)
    h.push(6)
    h.push(7)
    h.push(8)  # limit 3: the oldest falls off
    assert len(h) == 3 and [h.undo(), h.undo(), h.undo(), h.undo()] == [8, 7, 6, None]


# ------------------------------------------------------------------------------------- run loading
def _write_grid(run_dir, keys, probs, voxel_size=0.5, smooth=True):
    logp = np.log(np.clip(probs, 1e-9, 1)).astype(np.float16)
    logp -= logp.max(axis=1, keepdims=True)
    VoxelGrid(keys=keys, logp=logp, voxel_size=voxel_size).save(run_dir / "grid.npz")
    if smooth:
        atomic_save_npz(run_dir / "grid_smooth.npz", keys=keys, probs=probs.astype(np.float16))


def test_review_grid_loads_final_or_fused(tmp_path) -> None:
    xyz = np.array([[0.1, 0.1, 0.1], [1.2, 0.1, 0.1], [0.1, 2.3, 0.1]])
    keys = np.sort(voxel_keys(xyz, 0.5))
    probs = np.array([[0.7, 0.2, 0.1], [0.1, 0.1, 0.8], [0.4, 0.5, 0.1]], np.float32)
    _write_grid(tmp_path, keys, probs, smooth=False)
    g = ReviewGrid.load(tmp_path)
    assert g.source.endswith("grid.npz") and g.voxel_size == 0.5
    assert g.label.tolist() == [0, 2, 1]
    np.testing.assert_allclose(g.conf, [0.7, 0.8, 0.5], atol=2e-3)
    np.testing.assert_allclose(g.centres, key_centres(keys, 0.5))
    np.testing.assert_allclose(g.class_prob(2), [0.1, 0.8, 0.1], atol=2e-3)
    assert g.class_prob(2) is g.class_prob(2)
    assert g.rows_of([keys[1], 12345]).tolist() == [1, -1]
    smooth = np.array([[0.1, 0.8, 0.1], [0.1, 0.1, 0.8], [0.6, 0.3, 0.1]], np.float32)
    atomic_save_npz(tmp_path / "grid_smooth.npz", keys=keys, probs=smooth.astype(np.float16))
    g = ReviewGrid.load(tmp_path)
    assert g.source.endswith("grid_smooth.npz") and g.label.tolist() == [1, 2, 0] and g.voxel_size == 0.5


def test_review_grid_errors_name_the_file(tmp_path) -> None:
    from leap_core.errors import DatasetError

    with pytest.raises(DatasetError, match="has no voxel grid"):
        ReviewGrid.load(tmp_path)
    unsorted_keys = np.array([2, 1], np.int64)
    atomic_save_npz(tmp_path / "grid_smooth.npz", keys=unsorted_keys, probs=np.ones((2, 2), np.float16))
    with pytest.raises(DatasetError, match=r"grid_smooth\.npz: no voxel_size"):
        ReviewGrid.load(tmp_path)
    atomic_save_npz(
        tmp_path / "grid_smooth.npz",
        keys=unsorted_keys,
        probs=np.ones((2, 2), np.float16),
        voxel_size=np.float64(0.2),
    )
    with pytest.raises(DatasetError, match="not sorted"):
        ReviewGrid.load(tmp_path)
    (tmp_path / "grid_smooth.npz").write_bytes(b"junk")
    with pytest.raises(DatasetError, match=r"grid_smooth\.npz"):
        ReviewGrid.load(tmp_path)


def test_run_outputs_scan_view_and_disagreement(tmp_path, make_tiny_sequence) -> None:
    seq = make_tiny_sequence(tmp_path / "data", n_frames=2, n_points=40)
    run_dir = tmp_path / "run"
    outputs_seq = RunOutputs.__new__(RunOutputs)  # only to reuse world_points before outputs exist
    from leap_core.datasets.kitti import KittiSequence

    outputs_seq.seq = KittiSequence(seq.root)
    world = [outputs_seq.world_points(i) for i in range(2)]
    keys = np.unique(voxel_keys(np.concatenate(world), 0.5))
    probs = np.tile(np.array([[0.6, 0.3, 0.1]], np.float32), (keys.size, 1))
    run_dir.mkdir()
    _write_grid(run_dir, keys, probs)
    final = [np.zeros(40, np.int16), np.zeros(40, np.int16)]
    cam = [np.full(40, -1, np.int16), np.zeros(40, np.int16)]
    cam[1][:10] = 1  # 10 camera labels disagree with the final label 0
    atomic_save_npz(run_dir / "points" / f"{seq.frame_ids[0]}.npz", label=final[0], point_label=cam[0])
    atomic_save_npz(run_dir / "points" / f"{seq.frame_ids[1]}.npz", label=final[1], point_label=cam[1])
    out = RunOutputs(run_dir, seq.root)
    assert out.frame_indices == [0, 1]
    palette = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    view = out.scan_view(1, palette)
    np.testing.assert_allclose(view.points, world[1], atol=1e-5)
    assert view.label.tolist() == final[1].tolist()
    assert view.overlay is not None and view.overlay.shape == (48, 64, 3)
    assert (view.overlay == [255, 0, 0]).all(axis=2).sum() == 0  # alpha < 1 blends, never pure
    assert view.aspect == pytest.approx(64 / 48) and view.fov_y == pytest.approx(2 * math.atan(24 / 50))
    cam_to_world = out.seq.poses[1] @ np.linalg.inv(seq.calib.Tr)
    np.testing.assert_allclose(view.cam_position, cam_to_world[:3, 3])
    np.testing.assert_allclose(vl.quat_to_matrix(view.cam_wxyz), cam_to_world[:3, :3], atol=1e-9)
    grid = ReviewGrid.load(run_dir)
    rate, observed = out.disagreement(grid)
    assert observed.sum() == 40  # only frame 1 has camera labels
    rows = grid.rows_of(voxel_keys(world[1], 0.5))
    expected = np.bincount(rows[:10], minlength=grid.num_voxels) / np.maximum(observed, 1)
    np.testing.assert_allclose(rate, expected, atol=1e-6)
    assert out.disagreement(grid)[0] is rate  # cached


# ------------------------------------------------------------------------------------- scene facade
def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_scene_updates_handles_in_place_and_frees_its_port() -> None:
    from app.viewer.scene import ReviewScene

    scene = ReviewScene(port=0)
    try:
        port = scene.port
        assert port > 0 and scene.host == "127.0.0.1"
        pts = np.array([[0, 0, 0], [1000.01, 2, 3]], np.float32)
        cols = np.array([[1, 2, 3], [4, 5, 6]], np.uint8)
        scene.voxels.set(pts, cols)
        handle = scene.voxels.handle
        assert handle is not None and handle.points.dtype == np.float32
        np.testing.assert_array_equal(handle.points, pts)  # float32 keeps the centimetre at 1 km
        scene.voxels.set(pts[:1], cols[:1])
        assert scene.voxels.handle is handle and scene.voxels.count == 1
        assert handle.points.shape == (1, 3) and handle.colors.tolist() == [[1, 2, 3]]
        scene.voxels.set_colors(np.array([[9, 9, 9]], np.uint8))
        assert handle.colors.tolist() == [[9, 9, 9]]
        with pytest.raises(ValueError, match="needs 1 colours"):
            scene.voxels.set_colors(cols)
        with pytest.raises(ValueError, match="must both be"):
            scene.voxels.set(pts, cols[:1])
        scene.camera.set(
            position=(0, 0, 0), wxyz=(1, 0, 0, 0), fov_y=1.0, aspect=2.0, image=np.zeros((4, 8, 3), np.uint8)
        )
        frustum = scene.camera.handle
        scene.camera.set(position=(1, 0, 0), wxyz=(1, 0, 0, 0), fov_y=0.5, aspect=2.0, image=None)
        assert scene.camera.handle is frustum and frustum.fov == 0.5
    finally:
        scene.stop()
    assert _port_free(port)


def test_render_view_treats_corrected_voxels_as_certain() -> None:
    label = np.array([0, 1, 1], np.int16)
    conf = np.array([0.9, 0.8, 1.0], np.float32)
    prob1 = np.array([0.05, 0.8, 0.3], np.float32)  # voxel 2 was corrected to class 1
    corrected = np.array([False, False, True])
    palette = np.array([[1, 1, 1], [2, 2, 2]], np.uint8)
    state = vl.ViewState("class_probability", class_index=1, threshold=0.5)
    rows, cols = vl.render_view(state, label, conf, palette, prob1, corrected)
    assert rows.tolist() == [1, 2]
    assert cols[1].tolist() == vl.CONFIDENCE_LUT[-1].tolist()
    rows, _ = vl.render_view(vl.ViewState("class", threshold=0.85, max_points=1), label, conf, palette)
    assert rows.tolist() == [0]


# --------------------------------------------------------------- a session on the app's real SQLite store
SCHEMA3 = {
    "name": "tiny",
    "classes": [
        {"name": "road", "color": [255, 0, 255], "prompts": ["road"], "export_id": 40},
        {"name": "car", "color": [100, 150, 245], "prompts": ["car"], "export_id": 10},
        {"name": "building", "color": [255, 200, 0], "prompts": ["building"], "export_id": 50},
    ],
}


@pytest.fixture
def review_store(tmp_path, make_tiny_sequence):
    """A project with one finished run whose outputs are built by hand on a tiny sequence."""
    from app import crud
    from app.core.config import Settings
    from app.core.db import init_db, open_db
    from leap_core.datasets.kitti import KittiSequence

    settings = Settings(work_dir=tmp_path / "work", data_roots=[tmp_path], seed_demo=False)
    init_db(settings.database)
    seq = make_tiny_sequence(tmp_path / "data", n_frames=3, n_points=60)
    kseq = KittiSequence(seq.root)
    world = [
        (p[:, :3].astype(np.float64) @ kseq.poses[i][:3, :3].T + kseq.poses[i][:3, 3])
        for i, p in enumerate(seq.points)
    ]
    keys = np.unique(voxel_keys(np.concatenate(world), 0.5))
    centres = key_centres(keys, 0.5)
    # Class by height: low = road, middle = car, high = building; confidence grows with |y|.
    cls = np.digitize(centres[:, 2], [-1.0, 0.0]).astype(np.int64)
    conf = 0.55 + 0.4 * np.clip(np.abs(centres[:, 1]) / 6.0, 0, 1)
    probs = np.full((keys.size, 3), 0.0, np.float32)
    probs[np.arange(keys.size), cls] = conf
    probs[np.arange(keys.size), (cls + 1) % 3] = 1.0 - conf
    with open_db(settings.database) as db:
        project = crud.create_project(
            db,
            name="tiny <b>",
            dataset_kind="folder",
            sequences=[("00", str(seq.root))],
            schema=SCHEMA3,
            pipeline={"fusion": {"voxel_size": 0.5}},
        )
        # The sequences every run the app queues lists: the viewer shows a run only over the sequences it
        # labeled (app.rows.labeled_sequences).
        run = crud.create_run(
            db, project_id=project.id, params=run_params(SCHEMA3, seq.root), runs_dir=settings.runs_dir
        )
        crud.update_run(db, run.id, status="done")
    run_dir = run.sequence_layout("00").folder
    run_dir.mkdir(parents=True)
    _write_grid(run_dir, keys, probs, voxel_size=0.5)
    for i, fid in enumerate(seq.frame_ids):
        rows = np.searchsorted(keys, voxel_keys(world[i], 0.5))
        label = cls[rows].astype(np.int16)
        point_label = np.where(np.arange(60) % 3 == 0, (label + 1) % 3, label).astype(np.int16)
        atomic_save_npz(
            run_dir / "points" / f"{fid}.npz",
            label=label,
            point_label=point_label,
            conf=conf[rows].astype(np.float16),
        )
    return settings, project.id, run.id, keys, cls


def test_session_shows_edits_and_corrects_through_the_store(review_store) -> None:
    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.records import SessionConfig
    from app.viewer.session import ReviewSession

    settings, pid, run_id, keys, cls = review_store
    session = ReviewSession(
        AppBackend(settings, pid), panel=ReviewPanel, config=SessionConfig(queue_share=0.2, queue_min_count=1)
    )
    try:
        assert session.run is not None and session.run.run_id == run_id
        assert session.class_names() == ["road", "car", "building"]
        assert session.renderer.wait_drawn()
        handle = session.scene.voxels.handle
        assert handle is not None and handle.points.shape[0] == keys.size
        np.testing.assert_array_equal(handle.colors, np.array(SCHEMA3_COLORS)[cls])

        session.set_state(threshold=0.7)
        assert session.renderer.wait_drawn()
        assert session.scene.voxels.handle is handle  # updated in place
        assert handle.points.shape[0] == int((session.conf >= 0.7).sum()) < keys.size

        session.set_state(mode="class_probability", class_index=1, threshold=0.0)
        assert session.renderer.wait_drawn()
        expected = vl.scalar_colors(session.grid.class_prob(1))
        np.testing.assert_array_equal(handle.colors, expected)

        # Scan browser: points, frustum and label overlay of the second scan.
        view = session.player.show_scan(1)
        assert view is not None and session.scene.scan.count == 60
        assert session.scene.camera.handle is not None and view.overlay is not None

        # Review queue: the regions expected to hold the most wrong voxels first; the camera goes there.
        regions = session.queue.build_queue("confidence")
        assert regions and all(a.expected_wrong >= b.expected_wrong for a, b in pairwise(regions))
        assert session.queue.next_region() == regions[0]
        session.queue.clear_focus()
        dis = session.queue.build_queue("disagreement")
        assert dis and all(a.expected_wrong >= b.expected_wrong for a, b in pairwise(dis))

        # Steering: a renamed, recoloured, re-prompted class lands in the project's SQLite row.
        session.classes.update_class(1, name="vehicle", color=(1, 2, 3), prompts=["car", "van"])
        with open_db(settings.database) as db:
            stored = crud.require_project(db, pid).schema["classes"][1]
        assert stored["name"] == "vehicle" and stored["color"] == [1, 2, 3]
        assert stored["prompts"] == ["car", "van"]
        session.classes.add_class("pole")
        session.classes.remove_class(0)
        with open_db(settings.database) as db:
            names = [c["name"] for c in crud.require_project(db, pid).schema["classes"]]
        assert names == ["vehicle", "building", "pole"]
        with pytest.raises(Exception, match="duplicate name"):
            session.classes.update_class(0, name="building")

        # Corrections: select with a camera looking straight down on everything, assign, undo, redo.
        session.set_state(mode="class", threshold=0.0)
        assert session.renderer.wait_drawn()
        centre = session.grid.centres.mean(axis=0)
        from viser.transforms import SO3

        down = SO3.from_matrix(np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])).wxyz
        above = centre + np.array([0, 0, 200.0])
        session.tools.set_tools(depth_mode="through")
        n = session.tools.select_rect(above, down, math.radians(60), 1.0, (0.0, 0.0), (1.0, 1.0))
        assert n == keys.size
        cid = session.corrections.assign_selection("building")
        assert cid is not None and session.renderer.wait_drawn()
        with open_db(settings.database) as db:
            (corr,) = crud.list_corrections(db, pid)
        assert corr.class_name == "building" and corr.voxel_size == 0.5
        np.testing.assert_array_equal(corr.keys, keys)
        assert (session.label == 2).all() and session.corrected.all()
        np.testing.assert_array_equal(handle.colors[0], SCHEMA3_COLORS[2])
        session.corrections.undo()
        assert session.renderer.wait_drawn() and not session.corrected.any()
        with open_db(settings.database) as db:
            assert crud.list_corrections(db, pid) == []
        np.testing.assert_array_equal(session.label, cls)
        session.corrections.redo()
        assert session.renderer.wait_drawn() and session.corrected.all()
        with open_db(settings.database) as db:
            assert len(crud.list_corrections(db, pid)) == 1
    finally:
        session.close()


SCHEMA3_COLORS = [c["color"] for c in SCHEMA3["classes"]]


def test_viewer_api_and_authenticated_relay(review_store) -> None:
    import viser
    from fastapi.testclient import TestClient
    from starlette.testclient import WebSocketDenialResponse
    from starlette.websockets import WebSocketDisconnect

    from app.core.config import Settings
    from app.main import create_app

    settings, pid, run_id, keys, _ = review_store
    token = "correct-horse-battery"
    settings = Settings(
        work_dir=settings.work_dir, data_roots=settings.data_roots, seed_demo=False, access_token=token
    )
    app = create_app(settings)
    with TestClient(app) as client:
        base = f"/api/v1/projects/{pid}/viewer"
        assert client.post(base).status_code == 403
        auth = {"Authorization": f"Bearer {token}"}
        assert client.post("/api/v1/projects/999/viewer", headers=auth).status_code == 404
        assert client.post(base, json={"run_id": 0}, headers=auth).status_code == 422
        assert client.get(base, headers=auth).status_code == 404
        r = client.post(base, headers=auth)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["run_id"] == run_id and body["port"] > 0
        assert body["url"] == f"/api/v1/projects/{pid}/viewer/tabs/{body['tab']}/client/"
        assert "direct_url" not in body  # viser's own port streams only to the relay
        second = client.post(base, json={"run_id": run_id}, headers=auth).json()
        assert second["tab"] != body["tab"] and second["port"] != body["port"]  # a session per tab
        assert client.get(body["url"]).status_code == 403
        page = client.get(body["url"] + f"?token={token}")
        assert page.status_code == 200 and "Viser" in page.text
        assert page.cookies.get("leap_token") == token  # the websocket handshake carries it
        ws_url = body["url"].rstrip("/")
        proto = f"viser-v{viser.__version__}"
        with client.websocket_connect(ws_url, subprotocols=[proto]) as ws:
            first = ws.receive_bytes()  # viser's scene backlog, relayed
            assert len(first) > keys.size * 15
        client.cookies.clear()
        # The handshake itself is answered 403.
        with (
            pytest.raises(WebSocketDenialResponse) as refused,
            client.websocket_connect(ws_url, subprotocols=[proto]) as ws,
        ):
            ws.receive_bytes()
        assert refused.value.status_code == 403
        with (
            pytest.raises(WebSocketDisconnect) as cross_site,
            client.websocket_connect(
                ws_url + f"?token={token}", subprotocols=[proto], headers={"origin": "http://evil.example"}
            ) as ws,
        ):
            ws.receive_bytes()
        assert cross_site.value.code == 1008
        from app import crud
        from app.core.db import open_db

        with open_db(settings.database) as db:
            project = crud.get_project(db, pid)
            assert project is not None
            params = run_params(SCHEMA3, Path(project.dataset_path))
            queued = crud.create_run(db, project_id=pid, params=params, runs_dir=settings.runs_dir)
            empty = crud.create_run(db, project_id=pid, params=params, runs_dir=settings.runs_dir)
            crud.update_run(db, empty.id, status="done")
            crud.update_run(db, queued.id, status="cancelled")
        r = client.post(base, json={"run_id": queued.id}, headers=auth)
        assert r.status_code == 409 and "only finished runs" in r.json()["detail"]
        r = client.post(base, json={"run_id": empty.id}, headers=auth)
        assert r.status_code == 409 and "has no voxel grid" in r.json()["detail"]
        assert client.get(base, headers=auth).json()["run_id"] == run_id  # still showing the good run
        assert client.delete(base, headers=auth).status_code == 204
        assert client.delete(base, headers=auth).status_code == 404


def test_scan_scope_correction_relabels_only_its_points_of_its_scan(review_store) -> None:
    """A correction made on the shown scan's points in scan scope: stored as those point indices of that
    scan; the scan layer shows the class on exactly those points, other scans and the voxel map keep the
    run's labels, and undo takes it back."""
    from viser.transforms import SO3

    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession

    settings, pid, _run_id, _keys, cls = review_store
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        player, tools = session.player, session.tools
        view = player.show_scan(0)
        assert view is not None and session.renderer.wait_drawn()
        run_labels = view.label.copy()
        down = SO3.from_matrix(np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])).wxyz
        above = view.points.mean(axis=0) + np.array([0, 0, 200.0])
        tools.set_tools(target="scan", scope="scan", depth_mode="through")
        n = tools.select_rect(above, down, math.radians(60), 1.0, (0.0, 0.0), (0.5, 1.0))
        picked = tools.selection.rows.copy()
        assert 0 < n == picked.size < view.points.shape[0] and tools.selection.frame_id == view.frame_id
        cid = session.corrections.assign_selection("building")
        assert cid is not None and session.renderer.wait_drawn()
        with open_db(settings.database) as db:
            (corr,) = crud.list_corrections(db, pid)
        assert (corr.scope, corr.frame_id) == ("scan", view.frame_id)
        np.testing.assert_array_equal(corr.points, picked)
        expected = run_labels.copy()
        expected[picked] = 2
        np.testing.assert_array_equal(session.shared.scan_label, expected)
        np.testing.assert_array_equal(session.scene.scan.handle.colors, np.array(SCHEMA3_COLORS)[expected])
        np.testing.assert_array_equal(session.label, cls)  # the voxel map is not corrected
        assert not session.corrected.any() and tools.selection.rows.size == 0
        other = player.show_scan(1)
        assert other is not None
        np.testing.assert_array_equal(session.shared.scan_label, other.label)
        player.show_scan(0)
        np.testing.assert_array_equal(session.shared.scan_label, expected)
        assert session.corrections.undo() == cid
        np.testing.assert_array_equal(session.shared.scan_label, run_labels)
    finally:
        session.close()


def test_a_run_handed_over_twice_is_loaded_once(review_store) -> None:
    """The tab's run watcher and the project's follower may both hand over the run that just finished (one
    while the other is still loading it): the shown run is not loaded again."""
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession

    settings, pid, *_ = review_store
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        shown, version = session.run, session.scene_version
        assert shown is not None and version == 1
        session.follow_run(shown)
        assert session.scene_version == version and session.run is shown
    finally:
        session.close()


def test_split_here_and_merge_with_renumber_the_shown_objects_at_once(review_store) -> None:
    """The inspected object's *Split here* (at the shown scan) and *Merge with*: stored as object corrections
    of the run, and the shown scan's object ids (colour by objects) and the object line follow at once."""
    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.records import ObjectInfo
    from app.viewer.selection_tool import object_info
    from app.viewer.session import ReviewSession
    from leap_core.pipeline.tracks_file import SequenceTracks
    from leap_core.tracking import TrackTable

    settings, pid, run_id, *_ = review_store
    with open_db(settings.database) as db:
        run = crud.require_run(db, run_id)
    # Object 1: rows 0-9 of every scan (an id switch at scan 1); object 2: rows 20-29 of every scan.
    per_scan = [(np.r_[0:10, 20:30], np.r_[[1] * 10, [2] * 10])] * 3
    table = TrackTable(
        label=np.array([1, 1], np.int16),
        velocity=np.zeros((2, 3)),
        moving=np.zeros(2, bool),
        scans=np.full(2, 3, np.int64),
        sweep=np.zeros(2),
        voted=np.zeros(2, bool),
    )
    frame_ids = tuple(sorted(p.stem for p in (run.sequence_layout("00").folder / "points").glob("*.npz")))
    SequenceTracks(
        frame_ids,
        np.arange(0, 61, 20, dtype=np.int64),
        np.concatenate([r for r, _ in per_scan]).astype(np.int32),
        np.concatenate([t for _, t in per_scan]).astype(np.int32),
        table,
    ).save(run.sequence_layout("00").tracks)
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        player, tools = session.player, session.tools
        assert player.show_scan(1) is not None and session.shared.objects is not None
        tools.inspected_object = object_info(
            session.shared.objects, ObjectInfo(run_id, 0, -1, 0, False, 0.0, 0, frame_ids[1]), 1
        )
        cid = session.corrections.split_object()
        with open_db(settings.database) as db:
            stored = crud.get_correction(db, cid)
        assert (stored.action, stored.track_id, stored.split_frame) == ("split", 1, frame_ids[1])
        assert tools.inspected_object.track == 3 and tools.inspected_object.scans == 2
        assert session.shared.scan_instance[:10].tolist() == [3] * 10  # the new id, beyond the run's 1, 2
        player.show_scan(0)
        assert session.shared.scan_instance[:10].tolist() == [1] * 10
        # The split-off part takes object 2 in: one id (3) in every scan it is in.
        cid = session.corrections.merge_object(2)
        assert tools.inspected_object.track == 3 and tools.inspected_object.scans == 3
        assert session.shared.scan_instance[20:30].tolist() == [3] * 10
        assert session.corrections.undo() == cid
        assert session.shared.scan_instance[20:30].tolist() == [2] * 10
    finally:
        session.close()


def test_scan_player_plays_from_the_first_scan_and_stops_at_the_last(review_store) -> None:
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.panel_nav import BROWSE
    from app.viewer.records import SessionConfig
    from app.viewer.session import ReviewSession

    settings, pid, *_ = review_store
    session = ReviewSession(
        AppBackend(settings, pid), panel=ReviewPanel, config=SessionConfig(play_interval_s=0.05)
    )
    try:
        player = session.player
        assert player.scan_count == 3
        player.show_scan(2)
        shown: list[int] = []
        assert player.set_playing(None) is True  # from the last scan: starts again at the first
        assert player.frame_pos == 0
        deadline = time.monotonic() + 10
        while player.playing and time.monotonic() < deadline:
            shown.append(player.frame_pos)
            time.sleep(0.005)
        assert not player.playing and player.frame_pos == 2 and shown[0] == 0 and 1 in shown
        assert tuple(session.panel.nav.browse.options) == BROWSE  # "Play" again, not "Pause"
        assert player.set_playing(True) is True and player.frame_pos == 0
        assert player.set_playing(None) is False and not player.playing
    finally:
        session.close()


def test_final_grid_path_follows_the_run_parameters(tmp_path) -> None:
    from app.viewer.data import final_grid_path

    assert final_grid_path(tmp_path) == tmp_path / "grid_smooth.npz"
    for i in (1, 2, 10):
        (tmp_path / f"grid_smooth_3dcn{i}.npz").write_bytes(b"")
    assert final_grid_path(tmp_path) == tmp_path / "grid_smooth_3dcn10.npz"
    assert final_grid_path(tmp_path, {"consistency": {"enabled": False}}) == tmp_path / "grid_smooth.npz"
    assert final_grid_path(tmp_path, {"consistency": {"enabled": True, "iterations": 2}}) == (
        tmp_path / "grid_smooth_3dcn2.npz"
    )
    # Parameters without a 3D-CN section are the defaults (3D-CN off); unreadable ones fall back to the
    # folder.
    assert final_grid_path(tmp_path, {"smoothing": {"k": 3}}) == tmp_path / "grid_smooth.npz"
    assert final_grid_path(tmp_path, {"no_such_section": 1}) == tmp_path / "grid_smooth_3dcn10.npz"


def test_session_review_queue_highlights_jumps_and_keeps_marks(review_store) -> None:
    """The focused region: its voxels at full colour and the rest dimmed, a box around it, the scan that saw
    it most shown with the region boxed in its image; accept/skip stored so that a new session (a restarted
    server) sees them; a changed region loses its mark."""
    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.records import SessionConfig
    from app.viewer.region_logic import REVIEW_BOX_RGB
    from app.viewer.session import ReviewSession
    from leap_core import review

    settings, pid, _run_id, keys, cls = review_store
    config = SessionConfig(queue_share=0.3, queue_min_count=1, queue_cell=2.0)
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel, config=config)
    try:
        regions = session.queue.build_queue("confidence")
        assert len(regions) >= 3
        assert session.queue.review_progress() == {"total": len(regions), "reviewed": 0, "skipped": 0}
        region = session.queue.next_region()
        assert region is regions[0] and session.queue.focus is region
        assert session.renderer.wait_drawn()
        handle = session.scene.voxels.handle
        full = np.array(SCHEMA3_COLORS, np.uint8)[cls]
        inside = np.isin(np.arange(keys.size), region.rows)
        np.testing.assert_array_equal(handle.colors[inside], full[inside])
        np.testing.assert_array_equal(handle.colors[~inside], vl.blend(full[~inside], (235, 235, 235), 0.75))
        box = session.scene.review_box
        assert box is not None and box.visible
        held = session.grid.centres[region.rows]
        np.testing.assert_allclose(box.position, (held.min(axis=0) + held.max(axis=0)) / 2, atol=1e-5)

        # Drawn filled on top: the region's voxels again, larger, in their colours pulled toward cyan.
        focus = session.scene.focus
        assert focus.visible and focus.count == region.count
        assert focus.point_size > session.scene.voxels.point_size
        np.testing.assert_array_equal(focus.handle.points, session.grid.centres[region.rows])
        np.testing.assert_array_equal(focus.handle.colors, rl.highlight_colors(full[region.rows]))

        # Scan jump: brute force over every scan (three here, all within queue_scans), nearest first on a tie.
        out = session.outputs
        order = review.nearest_scans(out.seq.poses[out.frame_indices, :3, 3], region.centre, 99)
        counts = [out.region_observers(out.frame_indices[i], keys[region.rows], 0.5) for i in order]
        first = review.best_observer([c[1] for c in counts], [c[0] for c in counts])
        assert first is not None
        best = int(order[first])
        counts = [out.region_observers(f, keys[region.rows], 0.5) for f in out.frame_indices]
        assert session.queue.focus_frame == best and session.player.frame_pos == best
        # The scan's points fade while the region is focused.
        scan_full = vl.class_colors(session.shared.scan_label, session.palette)
        np.testing.assert_array_equal(
            session.scene.scan.handle.colors, vl.blend(scan_full, (235, 235, 235), 0.85)
        )
        # The image shows where the region is: its projected points boxed in magenta.
        assert counts[best][1] > 0, "the tiny scene's camera should see the region"
        plain = out.scan_view(out.frame_indices[best], session.palette)
        boxed = session.player.mark_region_in_image(plain, best)
        u0, v0, u1, v1 = review.image_box(counts[best][2], plain.overlay.shape[1], plain.overlay.shape[0])
        assert boxed.overlay[v0, u0].tolist() == list(REVIEW_BOX_RGB)
        assert boxed.overlay[v1, (u0 + u1) // 2].tolist() == list(REVIEW_BOX_RGB)
        # The enlarged image is the crop around that box, zoomed to the image's size.
        h, w = plain.overlay.shape[:2]
        zoomed = session.player.zoomed_image()
        crop = review.zoom_box((u0, v0, u1, v1), w, h)
        np.testing.assert_array_equal(zoomed, review.crop_zoom(session.shared.scan_view.overlay, crop))
        assert zoomed.shape == plain.overlay.shape and crop[2] - crop[0] + 1 < w

        # Accept, then skip: stored in SQLite, the next unmarked region is shown each time.
        nxt = session.queue.mark_region("accepted")
        assert nxt is regions[1] and session.queue.region_pos == 1
        session.queue.mark_region("skipped")
        assert session.queue.review_progress() == {"total": len(regions), "reviewed": 1, "skipped": 1}
        with open_db(settings.database) as db:
            marks = crud.list_review_marks(db, pid)
            (progress,) = crud.review_progress(db, pid)
        assert marks[regions[0].id].state == "accepted" and marks[regions[1].id].state == "skipped"
        assert (progress["kind"], progress["reviewed"], progress["skipped"]) == ("confidence", 1, 1)

        # Leaving the review: the whole map at full colour, no box in the map or in the scan's image, no
        # verdict on a region no longer shown; the queue stays, so the next step goes on after it.
        shown_pos = session.queue.region_pos
        session.queue.clear_focus()
        assert session.queue.focus is None and session.renderer.wait_drawn()
        np.testing.assert_array_equal(session.scene.voxels.handle.colors, full)
        assert not session.scene.review_box.visible and not session.scene.focus.visible
        assert session.player.zoomed_image() is None
        scan_full = vl.class_colors(session.shared.scan_label, session.palette)
        np.testing.assert_array_equal(session.scene.scan.handle.colors, scan_full)
        pos = session.player.frame_pos
        plain = out.scan_view(out.frame_indices[pos], session.palette)
        np.testing.assert_array_equal(session.shared.scan_view.overlay, plain.overlay)
        with pytest.raises(ValueError, match="press Next region"):
            session.queue.mark_region("accepted")
        assert session.queue.next_region() is regions[shown_pos + 1]
    finally:
        session.close()

    # A new session on the same store (the server restarted) ranks the same queue and sees the marks.
    again = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel, config=config)
    try:
        regions2 = again.queue.build_queue("confidence")
        assert [r.id for r in regions2] == [r.id for r in regions]
        assert again.queue.review_progress() == {"total": len(regions), "reviewed": 1, "skipped": 1}
        assert again.queue.region_state(0) == "accepted" and again.queue.region_state(1) == "skipped"
        # Relabel the first region (a correction): its content changed, so its old mark no longer counts
        # until it is accepted on the new content (relabel accepts it).
        again.queue.show_region(0)
        cid = again.queue.relabel_region("building")
        assert cid is not None and again.queue.region_state(0) == "accepted"
        with open_db(settings.database) as db:
            (corr,) = crud.list_corrections(db, pid)
            stored = crud.list_review_marks(db, pid)[regions[0].id]
        np.testing.assert_array_equal(corr.keys, keys[regions[0].rows])
        assert (
            stored.signature
            == again.queue.signatures[0]
            != review.region_signatures(
                again.grid.centres, again.grid.keys, again.grid.label, [regions[0].cell], 2.0
            )[0]
        )
        # Re-ranked: the relabelled voxels are certain now; if the cell still ranks, it stays accepted.
        ranked = [r.id for r in again.queue.build_queue("confidence")]
        if regions[0].id in ranked:
            assert again.queue.region_state(ranked.index(regions[0].id)) == "accepted"
    finally:
        again.close()


def test_the_viewer_chooses_the_projects_2d_labeler_for_the_next_rerun(review_store) -> None:
    """The Run folder's "2D labeler" shows the project's labeler; choosing another stores it in the project
    (what the project page's form shows and the next run uses) and says so in the status."""
    from app import crud
    from app.core.db import open_db
    from app.services import project_config
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession

    settings, pid, _run_id, _keys, _cls = review_store
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        panel = session.panel
        assert isinstance(panel, ReviewPanel)
        assert panel.labeler.value == "simulated" and "sam3" in panel.labeler.options
        panel.labeler.value = "sam3"
        with open_db(settings.database) as db:
            assert project_config(crud.require_project(db, pid)).labeler == "sam3"
        assert "SAM 3" in panel.status.content and "next re-run" in panel.status.content
        panel.labeler.value = "grounded-sam"
        assert session.backend.labeler() == "grounded-sam"
    finally:
        session.close()


def test_session_delta_mode_marks_the_voxels_whose_class_changed_since_the_run_before(review_store) -> None:
    """Run 2 lists the classes in another order and changed the class of some voxels: the Δ view shows
    exactly those in their class colour and the rest pale (classes matched by name, not index)."""
    import shutil

    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession

    settings, pid, run_id, keys, cls = review_store
    reordered = {**SCHEMA3, "classes": [SCHEMA3["classes"][i] for i in (2, 0, 1)]}  # building, road, car
    new_index = np.array([1, 2, 0])  # road → 1, car → 2, building → 0
    changed = np.zeros(keys.size, bool)
    changed[::4] = True
    cls2 = np.where(changed, (cls + 1) % 3, cls)  # in run 1's numbering
    probs = np.full((keys.size, 3), 0.05, np.float32)
    probs[np.arange(keys.size), new_index[cls2]] = 0.9
    with open_db(settings.database) as db:
        first = crud.require_run(db, run_id)
        run2 = crud.create_run(
            db,
            project_id=pid,
            params=run_params(reordered, first.params.sequences[0].dataset),
            runs_dir=settings.runs_dir,
        )
        crud.update_run(db, run2.id, status="done")
    folder = run2.sequence_layout("00").folder
    shutil.copytree(first.sequence_layout("00").folder, folder)
    _write_grid(folder, keys, probs, voxel_size=0.5)

    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        assert session.run is not None and session.run.run_id == run2.id
        session.panel.color_by.value = "Δ since the run before"
        session.set_state(mode="delta", threshold=0.0)
        assert session.state.mode == "delta" and session.renderer.wait_drawn()
        colors = session.scene.voxels.handle.colors
        palette = np.array([c["color"] for c in reordered["classes"]], np.uint8)
        np.testing.assert_array_equal(colors[changed], palette[new_index[cls2[changed]]])
        assert (colors[~changed] == vl.UNCHANGED_RGB).all()
        assert "unchanged since run 1" in session.panel.legend.content
        # "Changed only": the threshold keeps the changed voxels.
        session.set_state(threshold=0.5)
        assert session.renderer.wait_drawn()
        assert session.scene.voxels.handle.points.shape[0] == int(changed.sum())
    finally:
        session.close()


def test_panel_words_stages_counts_corrections_and_clears_a_stale_error(review_store) -> None:
    from dataclasses import replace

    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession

    settings, pid, _run_id, _keys, _cls = review_store
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        panel = session.panel
        info = replace(session.run, status="running", percent=40.0, stage="00/labels2d")
        panel.on_run_progress(info)
        assert panel.status.content == f"Run {info.number} running, 2D labels: 40%"
        # An action that fails shows its error; the next one that works clears it.
        panel.guard(lambda: session.tools.set_tools(tool="pencil"))()
        assert panel.status.content.startswith("**Error:** tool must be")
        panel.guard(lambda: session.tools.set_tools(tool="lasso"))()
        assert panel.status.content == ""
        # One correction: singular.
        session.tools.select_rows(np.arange(3))
        assert session.corrections.assign_selection("car") is not None
        assert panel._corr_summary() == "1 active correction (applied in every later run)."
        session.tools.select_rows(np.arange(3, 6))
        session.corrections.assign_selection("road")
        assert panel._corr_summary() == "2 active corrections (applied in every later run)."
        # Jump to the first correction: its voxels selected.
        first = min(c.id for c in session.shared.corrections)
        assert session.corrections.show_correction(first) == 3
        np.testing.assert_array_equal(session.tools.selection.rows, np.arange(3))
        with pytest.raises(LookupError):
            session.corrections.show_correction(first + 100)
    finally:
        session.close()


def test_objects_to_review_step_inspect_frame_and_leave_the_queue_when_relabelled(review_store) -> None:
    """The hand-built run gets four tracks: 1 a car whose vote was close (car 50 % vs building 45 %) in
    every scan, 2 a car seen in scan 0 only, 3 road (stuff), 4 a car in scans 0 and 2 (a gap). The queue
    is 1, 4, 2; showing one moves to its middle scan, inspects and frames it; relabelling 1 takes it out."""
    from app import crud
    from app.core.db import open_db
    from app.viewer.manager import AppBackend
    from app.viewer.panel import ReviewPanel
    from app.viewer.session import ReviewSession
    from leap_core.datasets.kitti import KittiSequence
    from leap_core.pipeline.tracks_file import SequenceTracks
    from leap_core.tracking import TrackTable, VoteEvidence

    settings, pid, run_id, _keys, _cls = review_store
    with open_db(settings.database) as db:
        run = crud.require_run(db, run_id)
    layout = run.sequence_layout("00")
    per_scan = [
        [(range(0, 10), 1), (range(10, 15), 2), (range(30, 35), 4)],
        [(range(0, 10), 1), (range(20, 25), 3)],
        [(range(0, 10), 1), (range(30, 35), 4)],
    ]
    rows = [np.concatenate([np.arange(r.start, r.stop) for r, _ in s]) for s in per_scan]
    track = [np.concatenate([np.full(len(r), t) for r, t in s]) for s in per_scan]
    k = 4
    table = TrackTable(
        label=np.array([1, 1, 0, 1], np.int16),
        velocity=np.zeros((k, 3)),
        moving=np.zeros(k, bool),
        scans=np.array([3, 1, 1, 2]),
        sweep=np.zeros(k),
        voted=np.zeros(k, bool),
        evidence=VoteEvidence(
            np.array([0.5, 1, 1, 1]), np.array([2, -1, -1, -1], np.int16), np.r_[0.45, 0, 0, 0]
        ),
    )
    frame_ids = tuple(KittiSequence(run.params.sequences[0].dataset).frame_ids)
    SequenceTracks(
        frame_ids,
        np.cumsum([0, *(r.size for r in rows)]).astype(np.int64),
        np.concatenate(rows).astype(np.int32),
        np.concatenate(track).astype(np.int32),
        table,
    ).save(layout.tracks)
    session = ReviewSession(AppBackend(settings, pid), panel=ReviewPanel)
    try:
        panel = session.panel.objects
        shown = panel.step(1)
        assert shown is not None and (shown.track, shown.position, shown.count) == (1, 1, 3)
        assert shown.frame_id == frame_ids[1] and session.player.frame_pos == 1
        assert session.tools.inspected_object is not None and session.tools.inspected_object.track == 1
        assert "(1 of 3), car: car 50 % vs building 45 %" in panel.info.content
        view = session.shared.scan_view
        assert view is not None
        look = np.array(session.scene.server.initial_camera.look_at)
        centre = view.points[:10].astype(np.float64)
        assert np.linalg.norm(look[:2] - np.percentile(centre[:, :2], [2, 98], axis=0).mean(axis=0)) < 1e-3
        shown = panel.step(1)
        assert shown is not None and (shown.track, shown.frame_id) == (4, frame_ids[2])
        assert "1 gap; seen in 2 scans" in panel.info.content
        assert panel.step(1) is not None and session.objects.current == 2
        assert panel.step(1) is None and "end of the queue" in panel.info.content
        assert [panel.step(-1).track, panel.step(-1).track] == [4, 1]  # type: ignore[union-attr]
        assert session.corrections.relabel_object("building") is not None
        assert "relabelled: done; 2 left" in panel.info.content
        assert session.objects.pending() == [4, 2]
        assert panel.step(1).track == 4 and panel.step(-1) is None  # type: ignore[union-attr]
    finally:
        session.close()
