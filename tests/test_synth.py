"""Tests of the embedded demo sequence generator (leap_core.synth): ray-casting maths on hand-computed
cases, sensor geometry, and generated sequences (small configs: few beams, a quarter-size image)."""

from __future__ import annotations

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cli import cli as app
from leap_core.datasets.kitti import KittiSequence, read_label, read_png16, read_scan
from leap_core.errors import DatasetError
from leap_core.synth import (
    CameraConfig,
    EgoConfig,
    LidarConfig,
    SceneConfig,
    SynthConfig,
    build_scene,
    generate_sequence,
)
from leap_core.synth.camera import pixel_rays, world_cells
from leap_core.synth.domains import STREET_32_LIDAR, STREET_32_SCENE, domain_config
from leap_core.synth.generator import SYNTH_VERSION, camera_poses_kitti, lidar_poses, synth_version
from leap_core.synth.lidar import beam_elevations, ray_grid, scan
from leap_core.synth.materials import REQUIRED_IDS, Material, SemanticId
from leap_core.synth.names import DEMO_EXTRA_RAW_IDS, NAMES_BY_ID, VOCABULARY
from leap_core.synth.preview import project_points
from leap_core.synth.raycast import (
    BOX,
    CYLINDER,
    ELLIPSOID,
    FACE_CURVED,
    FACE_SIDE,
    Primitives,
    cast_grid,
    intersect_box,
    intersect_cylinder,
    intersect_ellipsoid,
    occluded_towards,
    pinhole_tasks,
    rotation_z,
    spherical_tasks,
    surface_hits,
)
from leap_core.synth.textures import box_pattern, road_paint

SMALL = SynthConfig(
    frames=3,
    seed=0,
    lidar=LidarConfig(beams=24, azimuth_step_deg=0.8),
    camera=CameraConfig().scaled(0.25),
    scene=SceneConfig(margin=90.0),
)
"""A fast config: 3 frames, 24 beams, 311×94 image, smaller surroundings."""


def _prims(rows: list[tuple[int, tuple, tuple, float]]) -> Primitives:
    """Primitives from (kind, centre, half, yaw) rows, with semantic id = row index + 1."""
    n = len(rows)
    return Primitives(
        kind=np.array([r[0] for r in rows], np.int8),
        center=np.array([r[1] for r in rows], np.float64),
        rot=np.stack([rotation_z(r[3]) for r in rows]),
        half=np.array([r[2] for r in rows], np.float64),
        semantic=np.arange(1, n + 1, dtype=np.uint16),
        instance=np.zeros(n, np.uint16),
        name=np.zeros(n, np.uint16),
        material=np.zeros(n, np.uint8),
        color=np.zeros((n, 3), np.float32),
        param=np.zeros((n, 4), np.float32),
    )


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# -------------------------------------------------------------------------------------- ray maths
def test_box_hand_computed() -> None:
    # Unit-half box at the origin, rays from (-5, 0, 0): straight in hits x = -1 at t = 4; a ray along +y
    # misses; a diagonal ray (1, 0.5, 0) enters x = -1 at t = 4 where y = 2 > 1, so it misses too.
    f32 = np.float32
    dx = np.array([1, 0, 1], f32)
    dy = np.array([0, 1, 0.5], f32)
    dz = np.zeros(3, f32)
    t = intersect_box(-5.0, 0.0, 0.0, dx, dy, dz, half=np.array([1.0, 1.0, 1.0]), t_min=0.0)
    assert t[0] == pytest.approx(4.0)
    assert np.isinf(t[1]) and np.isinf(t[2])
    # From inside, the entry point is behind the origin: no hit.
    assert np.isinf(intersect_box(0.0, 0.0, 0.0, dx[:1], dy[:1], dz[:1], half=np.ones(3), t_min=0.0)[0])


