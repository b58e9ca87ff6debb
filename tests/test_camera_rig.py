"""A rig of several cameras per frame: the layouts that declare it (``image_K/`` with ``PK``, or
``cameras.yaml``), and a run where each camera alone sees about half the points: every point in either
view is labeled, and a point both cameras see fuses both observations."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from runhelpers import label

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import (
    Calib,
    KittiSequence,
    write_calib,
    write_image,
    write_png16,
    write_poses,
    write_scan,
)
from leap_core.datasets.rig import RIG_FILE, Camera, camera_rig_text
from leap_core.errors import DatasetError
from leap_core.fusion import VoxelGrid, log_table
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.pipeline.apply import frame_keys
from leap_core.pipeline.context import load_observation
from leap_core.projection import project_points
from leap_core.schema import builtin_schema

H, W, F = 48, 64, 50.0
AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
"""LiDAR axes (x forward, y left, z up) → camera axes (x right, y down, z forward)."""
ROAD, SIDEWALK = 40, 48
"""What the left and the right camera see everywhere (raw SemanticKITTI ids)."""


def yawed(deg: float) -> np.ndarray:
    """(4, 4) LiDAR → camera for a camera at the LiDAR turned ``deg`` to the left."""
    t = np.deg2rad(deg)
    rz = np.array([[np.cos(t), np.sin(t), 0.0], [-np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    tr = np.eye(4)
    tr[:3, :3] = AXES @ rz
    return tr


K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
P = np.concatenate([K, np.zeros((3, 1))], axis=1)
RIG = (Camera("left", P, yawed(25.0)), Camera("right", P, yawed(-25.0)))
"""Each camera sees ±32.6° about its axis: the two overlap within 7.6° of straight ahead."""


def two_camera_sequence(root: Path, n_points: int = 600) -> Path:
    """One scan whose points spread over ±55° ahead; ``cameras.yaml`` with the left and right camera,
    whose 2D ground truth is road (left) and sidewalk (right) everywhere."""
    rng = np.random.default_rng(3)
    az = np.deg2rad(rng.uniform(-55.0, 55.0, n_points))
    r = rng.uniform(4.0, 20.0, n_points)
    pts = np.column_stack(
        [r * np.cos(az), r * np.sin(az), rng.uniform(-1.0, 0.5, n_points), np.ones(n_points)]
    )
    write_scan(root / "velodyne" / "000000.bin", pts.astype(np.float32))
    write_calib(root / "calib.txt", Calib(P2=P, Tr=RIG[0].Tr))
    write_poses(root / "poses.txt", np.eye(4)[None])
    (root / RIG_FILE).write_text(camera_rig_text(RIG))
    for folder, raw in (("gt2d", ROAD), ("gt2d/right", SIDEWALK)):
        write_png16(root / folder / "semantic" / "000000.png", np.full((H, W), raw, np.uint16))
        write_png16(root / folder / "instance" / "000000.png", np.zeros((H, W), np.uint16))
    for cam, grey in zip(RIG, (60, 180), strict=True):
        write_image(root / cam.name / "000000.png", np.full((H, W, 3), grey, np.uint8))
    return root


def test_kitti_layout_reads_image_3_with_p3(tmp_path: Path, make_tiny_sequence) -> None:
    tiny = make_tiny_sequence(tmp_path, n_frames=1)
    seq = KittiSequence(tiny.root)
    assert [c.name for c in seq.cameras] == ["image_2"]  # the one-camera layout
    (tiny.root / "image_3").mkdir()
    text = (tiny.root / "calib.txt").read_text()
    (tiny.root / "calib.txt").write_text(text.replace("P3:", "Px:"))
    with pytest.raises(DatasetError, match=r"calib.txt: no 'P3:' line for the camera folder image_3/"):
        KittiSequence(tiny.root)
    p3 = tiny.calib.P2.copy()
    p3[0, 3] = -F * 0.54
    (tiny.root / "calib.txt").write_text(text + "P3: " + " ".join(map(str, p3.reshape(-1))) + "\n")
    seq = KittiSequence(tiny.root)
    assert [(c.name, c.source) for c in seq.cameras] == [
        ("image_2", "calib.txt P2"),
        ("image_3", "calib.txt P3"),
    ]
    np.testing.assert_array_equal(seq.cameras[1].lidar_to_image, p3 @ tiny.calib.Tr)
    assert not seq.frame(0, 1).has_image


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("cameras: {}\n", "expected 'cameras:' mapping"),
        (
            "cameras:\n  velodyne: {P: [1,0,0,0, 0,1,0,0, 0,0,1,0]}\n",
            "cameras.velodyne: 'velodyne' is a folder",
        ),
        ("cameras:\n  a: {P: [1, 2, 3]}\n", r"cameras.a.P: has 3 values, expected 12"),
        ("cameras:\n  a: {P: [0,0,0,0, 0,0,0,0, 0,0,1,0]}\n", r"cameras.a.P: left 3×3 block is singular"),
        ("cameras:\n  a: {P: [1,0,0,0, 0,1,0,0, 0,0,1,0], R: 1}\n", r"cameras.a: unknown key 'R'"),
        (
            "cameras:\n  ../up: {P: [1,0,0,0, 0,1,0,0, 0,0,1,0]}\n",
            r"cameras.../up: a camera name is a folder",
        ),
    ],
)
def test_bad_rig_file_names_file_and_field(
    tmp_path: Path, make_tiny_sequence, text: str, problem: str
) -> None:
    tiny = make_tiny_sequence(tmp_path, n_frames=1)
    (tiny.root / RIG_FILE).write_text(text)
    with pytest.raises(DatasetError, match=rf"cameras.yaml: {problem}"):
        KittiSequence(tiny.root)


def test_each_camera_paints_and_overlaps_fuse_both(tmp_path: Path) -> None:
    root = two_camera_sequence(tmp_path / "sequences" / "00")
    seq = KittiSequence(root)
    assert [c.name for c in seq.cameras] == ["left", "right"]
    pts = seq.frame(0).points
    seen = [np.zeros(len(pts), bool) for _ in RIG]
    for k, cam in enumerate(RIG):
        seen[k][project_points(pts, cam.lidar_to_image, H, W).idx] = True
    both = seen[0] & seen[1]
    # The premise: each camera alone sees about half the points, and some points both see.
    assert 0.4 < seen[0].mean() < 0.7 and 0.4 < seen[1].mean() < 0.7 and both.sum() >= 20

    schema = builtin_schema("semantickitti")
    cfg = PipelineConfig().with_labeler_config(SimulatedLabelerConfig.exact())
    result = label(root, schema, cfg, tmp_path / "run", until="label_points")
    lay = result.folder
    assert (lay / "labels2d" / "right" / "000000.npz").is_file()
    painted, n, in_view = load_observation(lay / "observations" / "000000.npz")
    np.testing.assert_array_equal(in_view, seen[0] | seen[1])  # "in view" = in any camera's view
    labels = np.load(lay / "points" / "000000.npz")["label"]
    assert (labels[in_view] >= 0).all(), "a point in some camera's view stayed unlabeled"
    road, sidewalk = schema.index("road"), schema.index("sidewalk")
    point_label = painted.point_labels(n)
    assert (point_label[seen[0] & ~seen[1]] == road).all()
    assert (point_label[seen[1] & ~seen[0]] == sidewalk).all()

    # A point both cameras see has two observations, and its voxel's log-likelihood is their sum.
    observations = np.bincount(painted.point_idx, minlength=n)
    np.testing.assert_array_equal(observations, seen[0].astype(int) + seen[1].astype(int))
    keys = frame_keys(seq.frame(0), cfg.fusion.voxel_size)
    alone = np.bincount(np.unique(keys, return_inverse=True)[1]) == 1
    lonely = both & alone[np.unique(keys, return_inverse=True)[1]]
    assert lonely.sum() >= 10
    grid = VoxelGrid.load(lay / "grid.npz")
    logp = grid.logp[grid.lookup(keys[lonely])].astype(np.float32)
    obs = log_table(painted.table, cfg.fusion.prob_floor)
    for row, p in zip(logp, np.flatnonzero(lonely), strict=True):
        mine = painted.rows[painted.point_idx == p]
        want = obs[mine].sum(axis=0)
        want = np.maximum(want - want.max(), -cfg.fusion.logp_clip)
        np.testing.assert_allclose(row, want, atol=2e-2)
    # Road from one camera and sidewalk from the other: both at the top of the fused distribution.
    assert (logp[:, road] == 0).all() and (logp[:, sidewalk] == 0).all()

    # The viewer shows the scan through either camera, and boxes a region in the camera that saw it.
    from app.viewer.data import RunOutputs

    outputs = RunOutputs(lay, root)
    palette = np.array([c.color for c in schema.classes], np.uint8)
    views = [outputs.scan_view(0, palette, camera=k) for k in range(2)]
    assert [v.camera for v in views] == ["left", "right"]
    assert views[0].overlay is not None and views[1].overlay is not None
    assert views[0].overlay[0, 0, 0] == 60 and views[1].overlay[0, 0, 0] == 180
    vs = cfg.fusion.voxel_size
    for k, only in ((0, seen[0] & ~seen[1]), (1, seen[1] & ~seen[0])):
        region = np.unique(keys[only])
        assert outputs.best_camera(0, region, vs) == k
        assert outputs.region_observers(0, region, vs, None)[1] == only.sum()


def test_check_reports_each_camera(tmp_path: Path) -> None:
    from app.advice import render_cli, report_dict
    from leap_core.pipeline.preflight import check_dataset

    root = two_camera_sequence(tmp_path / "sequences" / "00")
    (root / "gt2d" / "right" / "instance" / "000000.png").unlink()
    report = check_dataset(root, check_models=False)
    assert [(c.name, c.source, c.gt2d.present) for c in report.cameras] == [
        ("left", "cameras.yaml", 1),
        ("right", "cameras.yaml", 0),
    ]
    text = render_cli(report)
    assert "cameras   2, each painting the points in its view" in text
    assert "  right          cameras.yaml; 1 of 1 scans have its image, 0 its 2D ground truth" in text
    assert report_dict(report, "app")["cameras"][0]["gt2d"]["kind"] == "all"
    # Every camera's images are checked: a truncated one of the right camera is named.
    image = root / "right" / "000000.png"
    image.write_bytes(image.read_bytes()[:-20])
    damaged = check_dataset(root, check_models=False).finding("images_damaged")
    assert damaged is not None and damaged.path == str(root / "right") and damaged.frames == ("000000",)


@pytest.mark.slow
def test_synth_surround_rig_agrees_with_its_ground_truth(tmp_path: Path) -> None:
    """``leap synth --cameras 4``: four cameras rendered from the same world, each with its 2D ground
    truth; labelled points projected with each camera's ``P · Tr`` land on a pixel of their class."""
    from dataclasses import replace

    from leap_core.synth import generate_sequence
    from leap_core.synth.camera import CameraConfig
    from leap_core.synth.generator import SynthConfig
    from leap_core.synth.lidar import LidarConfig
    from leap_core.synth.scene import SceneConfig

    small = SynthConfig(
        frames=1,
        lidar=LidarConfig(beams=24, azimuth_step_deg=0.8),
        camera=CameraConfig().scaled(0.25),
        scene=SceneConfig(margin=90.0),
    )
    front = generate_sequence(tmp_path / "one", small)
    stats = generate_sequence(tmp_path / "four", replace(small, cameras=4))
    seq = KittiSequence(stats.path)
    assert [c.name for c in seq.cameras] == ["image_2", "image_rear", "image_left", "image_right"]
    # The front camera's files are those of the one-camera sequence, byte for byte.
    for rel in ("image_2/000000.png", "gt2d/semantic/000000.png", "velodyne/000000.bin"):
        assert (stats.path / rel).read_bytes() == (front.path / rel).read_bytes()
    assert stats.in_image_share > 2.5 * front.in_image_share
    frame = seq.frame(0)
    sem = (frame.labels & 0xFFFF).astype(np.uint16)
    seen = np.zeros(len(sem), bool)
    for view in frame.cameras():
        gt = view.gt2d_semantic
        proj = project_points(frame.points, view.rig_camera.lidar_to_image, *gt.shape)
        seen[proj.idx] = True
        pad = np.pad(gt, 1, mode="edge")
        inner = np.ones_like(gt, bool)  # away from class edges, where camera and LiDAR see different surfaces
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                inner &= pad[dy : dy + gt.shape[0], dx : dx + gt.shape[1]] == gt
        keep = inner[proj.v, proj.u]
        assert keep.sum() > 100, view.rig_camera.name
        agree = (gt[proj.v[keep], proj.u[keep]] == sem[proj.idx[keep]]).mean()
        assert agree >= 0.9, (view.rig_camera.name, agree)
    assert seen.sum() == stats.in_image[0]


