"""``leap import nuscenes``: a nuScenes-format folder written from generated demo frames (the JSON tables
the devkit reads, LIDAR_TOP ``.pcd.bin``, CAM_FRONT ``.jpg``, lidarseg ``.bin``), loaded by the devkit
itself, then imported and compared with what was written: points, images, calibration (projected pixels),
poses, times, labels; bad input; the ``projects/nuscenes.yaml`` preset against the devkit's lidarseg mapping.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
from pyquaternion import Quaternion
from runhelpers import folder
from typer.testing import CliRunner

from app.cli import cli
from leap_core.datasets.kitti import KittiSequence, read_label, read_scan
from leap_core.errors import Cancelled, DatasetError
from leap_core.importers.folder import IMPORT_NOTE
from leap_core.importers.nuscenes import (
    LIDARSEG_NAMES,
    camera_time_correction,
    import_nuscenes,
    intensity_to_remission,
    kitti_calib,
    kitti_cam_poses,
)
from leap_core.presets import load_preset
from leap_core.projection import project_points
from leap_core.synth import CameraConfig, LidarConfig, SceneConfig, SynthConfig, generate_sequence

VERSION = "v1.0-mini"
SCENE = "scene-0061"
T0 = 1_532_402_927_647_951
"""First LiDAR keyframe timestamp (µs), as nuScenes' (2018, microseconds)."""
KEYFRAME_US = 500_000
IMAGE_LAG_US = 18_000
"""The camera keyframe is taken 18 ms after the sweep's timestamp; the ego moves :data:`EGO_MOTION`
meanwhile."""

DEMO = SynthConfig(
    frames=4,
    seed=0,
    lidar=LidarConfig(beams=16, azimuth_step_deg=1.0),
    camera=CameraConfig().scaled(0.25),
    scene=SceneConfig(margin=90.0),
)
"""Four demo frames, coarse LiDAR and a 310×94 image: fast, and every part of the importer has data."""

SK_TO_LIDARSEG = {
    10: 17,
    252: 17,
    11: 14,
    13: 16,
    257: 16,
    15: 21,
    18: 23,
    258: 23,
    20: 22,
    259: 22,
    30: 2,
    254: 2,
    31: 2,
    40: 24,
    44: 24,
    60: 24,
    48: 26,
    49: 25,
    50: 28,
    51: 28,
    52: 28,
    80: 28,
    81: 28,
    70: 30,
    71: 30,
    72: 27,
    99: 29,
    300: 12,
    301: 29,
    302: 9,
}
"""The demo's SemanticKITTI (and demo) raw ids → nuScenes-lidarseg indices, unknown → 0 noise."""


def _rigid(yaw: float, t: tuple[float, float, float], tilt: float = 0.0) -> np.ndarray:
    """4×4 rotation about z by ``yaw`` (then about x by ``tilt``) and translation ``t``."""
    cz, sz, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(tilt), np.sin(tilt)
    m = np.eye(4)
    m[:3, :3] = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, cx, -sx], [0, sx, cx]]
    )
    m[:3, 3] = t
    return m


LIDAR_TO_EGO = _rigid(-np.pi / 2 + 0.01, (0.94, 0.01, 1.84), tilt=0.004)
"""A LIDAR_TOP-like extrinsic: on the roof, x to the right (rotated −90°)."""
MAP_OFFSET = _rigid(0.7, (411.3, 1180.9, 0.0))
"""Global map frame ← the demo's world: nuScenes poses are hundreds of metres from the map origin."""
EGO_MOTION = _rigid(0.004, (0.18, 0.005, 0.0))
"""Ego motion (in the ego frame) between a sweep and its camera image."""


def _token(kind: str, i: int) -> str:
    return hashlib.md5(f"{kind}-{i}".encode()).hexdigest()


def _pose_record(token: str, m: np.ndarray, **extra: object) -> dict[str, object]:
    q = Quaternion(matrix=m[:3, :3])
    return {
        "token": token,
        "translation": [float(v) for v in m[:3, 3]],
        "rotation": [float(v) for v in q.elements],
        **extra,
    }


@dataclass
class NuSource:
    """What :func:`write_nuscenes` wrote."""

    dataroot: Path
    seq: KittiSequence
    """The demo sequence the frames come from."""
    points: list[np.ndarray]
    """(N, 5) float32 x, y, z, intensity, ring per keyframe, as in the .pcd.bin."""
    lidarseg: list[np.ndarray]
    """(N,) uint8 per keyframe."""
    jpgs: list[bytes]
    """CAM_FRONT keyframe JPEG bytes."""
    cam_to_ego: np.ndarray
    intrinsic: np.ndarray
    lidar_tokens: list[str]
    camera_tokens: list[str]
    rig_tokens: list[dict[str, str]] = field(default_factory=list)
    """Per keyframe, each camera's keyframe sample_data token."""