def test_cylinder_and_ellipsoid_hand_computed() -> None:
    f32 = np.float32
    one, zero = np.ones(1, f32), np.zeros(1, f32)
    cyl = np.array([2.0, 2.0, 1.0])
    # Cylinder r = 2, half height 1 along z; from (-10, 0, 0) along +x the side is hit at t = 8.
    assert intersect_cylinder(-10.0, 0.0, 0.0, one, zero, zero, half=cyl, t_min=0.0)[0] == pytest.approx(8.0)
    # From above (0, 0, 5) looking down, the top cap z = 1 is hit at t = 4.
    assert intersect_cylinder(0.0, 0.0, 5.0, zero, zero, -one, half=cyl, t_min=0.0)[0] == pytest.approx(4.0)
    # Above the cylinder but passing beside it: miss.
    assert np.isinf(intersect_cylinder(3.0, 0.0, 5.0, zero, zero, -one, half=cyl, t_min=0.0)[0])
    # Ellipsoid semi-axes (4, 1, 1): from (-10, 0, 0) along +x, hit at x = -4, t = 6; along z from
    # (0, 0, -10), hit at z = -1, t = 9.
    s = np.array([4.0, 1.0, 1.0])
    assert intersect_ellipsoid(-10.0, 0.0, 0.0, one, zero, zero, half=s, t_min=0.0)[0] == pytest.approx(6.0)
    assert intersect_ellipsoid(0.0, 0.0, -10.0, zero, zero, one, half=s, t_min=0.0)[0] == pytest.approx(9.0)
    # Parallel rays (array origins, one direction) give the same answers.
    t = intersect_box(
        np.array([-5, -5], f32),
        np.array([0, 3], f32),
        zero.repeat(2),
        1.0,
        0.0,
        0.0,
        half=np.ones(3),
        t_min=0.0,
    )
    assert t[0] == pytest.approx(4.0) and np.isinf(t[1])


def test_surface_normals_and_faces() -> None:
    prims = _prims(
        [
            (BOX, (5, 0, 0), (1, 1, 1), np.pi / 2),
            (CYLINDER, (0, 5, 0), (1, 1, 2), 0.0),
            (ELLIPSOID, (0, 0, 5), (1, 2, 1), 0.0),
        ]
    )
    origin = np.zeros(3)
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    t = np.array([4, 4, 4], np.float32)
    hits = surface_hits(prims, origin, dirs, t, np.array([0, 1, 2], np.int32))
    np.testing.assert_allclose(hits.normal, -np.eye(3), atol=1e-6)
    # The box is yawed by +90° (local y = world −x): the face towards the origin is its +y face (id 2).
    assert hits.face.tolist() == [2, FACE_SIDE, FACE_CURVED]


def test_grid_bounds_are_conservative() -> None:
    """Casting only each primitive's rectangle gives exactly the brute-force result (every primitive
    against every ray), for a LiDAR grid and a pinhole camera."""
    rng = np.random.default_rng(3)
    n = 150
    kinds = rng.integers(0, 3, n)
    rows = [
        (
            int(k),
            (rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(-1, 4)),
            tuple(rng.uniform(0.2, 2.5, 3)),
            float(rng.uniform(0, 6)),
        )
        for k in kinds
    ]
    rows.append((BOX, (0, 0, -0.5), (40, 40, 0.5), 0.0))
    prims = _prims(rows)
    cfg = LidarConfig(beams=32, azimuth_step_deg=1.0)
    rays = ray_grid(cfg)
    origin = np.array([0.3, -0.2, 1.7])
    pose = np.eye(4)
    pose[:3, 3] = origin
    tasks = spherical_tasks(prims, np.linalg.inv(pose), beam_elevations(cfg), rays.shape[2], 80.0)
    d1, p1 = cast_grid(prims, origin, rays, tasks, 0.5, 80.0)
    full = np.array([[p, 0, rays.shape[1], 0, rays.shape[2]] for p in range(len(prims))])
    d2, p2 = cast_grid(prims, origin, rays, full, 0.5, 80.0)
    assert (p1 == p2).all() and np.array_equal(d1, d2)
    assert (p1 >= 0).mean() > 0.5

    cam = CameraConfig().scaled(0.2)
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]])
    world_to_cam[:3, 3] = -world_to_cam[:3, :3] @ origin
    cam_rays = np.einsum("ij,jhw->ihw", world_to_cam[:3, :3].T.astype(np.float32), pixel_rays(cam))
    tasks = pinhole_tasks(prims, world_to_cam, cam.K(), cam.width, cam.height, 200.0)
    d1, p1 = cast_grid(prims, origin, cam_rays, tasks, 0.05, 1e4)
    full = np.array([[p, 0, cam.height, 0, cam.width] for p in range(len(prims))])
    d2, p2 = cast_grid(prims, origin, cam_rays, full, 0.05, 1e4)
    assert (p1 == p2).all() and np.array_equal(d1, d2)