def test_rig_entries_linked_out_of_the_data_roots_are_refused(tmp_path: Path) -> None:
    """The app confines every entry the pipeline reads to its data roots: a rig's camera folders too."""
    from app.services import escaping_entry

    roots = [tmp_path / "data"]
    root = two_camera_sequence(roots[0] / "sequences" / "00")
    assert escaping_entry(root, roots) is None
    outside = tmp_path / "elsewhere"
    (root / "right").rename(outside)
    (root / "right").symlink_to(outside, target_is_directory=True)
    assert escaping_entry(root, roots) == ("right", outside)
    (root / "right").unlink()
    (root / "image_3").symlink_to(outside, target_is_directory=True)  # a KITTI camera folder
    assert escaping_entry(root, roots) == ("image_3", outside)


def test_synth_cameras_option_names_what_it_takes(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli
    from leap_core.synth.domains import domain_config

    with pytest.raises(ValueError, match="the agri-uav domain has one camera"):
        domain_config("agri-uav", 2, 0, cameras=4)
    out = CliRunner().invoke(cli, ["synth", str(tmp_path), "--frames", "1", "--cameras", "3"])
    assert (
        out.exit_code != 0 and "--cameras: SynthConfig.cameras must be one of [1, 2, 4], got 3" in out.output
    )
    assert not (tmp_path / "sequences").exists()


def _small_demo(root: Path) -> Path:
    """One frame of the demo street at a quarter of its camera size, as ``leap synth`` writes it."""
    from leap_core.synth import generate_sequence
    from leap_core.synth.camera import CameraConfig
    from leap_core.synth.generator import SynthConfig
    from leap_core.synth.lidar import LidarConfig
    from leap_core.synth.scene import SceneConfig

    small = SynthConfig(
        frames=1,
        lidar=LidarConfig(beams=8, azimuth_step_deg=2.0),
        camera=CameraConfig().scaled(0.25),
        scene=SceneConfig(margin=90.0),
    )
    return generate_sequence(root, small).path


def test_image_3_added_to_a_demo_is_refused_not_projected_as_image_2(tmp_path: Path) -> None:
    """The demo knows one camera: its ``calib.txt`` holds ``P2`` and ``Tr`` only, each line one key and
    twelve numbers (what semantic-kitti-api's ``parse_calibration`` reads), so an ``image_3/`` folder
    added by hand is refused naming ``calib.txt`` and the missing ``P3``, by the reader and ``leap check``."""
    from leap_core.pipeline.preflight import check_dataset

    root = _small_demo(tmp_path)
    lines = (root / "calib.txt").read_text().splitlines()
    assert [ln.split(":")[0] for ln in lines] == ["P2", "Tr"]
    assert all(len(ln.split(":")[1].split()) == 12 for ln in lines)
    assert [c.name for c in KittiSequence(root).cameras] == ["image_2"]
    (root / "image_3").mkdir()
    shutil.copy(root / "image_2" / "000000.png", root / "image_3" / "000000.png")
    with pytest.raises(DatasetError, match=r"calib.txt: no 'P3:' line for the camera folder image_3/"):
        KittiSequence(root)
    report = check_dataset(root)
    assert not report.cameras
    blockers = [f for f in report.findings if f.severity == "blocker"]
    assert [(Path(f.path or "").name, "'P3:'" in f.detail) for f in blockers] == [("calib.txt", True)]


def test_calib_with_p2_copied_to_every_camera_refuses_image_3(tmp_path: Path, make_tiny_sequence) -> None:
    """A ``calib.txt`` whose ``P3`` is ``P2`` (earlier versions of ``write_calib`` wrote P2 as P0..P3) gives
    ``image_3/`` no projection of its own: refused with the fix, not projected with camera 2's matrix."""
    tiny = make_tiny_sequence(tmp_path, n_frames=1)
    text = (tiny.root / "calib.txt").read_text()
    p2 = next(ln for ln in text.splitlines() if ln.startswith("P2:"))
    copies = "".join(f"P{k}:{p2[3:]}\n" for k in (0, 1, 3))
    (tiny.root / "calib.txt").write_text(copies + text)
    assert [c.name for c in KittiSequence(tiny.root).cameras] == ["image_2"]  # no image_3/: nothing to refuse
    (tiny.root / "image_3").mkdir()
    with pytest.raises(DatasetError, match=r"calib.txt: 'P3' is a copy of 'P2'.*image_3's own projection"):
        KittiSequence(tiny.root)