@dataclass(frozen=True)
class NuCamera:
    """A camera of the written scene: its channel, its yaw about the LiDAR, how long after the sweep it
    fires and how the ego moved meanwhile (in the ego frame)."""

    channel: str
    yaw_deg: float = 0.0
    lag_us: int = IMAGE_LAG_US
    motion: np.ndarray = field(default_factory=lambda: EGO_MOTION)


SIX = tuple(
    NuCamera(ch, yaw, IMAGE_LAG_US + 7_000 * k, _rigid(0.004 * (1 + k), (0.18 * (1 + k / 3), 0.005 * k, 0.0)))
    for k, (ch, yaw) in enumerate(
        [
            ("CAM_FRONT", 0.0),
            ("CAM_FRONT_RIGHT", -55.0),
            ("CAM_BACK_RIGHT", -110.0),
            ("CAM_BACK", 180.0),
            ("CAM_BACK_LEFT", 110.0),
            ("CAM_FRONT_LEFT", 55.0),
        ]
    )
)
"""nuScenes' six cameras around the LiDAR, each firing 7 ms after the one before, the ego moving on."""


def write_nuscenes(
    demo: KittiSequence,
    dataroot: Path,
    frames: int | None = None,
    lidarseg: bool = True,
    cameras: tuple[NuCamera, ...] = (NuCamera("CAM_FRONT"),),
) -> NuSource:
    """Write ``frames`` demo frames as one nuScenes scene (keyframes 2 Hz, one LiDAR and one camera sweep
    between keyframes, a CAM_BACK sensor without data unless ``cameras`` has one) and check the devkit
    loads it.

    The camera: the demo's P2 = K·[I | t] becomes the intrinsic K and an extrinsic with t folded in, so the
    nuScenes camera sees exactly what the demo camera saw. The ego pose of an image is the sweep's moved by
    :data:`EGO_MOTION`. Further ``cameras`` are that camera turned about the LiDAR (showing the same image:
    only their geometry is checked).
    """
    n = len(demo) if frames is None else frames
    tables = dataroot / VERSION
    tables.mkdir(parents=True)
    k = demo.calib.P2[:, :3]
    fold = np.eye(4)
    fold[:3, 3] = np.linalg.solve(k, demo.calib.P2[:, 3])
    cam_to_ego = LIDAR_TO_EGO @ np.linalg.inv(fold @ demo.calib.Tr)
    log, scene, cs_lidar = _token("log", 0), _token("scene", 0), _token("cs", 0)
    channels = [c.channel for c in cameras] + (["CAM_BACK"] if len(cameras) == 1 else [])
    sensors = [{"token": _token("sensor", 0), "channel": "LIDAR_TOP", "modality": "lidar"}] + [
        {"token": _token("sensor", j + 1), "channel": ch, "modality": "camera"}
        for j, ch in enumerate(channels)
    ]
    calibrated = [_pose_record(cs_lidar, LIDAR_TO_EGO, sensor_token=sensors[0]["token"], camera_intrinsic=[])]
    cs_cams = [_token("cs", j + 1) for j in range(len(cameras))]
    for j, cam in enumerate(cameras):
        yaw = _rigid(np.deg2rad(cam.yaw_deg), (0.0, 0.0, 0.0))
        calibrated.append(
            _pose_record(
                cs_cams[j],
                LIDAR_TO_EGO @ yaw @ np.linalg.inv(fold @ demo.calib.Tr),
                sensor_token=sensors[j + 1]["token"],
                camera_intrinsic=k.tolist(),
            )
        )
    ego_poses: list[dict[str, object]] = []
    samples: list[dict[str, object]] = []
    lidar_chain: list[dict[str, object]] = []
    cam_chains: list[list[dict[str, object]]] = [[] for _ in cameras]
    lidarseg_rows: list[dict[str, object]] = []
    rng = np.random.default_rng(7)
    src = NuSource(dataroot, demo, [], [], [], cam_to_ego, k, [], [])
    h, w = demo.frame(0).image.shape[:2]
    lut = np.zeros(0x10000, dtype=np.uint8)
    for raw, idx in SK_TO_LIDARSEG.items():
        lut[raw] = idx
    for i in range(n):
        frame = demo.frame(i)
        ego_sweep = MAP_OFFSET @ frame.pose @ np.linalg.inv(LIDAR_TO_EGO)
        sample = _token("sample", i)
        samples.append(
            {
                "token": sample,
                "timestamp": T0 + i * KEYFRAME_US,
                "scene_token": scene,
                "prev": _token("sample", i - 1) if i else "",
                "next": _token("sample", i + 1) if i < n - 1 else "",
            }
        )
        pts = np.column_stack(
            [frame.points[:, :3], frame.points[:, 3] * 255.0, rng.integers(0, 32, len(frame.points))]
        ).astype(np.float32)
        img = cv2.imencode(".jpg", cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR))[1].tobytes()
        sweeps = [(True, 0, pts, img)]
        if i < n - 1:  # one sweep between keyframes: different points and image, not to be imported
            sweeps.append(
                (
                    False,
                    KEYFRAME_US // 2,
                    pts[: len(pts) // 2],
                    cv2.imencode(".jpg", 255 - frame.image)[1].tobytes(),
                )
            )
        for key, dt, cloud, jpg in sweeps:
            ts = T0 + i * KEYFRAME_US + dt
            folder = "samples" if key else "sweeps"
            ego_l = _token("ego-l", ts)
            ego_poses.append(_pose_record(ego_l, ego_sweep, timestamp=ts))
            lname = f"{folder}/LIDAR_TOP/n008-2018-07-24__LIDAR_TOP__{ts}.pcd.bin"
            (dataroot / lname).parent.mkdir(parents=True, exist_ok=True)
            (dataroot / lname).write_bytes(cloud.tobytes())
            common = {"sample_token": sample, "is_key_frame": key}
            for j, cam in enumerate(cameras):
                ego_c = _token("ego-c" if j == 0 else f"ego-c{j}", ts)
                ego_poses.append(_pose_record(ego_c, ego_sweep @ cam.motion, timestamp=ts + cam.lag_us))
                cname = f"{folder}/{cam.channel}/n008-2018-07-24__{cam.channel}__{ts + cam.lag_us}.jpg"
                (dataroot / cname).parent.mkdir(parents=True, exist_ok=True)
                (dataroot / cname).write_bytes(jpg)
                cam_chains[j].append(
                    {
                        "token": _token("sd-c" if j == 0 else f"sd-c{j}", ts),
                        "ego_pose_token": ego_c,
                        "calibrated_sensor_token": cs_cams[j],
                        "timestamp": ts + cam.lag_us,
                        "fileformat": "jpg",
                        "height": h,
                        "width": w,
                        "filename": cname,
                        **common,
                    }
                )
            lidar_chain.append(
                {
                    "token": _token("sd-l", ts),
                    "ego_pose_token": ego_l,
                    "calibrated_sensor_token": cs_lidar,
                    "timestamp": ts,
                    "fileformat": "pcd",
                    "height": 0,
                    "width": 0,
                    "filename": lname,
                    **common,
                }
            )
            if key:
                sem = lut[frame.labels & 0xFFFF]
                src.points.append(cloud)
                src.lidarseg.append(sem)
                src.jpgs.append(jpg)
                src.lidar_tokens.append(lidar_chain[-1]["token"])  # type: ignore[arg-type]
                src.camera_tokens.append(cam_chains[0][-1]["token"])  # type: ignore[arg-type]
                src.rig_tokens.append(
                    {c.channel: str(ch[-1]["token"]) for c, ch in zip(cameras, cam_chains, strict=True)}
                )
                if lidarseg:
                    fname = f"lidarseg/{VERSION}/{lidar_chain[-1]['token']}_lidarseg.bin"
                    (dataroot / fname).parent.mkdir(parents=True, exist_ok=True)
                    (dataroot / fname).write_bytes(sem.tobytes())
                    lidarseg_rows.append(
                        {
                            "token": lidar_chain[-1]["token"],
                            "sample_data_token": lidar_chain[-1]["token"],
                            "filename": fname,
                        }
                    )
    for chain in (lidar_chain, *cam_chains):
        for j, rec in enumerate(chain):
            rec["prev"] = chain[j - 1]["token"] if j else ""
            rec["next"] = chain[j + 1]["token"] if j < len(chain) - 1 else ""
    (dataroot / "maps").mkdir()
    cv2.imwrite(str(dataroot / "maps" / "prior.png"), np.zeros((4, 4), np.uint8))
    out = {
        "category": [
            {"token": _token("cat", i), "name": nm, "description": nm, "index": i}
            for i, nm in enumerate(LIDARSEG_NAMES)
        ],
        "attribute": [],
        "visibility": [],
        "instance": [],
        "sample_annotation": [],
        "sensor": sensors,
        "calibrated_sensor": calibrated,
        "ego_pose": ego_poses,
        "log": [
            {
                "token": log,
                "logfile": "n008-2018-07-24",
                "vehicle": "n008",
                "date_captured": "2018-07-24",
                "location": "boston-seaport",
            }
        ],
        "scene": [
            {
                "token": scene,
                "log_token": log,
                "nbr_samples": n,
                "first_sample_token": samples[0]["token"],
                "last_sample_token": samples[-1]["token"],
                "name": SCENE,
                "description": "demo street",
            }
        ],
        "sample": samples,
        "sample_data": lidar_chain + [rec for chain in cam_chains for rec in chain],
        "map": [
            {
                "token": _token("map", 0),
                "log_tokens": [log],
                "category": "semantic_prior",
                "filename": "maps/prior.png",
            }
        ],
    }
    if lidarseg:
        out["lidarseg"] = lidarseg_rows
    for name, rows in out.items():
        (tables / f"{name}.json").write_text(json.dumps(rows))
    from nuscenes.nuscenes import NuScenes

    nusc = NuScenes(version=VERSION, dataroot=str(dataroot), verbose=False)  # the devkit accepts the folder
    assert [s["name"] for s in nusc.scene] == [SCENE] and len(nusc.sample) == n
    assert hasattr(nusc, "lidarseg") == lidarseg
    return src


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> KittiSequence:
    return KittiSequence(generate_sequence(tmp_path_factory.mktemp("demo"), DEMO).path)


@pytest.fixture
def source(demo: KittiSequence, tmp_path: Path) -> NuSource:
    return write_nuscenes(demo, tmp_path / "nuscenes")


def _project(calib_p2: np.ndarray, calib_tr: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixels and (N,) depths of (N, 3) LiDAR points."""
    cam = xyz.astype(np.float64) @ calib_tr[:3, :3].T + calib_tr[:3, 3]
    uvw = cam @ calib_p2[:, :3].T + calib_p2[:, 3]
    return uvw[:, :2] / uvw[:, 2:3], cam[:, 2]


# ------------------------------------------------------------------------------------------- maths
def test_intensity_scale_is_a_fixed_division_by_255() -> None:
    np.testing.assert_allclose(intensity_to_remission([0.0, 127.5, 255.0, 300.0, -1.0]), [0, 0.5, 1, 1, 0])
    assert intensity_to_remission([51.0]).dtype == np.float32


def test_kitti_calib_hand_computed() -> None:
    lidar_to_ego = _rigid(0.0, (1.0, 0.0, 2.0))
    cam_to_ego = np.eye(4)
    cam_to_ego[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera z forward = ego x
    cam_to_ego[:3, 3] = [2.0, 0.0, 1.5]
    calib = kitti_calib(lidar_to_ego, cam_to_ego, [[100, 0, 50], [0, 100, 40], [0, 0, 1]])
    # LiDAR point (10, 0, 0) → ego (11, 0, 2) → camera (0, -0.5, 9): pixel (50, 40 - 100·0.5/9).
    uv, depth = _project(calib.P2, calib.Tr, np.array([[10.0, 0.0, 0.0]]))
    np.testing.assert_allclose(depth, [9.0])
    np.testing.assert_allclose(uv, [[50.0, 40.0 - 50.0 / 9.0]])
    assert calib.P2[:, 3].tolist() == [0, 0, 0]
    with pytest.raises(ValueError, match="non-singular 3×3"):
        kitti_calib(lidar_to_ego, cam_to_ego, [[1, 0, 0], [0, 1, 0]])


def test_camera_time_correction_hand_computed() -> None:
    # The ego drove 1 m forward (global x) between sweep and image; the LiDAR sits 1 m up, unrotated.
    lidar = _rigid(0.0, (0.0, 0.0, 1.0))
    m = camera_time_correction(np.eye(4), _rigid(0.0, (1.0, 0.0, 0.0)), lidar)
    np.testing.assert_allclose(m, _rigid(0.0, (-1.0, 0.0, 0.0)), atol=1e-12)  # a point 1 m nearer
    # A LiDAR turned 90° left sees that forward motion as its −y.
    m = camera_time_correction(np.eye(4), _rigid(0.0, (1.0, 0.0, 0.0)), _rigid(np.pi / 2, (0.0, 0.0, 1.0)))
    np.testing.assert_allclose(m, _rigid(0.0, (0.0, 1.0, 0.0)), atol=1e-12)
    np.testing.assert_allclose(
        camera_time_correction(MAP_OFFSET, MAP_OFFSET, LIDAR_TO_EGO), np.eye(4), atol=1e-9
    )


def test_kitti_cam_poses_hand_computed() -> None:
    tr = np.eye(4)
    tr[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # LiDAR x forward → camera z forward
    g = np.stack(
        [_rigid(0.3, (100.0, 50.0, 0.0)), _rigid(0.3, (100.0, 50.0, 0.0)) @ _rigid(0.0, (2.0, 0.0, 0.0))]
    )
    poses = kitti_cam_poses(g, tr)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(poses[1], _rigid(0.0, (0.0, 0.0, 2.0)), atol=1e-12)  # 2 m along camera z


# ---------------------------------------------------------------------------------------- round trip
def test_round_trip_points_images_calibration_poses_labels(source: NuSource, tmp_path: Path) -> None:
    out = tmp_path / "seq"
    done: list[int] = []
    summary = import_nuscenes(
        source.dataroot, out, version=VERSION, scene=SCENE, progress=lambda d, _total: done.append(d)
    )
    n = len(source.points)
    assert (summary.frames, summary.images, summary.labels, summary.skipped_sweeps) == (n, n, n, n - 1)
    assert done == list(range(1, n + 1))
    assert summary.max_offset_ms == pytest.approx(IMAGE_LAG_US / 1e3)
    assert (
        f"wrote {n} frames of {SCENE}" in summary.line()
        and f"skipped {n - 1} LIDAR_TOP sweeps" in summary.line()
    )
    seq = KittiSequence(out)
    assert seq.frame_ids == [f"{i:06d}" for i in range(n)] and seq.has_labels and seq.pose_source == "file"
    # Motion compensation: the points are seen from the LiDAR at the image time, N = S⁻¹·D·S later.
    motion = np.linalg.inv(LIDAR_TO_EGO) @ EGO_MOTION @ LIDAR_TO_EGO
    to_image_time = np.linalg.inv(motion)
    from nuscenes.nuscenes import NuScenes

    nusc = NuScenes(version=VERSION, dataroot=str(source.dataroot), verbose=False)
    for i, frame in enumerate(seq):
        src_pts = source.points[i]
        got = read_scan(seq.scan_path(i))
        want_xyz = src_pts[:, :3].astype(np.float64) @ to_image_time[:3, :3].T + to_image_time[:3, 3]
        np.testing.assert_allclose(got[:, :3], want_xyz, atol=2e-5)
        np.testing.assert_allclose(got[:, 3], src_pts[:, 3] / 255.0, rtol=1e-6)
        # Images: the keyframe's bytes (not the sweep image between keyframes).
        assert seq.image_path(i) is not None and seq.image_path(i).read_bytes() == source.jpgs[i]  # type: ignore[union-attr]
        # Calibration: imported points through calib.txt land where the demo camera (its own P2, Tr) sees the
        # same physical points (moved by the ego motion in between), within 1e-3 px.
        uv_got, depth = _project(seq.calib.P2, seq.calib.Tr, got[:, :3])
        uv_src, src_depth = _project(source.seq.calib.P2, source.seq.calib.Tr, want_xyz)
        front = src_depth > 0.5
        assert front.sum() > 100
        np.testing.assert_allclose(uv_got[front], uv_src[front], atol=1e-3)
        # ... and where the devkit's own map_pointcloud_to_image puts them (it computes in float32 through
        # global map coordinates ~1000 m, so its pixels carry ~1e-2 px of rounding).
        dk_uv, _, im = nusc.explorer.map_pointcloud_to_image(source.lidar_tokens[i], source.camera_tokens[i])
        w, h = im.size
        keep = (
            (depth > 1.0)
            & (uv_got[:, 0] > 1)
            & (uv_got[:, 0] < w - 1)
            & (uv_got[:, 1] > 1)
            & (uv_got[:, 1] < h - 1)
        )
        assert dk_uv.shape[1] == keep.sum() > 100
        np.testing.assert_allclose(uv_got[keep], dk_uv[:2].T, atol=0.05)
        # Labels: the lidarseg index per point, instance 0.
        np.testing.assert_array_equal(read_label(seq.label_path(i)), source.lidarseg[i].astype(np.uint32))
        # Poses: each imported point's world position is the source's, in the world of frame 0's image time.
        world_got = got[:, :3].astype(np.float64) @ frame.pose[:3, :3].T + frame.pose[:3, 3]
        src_world = source.seq.poses[i] @ np.column_stack([src_pts[:, :3], np.ones(len(src_pts))]).T
        np.testing.assert_allclose(world_got, (to_image_time @ src_world).T[:, :3], atol=2e-4)
    np.testing.assert_allclose(seq.cam_poses[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(seq.times, np.arange(n) * KEYFRAME_US / 1e6)
    note = json.loads((out / IMPORT_NOTE).read_text())
    assert note["scene"] == SCENE and [f["lidar_token"] for f in note["frames"]] == source.lidar_tokens
    assert not list(tmp_path.glob(".seq.*"))  # no staging folder left


def test_six_cameras_project_as_the_devkit_does(demo: KittiSequence, tmp_path: Path) -> None:
    """``--camera all``: each of six cameras, firing at its own time, projects the imported points through
    ``cameras.yaml`` and its ``tr_frames`` line where the devkit's ``map_pointcloud_to_image`` puts them."""
    from nuscenes.nuscenes import NuScenes

    src = write_nuscenes(demo, tmp_path / "nu", frames=2, cameras=SIX)
    out = tmp_path / "seq"
    summary = import_nuscenes(src.dataroot, out, version=VERSION, scene=SCENE, camera="all")
    assert (summary.frames, summary.images, summary.cameras) == (2, 12, 6)
    assert "12 images of 6 cameras: CAM_FRONT, CAM_FRONT_RIGHT, CAM_BACK_RIGHT" in summary.line()
    seq = KittiSequence(out)
    assert [c.name for c in seq.cameras] == [c.channel for c in SIX]
    nusc = NuScenes(version=VERSION, dataroot=str(src.dataroot), verbose=False)
    for i in range(2):
        pts = read_scan(seq.scan_path(i))
        np.testing.assert_allclose(pts[:, :3], src.points[i][:, :3], atol=1e-6)  # as the LiDAR saw them
        for k, cam in enumerate(SIX):
            assert seq.image_path(i, k) is not None
            m = seq.lidar_to_image(i, k)
            q = pts[:, :3].astype(np.float64) @ m[:, :3].T + m[:, 3]
            depth, sub = q[:, 2], q[:, :2] / q[:, 2:]
            dk_uv, _, im = nusc.explorer.map_pointcloud_to_image(
                src.lidar_tokens[i], src.rig_tokens[i][cam.channel]
            )
            w, h = im.size
            keep = (
                (depth > 1.0) & (sub[:, 0] > 1) & (sub[:, 0] < w - 1) & (sub[:, 1] > 1) & (sub[:, 1] < h - 1)
            )
            assert dk_uv.shape[1] == keep.sum() > 50, cam.channel
            np.testing.assert_allclose(sub[keep], dk_uv[:2].T, atol=0.05, err_msg=cam.channel)
            # The project stage paints exactly these pixels, rounded.
            proj = project_points(pts, m, h, w)
            np.testing.assert_array_equal(np.column_stack([proj.u, proj.v]), np.floor(sub[proj.idx] + 0.5))
    # The time correction differs per camera: the later a camera fires, the further the transform moves.
    assert not np.allclose(seq.camera_tr(0, 0), seq.camera_tr(0, 5), atol=1e-3)
    text = CliRunner().invoke(cli, ["check", str(out)]).output
    assert "CAM_BACK_LEFT  cameras.yaml, Tr per frame from tr_frames/CAM_BACK_LEFT.txt; 2 of 2 scans" in text


def test_without_lidarseg_writes_no_labels(demo: KittiSequence, tmp_path: Path) -> None:
    src = write_nuscenes(demo, tmp_path / "nu", frames=2, lidarseg=False)
    summary = import_nuscenes(src.dataroot, tmp_path / "seq", version=VERSION, scene=SCENE)
    assert (
        summary.frames == 2 and summary.labels == 0 and "no labels (lidarseg not installed)" in summary.line()
    )
    assert not (tmp_path / "seq" / "labels").exists() and not KittiSequence(tmp_path / "seq").has_labels


def test_the_chosen_camera_and_a_keyframe_without_it(source: NuSource, tmp_path: Path) -> None:
    tables = source.dataroot / VERSION
    sample_data = json.loads((tables / "sample_data.json").read_text())
    # Frame 1's CAM_FRONT keyframe becomes a non-keyframe image: that frame is written without an image.
    victim = next(r for r in sample_data if r["token"] == source.camera_tokens[1])
    victim["is_key_frame"] = False
    (tables / "sample_data.json").write_text(json.dumps(sample_data))
    summary = import_nuscenes(
        source.dataroot, tmp_path / "seq", version=VERSION, scene=SCENE, camera="CAM_FRONT"
    )
    seq = KittiSequence(tmp_path / "seq")
    assert summary.images == len(seq) - 1 and seq.image_path(1) is None and seq.image_path(2) is not None
    assert "1 keyframes have no CAM_FRONT image" in summary.line()


# -------------------------------------------------------------------------------------------- bad input
def test_missing_dataroot_version_scene_camera_list_what_exists(source: NuSource, tmp_path: Path) -> None:
    out = tmp_path / "seq"
    with pytest.raises(DatasetError, match="nuScenes dataroot does not exist"):
        import_nuscenes(tmp_path / "nowhere", out, scene=SCENE)
    with pytest.raises(
        DatasetError, match=r"no nuScenes version 'v1.0-trainval' .*versions in .*: v1.0-mini"
    ):
        import_nuscenes(source.dataroot, out, version="v1.0-trainval", scene=SCENE)
    with pytest.raises(DatasetError, match=r"scene.json: no scene 'scene-9999' \(scenes: scene-0061\)"):
        import_nuscenes(source.dataroot, out, scene="scene-9999")
    with pytest.raises(
        DatasetError, match=r"sensor.json: no camera 'CAM_LEFT' \(cameras: CAM_BACK, CAM_FRONT\)"
    ):
        import_nuscenes(source.dataroot, out, scene=SCENE, camera="CAM_LEFT")
    with pytest.raises(DatasetError, match="scene 'scene-0061' has no CAM_BACK keyframe images"):
        import_nuscenes(source.dataroot, out, scene=SCENE, camera="CAM_BACK")
    assert not out.exists()


def test_broken_tables_and_files_name_the_file(source: NuSource, tmp_path: Path) -> None:
    tables = source.dataroot / VERSION
    good = (tables / "calibrated_sensor.json").read_text()
    (tables / "calibrated_sensor.json").write_text("[]")  # sample_data now points at unknown calibrations
    with pytest.raises(
        DatasetError, match=r"v1.0-mini: the nuScenes devkit cannot load it: missing key or token"
    ):
        import_nuscenes(source.dataroot, tmp_path / "a", scene=SCENE)
    (tables / "calibrated_sensor.json").write_text(good)
    poses = json.loads((tables / "ego_pose.json").read_text())
    (tables / "ego_pose.json").write_text(json.dumps(poses[1:]))  # the loader does not check these tokens
    with pytest.raises(DatasetError, match=r"v1.0-mini: a record refers to a token its table lacks: '"):
        import_nuscenes(source.dataroot, tmp_path / "a", scene=SCENE)
    (tables / "ego_pose.json").write_text(json.dumps(poses))
    pcd = source.dataroot / json.loads((tables / "sample_data.json").read_text())[0]["filename"]
    good_pcd = pcd.read_bytes()
    pcd.write_bytes(good_pcd[:-4])
    with pytest.raises(DatasetError, match=rf"{pcd.name}: not a nuScenes LiDAR file"):
        import_nuscenes(source.dataroot, tmp_path / "b", scene=SCENE)
    pcd.write_bytes(good_pcd)
    label = next((source.dataroot / "lidarseg" / VERSION).glob(f"{source.lidar_tokens[2]}*"))
    label.write_bytes(label.read_bytes()[:-1])
    with pytest.raises(
        DatasetError, match=rf"{label.name}: {len(source.points[2]) - 1} lidarseg labels but "
    ):
        import_nuscenes(source.dataroot, tmp_path / "c", scene=SCENE)
    for name in ("a", "b", "c"):  # nothing half-written
        assert not (tmp_path / name).exists() and not list(tmp_path.glob(f".{name}.*"))


def test_calibration_changing_within_the_scene_is_refused(source: NuSource, tmp_path: Path) -> None:
    tables = source.dataroot / VERSION
    calibrated = json.loads((tables / "calibrated_sensor.json").read_text())
    moved = dict(calibrated[1], token="moved", translation=[2.0, 0.0, 1.5])
    (tables / "calibrated_sensor.json").write_text(json.dumps([*calibrated, moved]))
    sample_data = json.loads((tables / "sample_data.json").read_text())
    next(r for r in sample_data if r["token"] == source.camera_tokens[2])["calibrated_sensor_token"] = "moved"
    (tables / "sample_data.json").write_text(json.dumps(sample_data))
    with pytest.raises(DatasetError, match="CAM_FRONT has 2 different calibrations within the scene"):
        import_nuscenes(source.dataroot, tmp_path / "seq", scene=SCENE)


def test_output_folder_is_never_overwritten_without_force(source: NuSource, tmp_path: Path) -> None:
    out = tmp_path / "seq"
    out.mkdir()
    (out / "poses.txt").write_text("mine\n")
    with pytest.raises(DatasetError, match=r"output folder is not empty .*pass --force"):
        import_nuscenes(source.dataroot, out, scene=SCENE)
    assert (out / "poses.txt").read_text() == "mine\n"
    import_nuscenes(source.dataroot, out, scene=SCENE, force=True)  # a previous import is replaced
    assert len(KittiSequence(out)) == len(source.points)
    (out / "predictions").mkdir()
    with pytest.raises(DatasetError, match="holds 'predictions', which an import does not write"):
        import_nuscenes(source.dataroot, out, scene=SCENE, force=True)
    (out / "predictions").rmdir()
    # Interrupted: the previous import stays whole and no staging folder is left.
    before = sorted(p.name for p in (out / "velodyne").iterdir())

    def stop(done: int, total: int) -> None:
        if done == 2:
            raise Cancelled

    with pytest.raises(Cancelled):
        import_nuscenes(source.dataroot, out, scene=SCENE, force=True, progress=stop)
    assert sorted(p.name for p in (out / "velodyne").iterdir()) == before
    assert not list(tmp_path.glob(".seq.*"))


# ---------------------------------------------------------------------------------------------- CLI
def test_cli_imports_with_a_summary_and_reports_errors_in_one_line(source: NuSource, tmp_path: Path) -> None:
    runner = CliRunner()
    args = [
        "import",
        "nuscenes",
        str(source.dataroot),
        "--version",
        VERSION,
        "--scene",
        SCENE,
        "--out",
        str(tmp_path / "seq"),
    ]
    res = runner.invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert f"wrote {len(source.points)} frames of {SCENE}" in res.output and "nuscenes: 100%" in res.output
    again = runner.invoke(cli, args)
    assert again.exit_code == 2 and "output folder is not empty" in again.output
    assert runner.invoke(cli, [*args, "--force"]).exit_code == 0
    bad = runner.invoke(cli, [*args[:-2], "--out", str(tmp_path / "x"), "--camera", "CAM_SIDE"])
    assert bad.exit_code == 2 and "no camera 'CAM_SIDE' (cameras: CAM_BACK, CAM_FRONT)" in bad.output


# ------------------------------------------------------------------------------------------- preset
def test_preset_matches_the_devkit_lidarseg_mapping(source: NuSource) -> None:
    from nuscenes.eval.lidarseg.utils import LidarsegClassMapper
    from nuscenes.nuscenes import NuScenes
    from nuscenes.panoptic.panoptic_utils import STUFF_START_CLASS_ID
    from nuscenes.utils.color_map import get_colormap

    # The category indices: the devkit's colormap lists the 32 categories in index order, things before
    # the stuff classes that start at STUFF_START_CLASS_ID.
    assert tuple(get_colormap()) == LIDARSEG_NAMES
    assert LIDARSEG_NAMES.index("flat.driveable_surface") == STUFF_START_CLASS_ID
    mapper = LidarsegClassMapper(NuScenes(version=VERSION, dataroot=str(source.dataroot), verbose=False))
    preset = load_preset("nuscenes")
    assert preset.pipeline.labeler == "grounded-sam"  # no 2D ground truth in nuScenes
    coarse = {idx: name for name, idx in mapper.coarse_name_2_coarse_idx_mapping.items() if idx}
    assert [c.name for c in preset.schema.classes] == [coarse[i] for i in sorted(coarse)]
    for c in preset.schema.classes:
        assert c.export_id == mapper.coarse_name_2_coarse_idx_mapping[c.name]
        fine = sorted(f for f, k in mapper.fine_idx_2_coarse_idx_mapping.items() if k == c.export_id)
        assert sorted(c.gt_ids) == fine, c.name
        assert c.color == mapper.coarse_colormap[c.name]
    # Prompts: no word in two classes (the score is a max over tokens), all in one detector pass.
    from test_prompts import _words_by_class, words

    from leap_core.labelers.prompts import ClassPrompts, plan_passes

    assert {w: o for w, o in _words_by_class(preset.schema).items() if len(o) > 1} == {}
    classes = [
        ClassPrompts(i, c.name, c.prompts, c.negative_prompts) for i, c in enumerate(preset.schema.classes)
    ]
    assert len(plan_passes(classes, words, budget=256)) == 1


# ---------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_leap_run_on_an_imported_scene_with_the_nuscenes_preset(demo: KittiSequence, tmp_path: Path) -> None:
    from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models

    src = write_nuscenes(demo, tmp_path / "nu", frames=3)
    seq = tmp_path / "seq"
    assert import_nuscenes(src.dataroot, seq, scene=SCENE).frames == 3
    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=12)).models_dir
    res = CliRunner().invoke(
        cli,
        [
            "run",
            str(seq),
            "--project-file",
            "nuscenes",
            "--models",
            str(models),
            "--no-3dcn",
            "--out",
            str(tmp_path / "run"),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "2D labels: grounded-sam" in res.output and "3 .label files" in res.output
    assert "driveable_surface" in res.output  # the result table: the imported lidarseg labels were evaluated
    for fid in ("000000", "000001", "000002"):
        exported = read_label(folder(tmp_path / "run", seq.name) / "export" / f"{fid}.label")
        # Class in the low 16 bits (the upper 16 hold track ids of things).
        classes = exported & 0xFFFF
        assert exported.shape == (len(src.points[int(fid)]),) and set(np.unique(classes)) <= set(range(17))