def test_occluded_towards() -> None:
    # A box floating above (0, 0, 2): points below it are occluded looking up, points beside it are not.
    prims = _prims([(BOX, (0, 0, 2), (1, 1, 0.5), 0.0)])
    pts = np.array([[0, 0, 0], [0.9, -0.9, 0], [3, 0, 0], [0, 0, 4]], np.float32)
    assert occluded_towards(prims, pts, np.array([0, 0, 1.0])).tolist() == [True, True, False, False]


def test_road_paint_and_pattern_antialiasing() -> None:
    # Dashed centre line: 3 m dash every 9 m; edge line 6-18 cm inside the lane edge (lane width 3.5).
    local = np.array([[1.0, 0.0, 0], [5.0, 0.0, 0], [5.0, 3.38, 0], [5.0, 2.0, 0], [0.0, 0.3, 0]], np.float32)
    param = np.tile(np.array([[0.0, 1.0, 3.5, 0.0]], np.float32), (5, 1))
    fp = np.full(5, 0.001, np.float32)
    np.testing.assert_allclose(road_paint(local, param, fp), [1, 0, 1, 0, 0])
    # Zebra: 0.5 m stripes every 1 m across the street.
    param[:, 1] = 2.0
    zebra = road_paint(np.array([[0, 0.0, 0], [0, 0.5, 0]], np.float32), param[:2], fp[:2])
    np.testing.assert_allclose(zebra, [1, 0])
    # Far away (footprint ≥ the period) a pattern shows its mean coverage instead of aliasing.
    x = np.linspace(0, 10, 7, dtype=np.float32)
    np.testing.assert_allclose(box_pattern(x, 0.5, 0.3, np.full(7, 1.0, np.float32)), 0.3)


# ------------------------------------------------------------------------------------------ sensors
def test_hdl64_beam_layout() -> None:
    elev = np.rad2deg(beam_elevations(LidarConfig()))
    assert len(elev) == 64 and (np.diff(elev) < 0).all()
    assert elev[0] == pytest.approx(2.0) and elev[-1] == pytest.approx(-24.9)
    # Upper block about 1/3° apart, lower block about 1/2°.
    assert np.diff(elev[:32]).mean() == pytest.approx(-1 / 3, abs=0.01)
    assert np.diff(elev[32:]).mean() == pytest.approx(-0.518, abs=0.01)


def test_lidar_range_noise_and_labels() -> None:
    """A wall 20 m ahead: every return carries the wall's label and the range error has σ ≈ 2 cm."""
    prims = Primitives.concat([_prims([(BOX, (20.5, 0, 0), (0.5, 30, 30), 0.0)])])
    prims = replace(prims, material=np.array([Material.SLABS], np.uint8))
    cfg = LidarConfig(azimuth_step_deg=0.5)
    pose = np.eye(4)
    sc = scan(prims, pose, cfg, np.random.default_rng(0))
    assert len(sc.points) > 2000 and (sc.semantic == 1).all()
    front = np.abs(np.arctan2(sc.points[:, 1], sc.points[:, 0])) < np.deg2rad(30)
    err = sc.points[front, 0] - 20.0
    assert abs(err.mean()) < 0.005 and 0.015 < err.std() < 0.025
    assert ((sc.points[:, 3] >= 0) & (sc.points[:, 3] <= 1)).all()


def test_calibration_is_kitti_like() -> None:
    cam = CameraConfig()
    p2, tr = cam.P2(), cam.Tr()
    assert (cam.width, cam.height) == (1242, 375)
    assert 718 <= p2[0, 0] <= 721.6 and p2[0, 0] == p2[1, 1]
    # LiDAR x (forward) becomes camera z, LiDAR y (left) camera −x, LiDAR z (up) camera −y.
    np.testing.assert_allclose(tr[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=0.02)
    np.testing.assert_allclose(tr[:3, :3] @ [0, 1, 0], [-1, 0, 0], atol=0.02)
    cam_centre_in_lidar = -tr[:3, :3].T @ tr[:3, 3]
    assert cam_centre_in_lidar[0] == pytest.approx(0.27, abs=0.01)
    assert cam_centre_in_lidar[2] == pytest.approx(-0.08, abs=0.01)


# -------------------------------------------------------------------------------------------- scene
@pytest.fixture(scope="module")
def default_scene():
    return build_scene(SceneConfig(), EgoConfig(), 60, 10.0, 0)


def test_default_scene_has_every_required_class(default_scene) -> None:
    assert default_scene.semantic_ids() >= REQUIRED_IDS
    moving = {a.semantic for a in default_scene.actors}
    assert {SemanticId.MOVING_CAR, SemanticId.MOVING_PERSON} <= moving
    other = build_scene(SceneConfig(), EgoConfig(), 60, 10.0, 7)
    assert other.semantic_ids() >= REQUIRED_IDS
    assert not np.array_equal(other.static.center[:50], default_scene.static.center[:50])


def test_route_turns_and_speed(default_scene) -> None:
    route = default_scene.route
    yaw = np.arctan2(route.poses[:, 1, 0], route.poses[:, 0, 0])
    assert abs(np.unwrap(yaw)[-1] - yaw[0]) > np.deg2rad(80)
    step = np.linalg.norm(np.diff(route.poses[:, :2, 3], axis=0), axis=1)
    assert step.min() > 0.4 and step.max() < 1.0


def test_ego_from_rest_accelerates_at_accel(default_scene) -> None:
    """``start_speed=0``: the ego starts at rest and covers ½·a·t² until it meets the speed envelope; the
    default (None) route is the one that starts at cruise speed, unchanged."""
    ego = EgoConfig(start_speed=0.0)
    route = build_scene(SceneConfig(), ego, 60, 10.0, 0).route
    t = np.arange(6) / 10.0
    np.testing.assert_allclose(route.frame_s[:6], 0.5 * ego.accel * t**2, atol=1e-9)
    assert route.speed[0] == 0.0 and route.speed[5] == pytest.approx(0.8)
    # Same seed, same streets: the path is the default scene's, driven later.
    np.testing.assert_allclose(route.xy, default_scene.route.xy)
    assert default_scene.route.frame_s[1] == pytest.approx(0.8, abs=0.01)
    with pytest.raises(ValueError, match="start_speed must be a speed >= 0"):
        EgoConfig(start_speed=-1.0)


def test_actors_move(default_scene) -> None:
    for actor in default_scene.actors:
        moved = np.linalg.norm(actor.xy[-1] - actor.xy[0])
        assert moved > 5.0, actor.semantic
    walker = next(a for a in default_scene.actors if a.semantic == SemanticId.MOVING_PERSON)
    legs0 = walker.primitives(0).center[:2]
    legs5 = walker.primitives(5).center[:2] - np.r_[walker.xy[5] - walker.xy[0], 0]
    assert not np.allclose(legs0, legs5)  # the gait animates the legs


# -------------------------------------------------------------------------------------- sequences
@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    base = tmp_path_factory.mktemp("synth")
    a = generate_sequence(base / "a", SMALL, workers=1)
    b = generate_sequence(base / "b", SMALL, workers=2)
    c = generate_sequence(base / "c", replace(SMALL, seed=1), workers=1)
    return a, b, c


def test_deterministic_bytes(sequences) -> None:
    a, b, c = sequences
    da, db, dc = _digest(a.path), _digest(b.path), _digest(c.path)
    assert (
        len(da) == 3 * 7 + 4
    )  # velodyne, labels, image_2, gt2d/{semantic,instance,name,cell}; 4 files per sequence
    assert da == db  # same seed, one or two worker processes
    differing = [k for k in da if da[k] != dc.get(k)]
    assert "velodyne/000000.bin" in differing and "image_2/000000.png" in differing


def test_layout_reads_back(sequences) -> None:
    stats = sequences[0]
    seq = KittiSequence(stats.path)
    assert len(seq) == 3 and seq.has_labels and seq.has_images and seq.has_gt2d and seq.times is not None
    for f in seq:
        assert f.labels.shape[0] == f.points.shape[0] == stats.points[f.index]
        assert f.image.shape == (94, 310, 3)
        assert f.gt2d_semantic.shape == f.gt2d_instance.shape == (94, 310)
        assert read_label(seq.label_path(f.index)).dtype == np.uint32
    # The reader's LiDAR poses are the generator's, relative to the first scan.
    scene = build_scene(SMALL.scene, SMALL.ego, SMALL.frames, SMALL.hz, SMALL.seed)
    lp = lidar_poses(scene, SMALL)
    np.testing.assert_allclose(seq.poses, np.linalg.inv(lp[0])[None] @ lp, atol=1e-9)
    np.testing.assert_allclose(camera_poses_kitti(lp, seq.calib.Tr)[0], np.eye(4), atol=1e-12)


def test_name_image_agrees_with_class_and_instance_masks(sequences) -> None:
    """gt2d/name: sky exactly where the class mask is 0, every name's raw ids include the pixel's class,
    one name per object instance, and the names are the fine-grained vocabulary (not one per class)."""
    seq = KittiSequence(sequences[0].path)
    assert synth_version(seq.root) == SYNTH_VERSION
    seen: set[int] = set()
    for f in seq:
        names = read_png16(seq.root / "gt2d" / "name" / f"{f.frame_id}.png")
        sem, inst = f.gt2d_semantic, f.gt2d_instance
        np.testing.assert_array_equal(names == 0, sem == 0)
        assert set(np.unique(names).tolist()) - {0} <= {n.id for n in VOCABULARY}
        for nid in np.unique(names[names > 0]):
            assert set(np.unique(sem[names == nid]).tolist()) <= set(NAMES_BY_ID[int(nid)].raw_ids), nid
        for k in np.unique(inst[inst > 0]):
            assert np.unique(names[inst == k]).size == 1, k
        seen |= set(np.unique(names).tolist())
    assert len(seen - {0}) >= 15


def test_every_primitive_is_named_in_its_class(default_scene) -> None:
    prims = Primitives.concat([default_scene.primitives_at(0)])
    for nid in np.unique(prims.name):
        assert set(np.unique(prims.semantic[prims.name == nid]).tolist()) <= set(
            NAMES_BY_ID[int(nid)].raw_ids
        )
    used = {NAMES_BY_ID[int(n)].name for n in np.unique(prims.name)}
    # Every demo name is used somewhere in the default scene, and the demo's own objects carry their raw ids.
    assert used == {n.name for n in VOCABULARY}
    assert {300, 301, 302} <= set(np.unique(prims.semantic).tolist())
    assert {DEMO_EXTRA_RAW_IDS[i] for i in (300, 301, 302)} == {"traffic-cone", "bench", "bollard"}


def test_points_in_image_share(sequences) -> None:
    share = sequences[0].in_image_share
    assert 0.08 < share < 0.3


def test_2d_3d_ground_truth_agree(sequences) -> None:
    """Labelled points projected with P2·Tr land on a pixel of the same class (≥ 90 %), away from class
    edges (where the camera and the LiDAR, 0.27 m apart, see different surfaces)."""
    seq = KittiSequence(sequences[0].path)
    for f in seq:
        sem = (f.labels & 0xFFFF).astype(np.uint16)
        gt = f.gt2d_semantic
        u, v, ok, _ = project_points(f.points[:, :3], seq.calib.lidar_to_image, gt.shape[1], gt.shape[0])
        pad = np.pad(gt, 1, mode="edge")
        same = np.ones_like(gt, bool)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                same &= pad[dy : dy + gt.shape[0], dx : dx + gt.shape[1]] == gt
        inner = ok.copy()
        inner[ok] = same[v[ok], u[ok]]
        assert inner.sum() > 300
        agree = (gt[v[inner], u[inner]] == sem[inner]).mean()
        assert agree >= 0.9, (f.index, agree)
        inst = f.labels >> 16
        thing = inner & (inst > 0)
        if thing.any():
            assert (f.gt2d_instance[v[thing], u[thing]] == inst[thing]).mean() > 0.8


def test_world_cells_hand_computed() -> None:
    # 2 m cells: (x, y) = (5.0, -0.5) is cell (2, -1) -> (2, 255); (513.0, 3.9) is cell (256, 1) -> (0, 1).
    got = world_cells(np.array([[5.0, -0.5, 9.0], [513.0, 3.9, 0.0], [0.0, 0.0, 0.0]]))
    assert got.dtype == np.uint16
    assert got.tolist() == [(2 << 8) | 255, (0 << 8) | 1, 0]


def test_cell_images_are_fixed_to_the_world(sequences) -> None:
    """A static point seen in two frames lands on the same world cell in both cell images (≥ 90 % of
    the points away from cell borders): the cells move with the world, not with the camera."""
    seq = KittiSequence(sequences[0].path)

    def inner_cells(img: np.ndarray) -> np.ndarray:
        pad = np.pad(img, 1, mode="edge")
        same = np.ones_like(img, bool)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                same &= pad[dy : dy + img.shape[0], dx : dx + img.shape[1]] == img
        return same

    for a, b in ((0, 1), (1, 2)):
        fa, fb = seq.frame(a), seq.frame(b)
        cells_a, cells_b = fa.gt2d_cell, fb.gt2d_cell
        assert cells_a is not None and cells_b is not None and cells_a.shape == fa.gt2d_semantic.shape
        static = (fa.labels >> 16) == 0
        pts = fa.points[static, :3].astype(np.float64)
        world = pts @ fa.pose[:3, :3].T + fa.pose[:3, 3]
        inv = np.linalg.inv(fb.pose)
        in_b = world @ inv[:3, :3].T + inv[:3, 3]
        h, w = cells_a.shape
        ua, va, oka, _ = project_points(pts, seq.calib.lidar_to_image, w, h)
        ub, vb, okb, _ = project_points(in_b, seq.calib.lidar_to_image, w, h)
        ok = oka & okb
        ok[ok] = inner_cells(cells_a)[va[ok], ua[ok]] & inner_cells(cells_b)[vb[ok], ub[ok]]
        ok[ok] &= fa.gt2d_semantic[va[ok], ua[ok]] > 0
        assert ok.sum() > 100
        agree = (cells_a[va[ok], ua[ok]] == cells_b[vb[ok], ub[ok]]).mean()
        assert agree >= 0.9, (a, b, agree)
        # And the ids are not all one cell: the street spans several.
        assert len(np.unique(cells_a[va[ok], ua[ok]])) > 5


def test_moving_car_points_move(sequences) -> None:
    seq = KittiSequence(sequences[0].path)
    centroids = []
    for f in (seq.frame(0), seq.frame(2)):
        moving = (f.labels & 0xFFFF) == SemanticId.MOVING_CAR
        inst = f.labels >> 16
        ids = np.unique(inst[moving])
        xyz = f.points[:, :3] @ f.pose[:3, :3].T + f.pose[:3, 3]
        centroids.append({int(i): xyz[moving & (inst == i)].mean(axis=0) for i in ids})
    common = set(centroids[0]) & set(centroids[1])
    assert common
    assert max(np.linalg.norm(centroids[1][i] - centroids[0][i]) for i in common) > 0.7


def test_refuses_to_overwrite(tmp_path, sequences) -> None:
    seq = tmp_path / "sequences" / "00"
    seq.mkdir(parents=True)
    (seq / "keep.txt").write_text("x")
    with pytest.raises(DatasetError, match="not empty"):
        generate_sequence(tmp_path, SMALL)
    result = CliRunner().invoke(app, ["synth", str(tmp_path), "--frames", "1"])
    assert result.exit_code == 2 and "--force" in result.output
    assert (seq / "keep.txt").exists()
    stats = generate_sequence(tmp_path, replace(SMALL, frames=1), force=True)
    assert not (seq / "keep.txt").exists()
    assert read_scan(stats.path / "velodyne" / "000000.bin").shape[0] == stats.points[0]


# --------------------------------------------------------------------------------- the street-32 domain
def test_street_32_beam_layout() -> None:
    elev = np.rad2deg(beam_elevations(STREET_32_LIDAR))
    assert len(elev) == 32 and (np.diff(elev) < 0).all()
    assert elev[0] == pytest.approx(10.0) and elev[-1] == pytest.approx(-30.0)
    # Evenly about 1.3° apart, across the two blocks too (nuScenes' HDL-32E: 1.33°).
    np.testing.assert_allclose(np.diff(elev), -1.29, atol=0.02)


def test_domain_configs() -> None:
    assert domain_config("street", 7, 3) == SynthConfig(frames=7, seed=3)
    s32 = domain_config("street-32", 7, 3)
    assert isinstance(s32, SynthConfig) and (s32.frames, s32.seed) == (7, 3)
    assert s32.lidar == STREET_32_LIDAR and s32.lidar.height == 1.84
    assert s32.scene == STREET_32_SCENE != SceneConfig()
    # Only the sensor and the town differ from the street: same camera, driving and frame rate.
    assert replace(s32, lidar=LidarConfig(), scene=SceneConfig()) == SynthConfig(frames=7, seed=3)
    assert type(domain_config("agri-uav", 2, 0)).__name__ == "AgriSynthConfig"
    with pytest.raises(ValueError, match=r"unknown domain 'moon' \(known: street, street-32, agri-uav\)"):
        domain_config("moon", 1, 0)


def test_cli_street_32_scans_have_32_rings_from_plus_10_to_minus_30(tmp_path) -> None:
    result = CliRunner().invoke(app, ["synth", str(tmp_path), "--frames", "1", "--domain", "street-32"])
    assert result.exit_code == 0, result.output
    pts = read_scan(tmp_path / "sequences" / "00" / "velodyne" / "000000.bin")
    # The range noise lies along each ray, so a return keeps its beam's elevation.
    elev = np.rad2deg(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1])))
    rings = np.unique(np.round(elev, 1))
    assert 20 <= len(rings) <= 32
    assert elev.max() == pytest.approx(10.0, abs=0.1) and elev.min() == pytest.approx(-30.0, abs=0.1)
    assert synth_version(tmp_path / "sequences" / "00") == SYNTH_VERSION
