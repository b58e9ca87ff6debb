"""``leap import rosbag``: real bags written with rosbags' own writers (ROS 2 mcap and sqlite3, ROS 1) from a
few frames of the generated demo street, read back into the KITTI layout and compared with the source
frames: points, images, calibration (projected pixels), poses, times, dropped frames, bad input."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from runhelpers import folder
from scipy.spatial.transform import Rotation
from test_synth import SMALL as SYNTH_SMALL

from leap_core.datasets.kitti import Calib, KittiSequence
from leap_core.errors import DatasetError
from leap_core.importers.rosbag import (
    ImportSummary,
    RosbagImportConfig,
    import_rosbag,
    pair_nearest,
    pointcloud_xyzi,
    read_calib_file,
)
from leap_core.synth import generate_sequence

DEMO = replace(SYNTH_SMALL, frames=5)
"""Five frames of the demo street (seed 0) with a coarse LiDAR (~10k points) and a 311×94 camera."""

T0_NS = 1_700_000_000_123_456_789
"""Stamp of the first scan: a real epoch time, so nanosecond precision matters."""


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> KittiSequence:
    return KittiSequence(generate_sequence(tmp_path_factory.mktemp("demo"), DEMO).path)


# ============================================================================== writing test bags
@dataclass(frozen=True)
class BagSpec:
    """How a test bag encodes the demo frames."""

    kind: str = "mcap"
    """mcap | sqlite3 | ros1"""
    fields: tuple[tuple[str, str], ...] = (("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "f4"))
    """PointCloud2 fields in their byte order, with numpy type codes."""
    pad: int = 0
    """Bytes of padding after each point."""
    bigendian: bool = False
    height: int = 1
    """Rows of the cloud (organised clouds: NaN points fill the last row; rows get 8 bytes of padding)."""
    nan_every: int = 0
    """Insert a NaN point after every n-th point (0: none)."""
    image: str = "rgb8"
    """rgb8 | bgr8 | mono8 | jpeg | png"""
    camera_offsets_ms: tuple[float | None, ...] = ()
    """Camera stamp minus scan stamp per frame (default 10 ms each; None: that camera frame is missing)."""
    camera_info: bool = True
    tf_static: bool = True
    tf: bool = True
    moving_map: bool = False
    """map → odom drifts linearly (sampled only 0.5 s before the first and after the last scan)."""
    info_pad: int = 0
    """CameraInfo height minus the images' height."""
    tf_start_frame: int = 0
    """odom → base_link samples start at this frame (earlier scans have no pose)."""
    rear: bool = False
    """Also the sequence's second camera (a rig) on ``/rear/image_raw``, 3 ms after the first, with its
    CameraInfo and its ``/tf_static`` edge; frame 1 has no rear image."""


OPTICAL = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], np.float64)
"""camera_link ← camera_optical: optical z forward = link x, optical x right = -link y."""


def _rt(rot_z: float, t: Sequence[float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("z", rot_z).as_matrix()
    m[:3, 3] = t
    return m


BASE_VELO = _rt(0.02, (0.3, 0.0, 1.6))
"""base_link ← velodyne."""


def map_odom(t_s: float, t_end: float) -> np.ndarray:
    """map ← odom of the moving-map bags: yaw 0 → 0.2 rad and translation 0 → (2, 1, 0) over
    [-0.5, t_end + 0.5] s
    (constant rates, so slerp + linear interpolation between the two samples is exact)."""
    a = (t_s + 0.5) / (t_end + 1.0)
    return _rt(0.2 * a, (2.0 * a, 1.0 * a, 0.0))


class Msgs:
    """Message builders for one typestore (ROS 1 headers have a seq, ROS 1 CameraInfo upper-case matrices)."""

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.ros1 = ros1
        self.info_pad = 0
        """Rows added to the image height the CameraInfo states (a mismatched calibration)."""
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        tf_msg = "tf2_msgs/msg/TFMessage"
        if tf_msg not in self.ts.types:  # not in the Noetic store; real bags carry their definitions
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", tf_msg))
        self.t = self.ts.types

    def header(self, ns: int, frame: str) -> Any:
        stamp = self.t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        extra = {"seq": 0} if self.ros1 else {}
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    def serialize(self, msg: Any) -> bytes:
        typ = msg.__msgtype__
        return bytes(self.ts.serialize_ros1(msg, typ) if self.ros1 else self.ts.serialize_cdr(msg, typ))

    def cloud(self, ns: int, pts: np.ndarray, spec: BagSpec) -> Any:
        order = ">" if spec.bigendian else "<"
        pts = pts.astype(np.float64)
        if spec.nan_every:
            pts = np.insert(pts, np.arange(spec.nan_every, len(pts), spec.nan_every), np.nan, axis=0)
        width = -(-len(pts) // spec.height)
        pts = np.vstack([pts, np.full((width * spec.height - len(pts), 4), np.nan)])
        names = [n for n, _ in spec.fields]
        dt = np.dtype({"names": names, "formats": [order + c for _, c in spec.fields]})
        step = dt.itemsize + spec.pad
        dt = np.dtype(
            {
                "names": names,
                "formats": [order + c for _, c in spec.fields],
                "offsets": [dt.fields[n][1] for n in names],
                "itemsize": step,
            }
        )
        rec = np.zeros(len(pts), dt)
        for name, code in spec.fields:
            col = pts[:, "xyzi".index(name[0])] if name != "intensity" else pts[:, 3]
            if np.dtype(code).kind in "ui":
                col = np.round(np.nan_to_num(col) * np.iinfo(np.dtype(code)).max)
            rec[name] = col
        row_pad = 8 if spec.height > 1 else 0
        rows = rec.view(np.uint8).reshape(spec.height, width * step)
        data = np.hstack([rows, np.zeros((spec.height, row_pad), np.uint8)]).ravel()
        codes = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
        pf = self.t["sensor_msgs/msg/PointField"]
        fields = [pf(name=n, offset=dt.fields[n][1], datatype=codes[c], count=1) for n, c in spec.fields]
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self.header(ns, "velodyne"),
            height=spec.height,
            width=width,
            fields=fields,
            is_bigendian=spec.bigendian,
            point_step=step,
            row_step=width * step + row_pad,
            data=data,
            is_dense=False,
        )

    def image(self, ns: int, rgb: np.ndarray, kind: str, frame: str = "camera_optical") -> Any:
        hdr = self.header(ns, frame)
        if kind in ("jpeg", "png"):
            ok, buf = cv2.imencode(".jpg" if kind == "jpeg" else ".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            assert ok
            return self.t["sensor_msgs/msg/CompressedImage"](header=hdr, format=kind, data=buf.ravel())
        h, w, _ = rgb.shape
        px = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "mono8": rgb[:, :, :1]}[kind]
        ch = px.shape[2]
        # Rows padded by 4 bytes (step > width · channels).
        rows = np.hstack([np.ascontiguousarray(px).reshape(h, w * ch), np.zeros((h, 4), np.uint8)])
        return self.t["sensor_msgs/msg/Image"](
            header=hdr,
            height=h,
            width=w,
            encoding=kind,
            is_bigendian=False,
            step=w * ch + 4,
            data=rows.ravel(),
        )

    def camera_info(self, ns: int, calib: Calib, hw: tuple[int, int], frame: str = "camera_optical") -> Any:
        hw = (hw[0] + self.info_pad, hw[1])
        mats = {"d": np.zeros(5), "k": calib.P2[:, :3].ravel(), "r": np.eye(3).ravel(), "p": calib.P2.ravel()}
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(ns, frame),
            height=hw[0],
            width=hw[1],
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **{(k.upper() if self.ros1 else k): v.astype(np.float64) for k, v in mats.items()},
        )

    def tf(self, ns: int, items: list[tuple[str, str, np.ndarray]]) -> Any:
        g = self.t
        out = []
        for parent, child, m in items:
            q = Rotation.from_matrix(m[:3, :3]).as_quat()
            out.append(
                g["geometry_msgs/msg/TransformStamped"](
                    header=self.header(ns, parent),
                    child_frame_id=child,
                    transform=g["geometry_msgs/msg/Transform"](
                        translation=g["geometry_msgs/msg/Vector3"](x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                        rotation=g["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                    ),
                )
            )
        return g["tf2_msgs/msg/TFMessage"](transforms=out)


def scan_stamps(seq: KittiSequence) -> np.ndarray:
    assert seq.times is not None
    return T0_NS + np.round(seq.times * 1e9).astype(np.int64)


def expected_lidar_world(seq: KittiSequence, spec: BagSpec) -> np.ndarray:
    """map ← velodyne at each scan (not re-based), as the bag's /tf says."""
    tr = seq.calib.Tr
    lidar = np.linalg.inv(tr)[None] @ seq.cam_poses @ tr[None]
    if not spec.moving_map:
        return lidar
    t = (scan_stamps(seq) - T0_NS) * 1e-9
    return np.stack([map_odom(ti, t[-1]) for ti in t]) @ lidar


def write_bag(seq: KittiSequence, path: Path, spec: BagSpec = BagSpec()) -> Path:
    """Write ``seq``'s frames into a real bag at ``path`` (a folder for ROS 2, a ``.bag`` for ROS 1)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    m = Msgs(spec.kind == "ros1")
    m.info_pad = spec.info_pad
    stamps = scan_stamps(seq)
    offsets = spec.camera_offsets_ms or (10.0,) * len(seq)
    msgs: list[tuple[int, str, Any]] = []  # (recording time, topic, message)
    cam_topic = "/camera/image_raw/compressed" if spec.image in ("jpeg", "png") else "/camera/image_raw"
    for i, frame in enumerate(seq):
        cloud = m.cloud(int(stamps[i]), frame.points, spec)
        msgs.append((int(stamps[i]) + 2_000_000, "/velodyne_points", cloud))
        offset = offsets[i]
        if offset is None:
            continue
        cam_ns = int(stamps[i] + round(offset * 1e6))
        msgs.append((cam_ns + 1_000_000, cam_topic, m.image(cam_ns, frame.image, spec.image)))
        if spec.camera_info:
            msgs.append(
                (
                    cam_ns + 1_000_000,
                    "/camera/camera_info",
                    m.camera_info(cam_ns, seq.calib, frame.image.shape[:2]),
                )
            )
        if spec.rear and i != 1:
            rear, rear_ns = seq.frame(i, 1), cam_ns + 3_000_000
            msgs.append(
                (rear_ns + 1_000_000, "/rear/image_raw", m.image(rear_ns, rear.image, "rgb8", "rear_optical"))
            )
            info = m.camera_info(rear_ns, rear.calib, rear.image.shape[:2], "rear_optical")
            msgs.append((rear_ns + 1_000_000, "/rear/camera_info", info))
    tr = seq.calib.Tr
    if spec.tf_static:
        base_cam = BASE_VELO @ np.linalg.inv(tr) @ np.linalg.inv(OPTICAL)
        msgs.append(
            (
                int(stamps[0]) - 10**9,
                "/tf_static",
                m.tf(
                    int(stamps[0]) - 10**9,
                    [
                        ("base_link", "velodyne", BASE_VELO),
                        ("base_link", "camera_link", base_cam),
                        ("camera_link", "camera_optical", OPTICAL),
                    ]
                    + (
                        [("base_link", "rear_optical", BASE_VELO @ np.linalg.inv(seq.cameras[1].Tr))]
                        if spec.rear
                        else []
                    ),
                ),
            )
        )
    if spec.tf:
        lidar = np.linalg.inv(tr)[None] @ seq.cam_poses @ tr[None]
        t_end = (stamps[-1] - T0_NS) * 1e-9
        for i in range(spec.tf_start_frame, len(seq)):
            msgs.append(
                (
                    int(stamps[i]),
                    "/tf",
                    m.tf(int(stamps[i]), [("odom", "base_link", lidar[i] @ np.linalg.inv(BASE_VELO))]),
                )
            )
        for t_s in (-0.5, t_end + 0.5):
            ns = T0_NS + round(t_s * 1e9)
            edge = map_odom(t_s, t_end) if spec.moving_map else np.eye(4)
            msgs.append((ns, "/tf", m.tf(ns, [("map", "odom", edge)])))
    msgs.sort(key=lambda x: x[0])
    types = {topic: msg.__msgtype__ for _, topic, msg in msgs}
    if spec.kind == "ros1":
        with Writer1(path) as w:
            conns = {t: w.add_connection(t, typ, typestore=m.ts) for t, typ in types.items()}
            for ns, topic, msg in msgs:
                w.write(conns[topic], ns, m.serialize(msg))
    else:
        plugin = StoragePlugin.MCAP if spec.kind == "mcap" else StoragePlugin.SQLITE3
        with Writer2(path, version=9, storage_plugin=plugin) as w:
            conns = {t: w.add_connection(t, typ, typestore=m.ts) for t, typ in types.items()}
            for ns, topic, msg in msgs:
                w.write(conns[topic], ns, m.serialize(msg))
    return path


def bag_path(tmp_path: Path, spec: BagSpec, name: str = "rec") -> Path:
    return tmp_path / (f"{name}.bag" if spec.kind == "ros1" else name)


def do_import(
    seq: KittiSequence, tmp_path: Path, spec: BagSpec = BagSpec(), **cfg: Any
) -> tuple[KittiSequence, ImportSummary]:
    bag = write_bag(seq, bag_path(tmp_path, spec), spec)
    cam = "/camera/image_raw/compressed" if spec.image in ("jpeg", "png") else "/camera/image_raw"
    config = RosbagImportConfig(lidar_topic="/velodyne_points", camera_topic=cam, **cfg)
    out = tmp_path / "out" / "sequences" / "00"
    summary = import_rosbag(bag, out, config)
    return KittiSequence(out), summary


def pixels(calib: Calib, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixel coordinates of LiDAR points and the (N,) mask of points in front of the camera."""
    h = np.column_stack([pts[:, :3].astype(np.float64), np.ones(len(pts))]) @ calib.lidar_to_image.T
    front = h[:, 2] > 0.5
    return h[:, :2] / h[:, 2:3], front


def assert_same_sequence(
    got: KittiSequence, src: KittiSequence, frames: Sequence[int], spec: BagSpec, *, poses: bool = True
) -> None:
    """Points equal, images equal, projections within 1e-3 px, LiDAR poses within 1e-6 (or none), times
    within 1 ns."""
    assert len(got) == len(frames)
    for k, i in enumerate(frames):
        a, b = got.frame(k), src.frame(i)
        np.testing.assert_array_equal(a.points[:, :3], b.points[:, :3])
        np.testing.assert_allclose(a.points[:, 3], b.points[:, 3], atol=1e-7)
        np.testing.assert_array_equal(a.image, b.image)
        (pa, fa), (pb, fb) = pixels(got.calib, a.points), pixels(src.calib, b.points)
        np.testing.assert_array_equal(fa, fb)
        assert np.abs(pa[fa] - pb[fb]).max() < 1e-3
    if poses:
        np.testing.assert_allclose(got.cam_poses[0], np.eye(4), atol=1e-12)  # KITTI: frame 0 at the origin
        world = expected_lidar_world(src, spec)[list(frames)]
        want = np.linalg.inv(world[0])[None] @ world
        np.testing.assert_allclose(got.poses, want, atol=1e-6)
    else:
        assert not got.has_poses
    assert src.times is not None and got.times is not None
    np.testing.assert_allclose(got.times, src.times[list(frames)] - src.times[frames[0]], atol=1e-9)


# ================================================================================== round trips
@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_round_trip_points_images_calibration_poses_times(
    demo: KittiSequence, tmp_path: Path, kind: str
) -> None:
    spec = BagSpec(kind=kind, moving_map=True)
    got, summary = do_import(demo, tmp_path, spec)
    assert_same_sequence(got, demo, range(len(demo)), spec)
    # Tr went through quaternions on /tf_static (three edges, via base_link): equal to rounding.
    np.testing.assert_allclose(got.calib.Tr, demo.calib.Tr, atol=1e-9)
    np.testing.assert_array_equal(got.calib.P2, demo.calib.P2)
    assert summary.frames == summary.scans == len(demo) and summary.no_camera == summary.no_pose == 0
    assert summary.calib_source == "CameraInfo /camera/camera_info + /tf_static velodyne → camera_optical"
    assert summary.pose_source == "/tf map → velodyne"
    assert got.pose_source == "file"
    assert sorted(p.name for p in got.root.iterdir()) == [
        "calib.txt",
        "image_2",
        "poses.txt",
        "times.txt",
        "velodyne",
    ]


@pytest.mark.parametrize(
    "spec",
    [
        BagSpec(fields=(("intensity", "f4"), ("z", "f4"), ("x", "f4"), ("y", "f4")), pad=4),
        BagSpec(
            kind="sqlite3",
            fields=(("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f8")),
            bigendian=True,
        ),
        BagSpec(
            kind="ros1",
            fields=(("y", "f4"), ("x", "f4"), ("z", "f4"), ("intensity", "u2")),
            height=4,
            nan_every=7,
        ),
    ],
    ids=["reordered-padded", "float64-bigendian", "uint16-organised-nan"],
)
def test_field_order_dtype_padding_and_nan_points(demo: KittiSequence, tmp_path: Path, spec: BagSpec) -> None:
    got, summary = do_import(demo, tmp_path, spec)
    int_inten = dict(spec.fields)["intensity"] == "u2"
    for k in range(len(demo)):
        a, b = got.frame(k).points, demo.frame(k).points
        np.testing.assert_array_equal(a[:, :3], b[:, :3])
        np.testing.assert_allclose(a[:, 3], b[:, 3], atol=0.5 / 65535 + 1e-7 if int_inten else 1e-7)
    if spec.nan_every or spec.height > 1:
        assert summary.nan_points > 0 and f"{summary.nan_points} non-finite points dropped" in summary.line()


def test_uint8_intensity_is_scaled_to_remission() -> None:
    m = Msgs(ros1=False)
    pts = np.array([[1, 2, 3, 0.0], [4, 5, 6, 1.0], [7, 8, 9, 0.5]], np.float32)
    msg = m.cloud(0, pts, BagSpec(fields=(("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u1"))))
    out, nan, has = pointcloud_xyzi(msg)
    assert has and nan == 0
    np.testing.assert_allclose(out[:, 3], [0.0, 1.0, 128 / 255], atol=1e-7)
    without = m.cloud(0, pts, BagSpec(fields=(("x", "f4"), ("y", "f4"), ("z", "f4"))))
    out, _, has = pointcloud_xyzi(without)
    assert not has and (out[:, 3] == 0).all()
    np.testing.assert_array_equal(out[:, :3], pts[:, :3])


@pytest.mark.parametrize("image", ["bgr8", "mono8", "jpeg", "png"])
def test_image_encodings(demo: KittiSequence, tmp_path: Path, image: str) -> None:
    got, _ = do_import(demo, tmp_path, BagSpec(image=image))
    for k in range(len(demo)):
        src = demo.frame(k).image
        if image == "mono8":
            want = np.repeat(src[:, :, :1], 3, axis=2)
        elif image == "jpeg":
            _, buf = cv2.imencode(".jpg", cv2.cvtColor(src, cv2.COLOR_RGB2BGR))
            want = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            assert got.image_path(k) is not None and got.image_path(k).read_bytes() == buf.tobytes()  # type: ignore[union-attr]
        else:
            want = src
        np.testing.assert_array_equal(got.frame(k).image, want)


# =============================================================================== pairing and drops
def test_more_camera_topics_make_a_rig(tmp_path: Path) -> None:
    """``--camera-topic`` twice: the second camera's frames go to their own folder, calibrated from its
    CameraInfo and /tf_static, and project as the source rig's camera does; a frame without its image keeps
    the scan."""
    src = KittiSequence(generate_sequence(tmp_path / "demo2", replace(DEMO, frames=3, cameras=2)).path)
    spec = BagSpec(rear=True)
    got, summary = do_import(src, tmp_path, spec, more_camera_topics=("/rear/image_raw",))
    assert [c.name for c in got.cameras] == ["image_2", "rear_image_raw"]
    assert len(got) == 3 and "1 frames without a /rear/image_raw image" in summary.line()
    for i in range(3):
        a, b = got.frame(i, 1), src.frame(i, 1)
        assert a.has_image == (i != 1)
        if a.has_image:
            np.testing.assert_array_equal(a.image, b.image)
        (pa, fa), (pb, fb) = pixels(a.calib, a.points), pixels(b.calib, b.points)
        np.testing.assert_array_equal(fa, fb)
        assert np.abs(pa[fa] - pb[fb]).max() < 1e-3
        np.testing.assert_array_equal(got.frame(i).image, src.frame(i).image)


def test_pair_nearest_hand_computed() -> None:
    # scans at 0, 100, 200, 300 ms; cameras (unsorted) at 290, 40, 95, 160 ms; max offset 50 ms.
    ms = 1_000_000
    got = pair_nearest(np.array([0, 100, 200, 300]) * ms, np.array([290, 40, 95, 160]) * ms, 50 * ms)
    # 0 → 40 (40 ms); 100 → 95; 200 → 160 (40 ms); 300 → 290.
    np.testing.assert_array_equal(got, [1, 2, 3, 0])
    assert pair_nearest(np.array([0]), np.array([51 * ms]), 50 * ms).tolist() == [-1]
    assert pair_nearest(np.array([0]), np.array([], np.int64), 50 * ms).tolist() == [-1]


def test_scans_without_a_camera_partner_are_dropped_and_counted(demo: KittiSequence, tmp_path: Path) -> None:
    # Scans 100 ms apart. Frame 2's camera frame is missing (nearest others: 120 and 149 ms away); frame
    # 4's is 70 ms early, so 30 ms after scan 3, which still takes its own (20 ms).
    spec = BagSpec(camera_offsets_ms=(10, -49, None, 20, -70))
    got, summary = do_import(demo, tmp_path, spec)
    assert summary.scans == 5 and summary.frames == 3 and summary.no_camera == 2
    assert "dropped 2 without a camera frame within the maximum offset" in summary.line()
    assert_same_sequence(got, demo, [0, 1, 3], spec)
    wide, summary = do_import(demo, tmp_path / "wide", spec, max_offset_ms=100)
    assert summary.frames == 4 and summary.no_camera == 1
    assert_same_sequence(wide, demo, [0, 1, 3, 4], spec)


def test_scans_outside_tf_are_dropped_and_counted(demo: KittiSequence, tmp_path: Path) -> None:
    spec = BagSpec(tf_start_frame=2)
    got, summary = do_import(demo, tmp_path, spec)
    assert summary.no_pose == 2 and summary.frames == 3
    assert_same_sequence(got, demo, [2, 3, 4], spec)


def test_fixed_frame_option(demo: KittiSequence, tmp_path: Path) -> None:
    # Poses in odom instead of the tree's root (map): the drifting map → odom edge no longer enters.
    got, summary = do_import(demo, tmp_path, BagSpec(moving_map=True), fixed_frame="odom")
    assert summary.pose_source == "/tf odom → velodyne"
    assert_same_sequence(got, demo, range(len(demo)), BagSpec(moving_map=False))
    with pytest.raises(DatasetError) as err:
        do_import(demo, tmp_path / "bad", BagSpec(), fixed_frame="camera_link")
    assert (
        "fixed frame 'camera_link' is not above the LiDAR frame in /tf and /tf_static (its chain: "
        "velodyne → base_link → odom → map)" in str(err.value)
    )


def test_without_tf_there_are_no_poses(demo: KittiSequence, tmp_path: Path) -> None:
    got, summary = do_import(demo, tmp_path, BagSpec(tf=False))
    assert summary.pose_source is None and "no poses in the bag" in summary.line()
    assert not (got.root / "poses.txt").exists() and got.pose_source == "missing"
    assert summary.frames == 5


# ================================================================================== calibration
def write_yaml_calib(
    path: Path, calib: Calib, *, camera: bool = True, extrinsic: str | None = "matrix"
) -> Path:
    def nums(a: np.ndarray) -> str:
        return "[" + ", ".join(repr(float(v)) for v in a.ravel()) + "]"

    lines = []
    if camera:
        lines += ["camera:", f"  P: {nums(calib.P2)}"]
    if extrinsic == "matrix":
        lines += ["lidar_to_camera:", f"  matrix: {nums(calib.Tr[:3])}"]
    elif extrinsic == "quaternion":
        q = Rotation.from_matrix(calib.Tr[:3, :3]).as_quat()
        lines += ["lidar_to_camera:", f"  translation: {nums(calib.Tr[:3, 3])}", f"  rotation: {nums(q)}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_calibration_from_yaml_when_the_bag_has_none(demo: KittiSequence, tmp_path: Path) -> None:
    spec = BagSpec(camera_info=False, tf_static=False)
    yml = write_yaml_calib(tmp_path / "calib.yaml", demo.calib, extrinsic="quaternion")
    got, summary = do_import(demo, tmp_path, spec, calib_file=yml)
    assert summary.calib_source == f"{yml} (camera) + {yml} (lidar_to_camera)"
    # /tf moves base_link, but without /tf_static nothing ties the LiDAR frame to it: no poses.
    assert summary.pose_source is None
    assert_same_sequence(got, demo, range(len(demo)), spec, poses=False)


def test_yaml_gives_the_part_the_bag_lacks(demo: KittiSequence, tmp_path: Path) -> None:
    spec = BagSpec(tf_static=False, tf=False)
    yml = write_yaml_calib(tmp_path / "calib.yaml", demo.calib, camera=False)
    got, summary = do_import(demo, tmp_path, spec, calib_file=yml)
    assert summary.calib_source == f"CameraInfo /camera/camera_info + {yml} (lidar_to_camera)"
    np.testing.assert_array_equal(got.calib.Tr, demo.calib.Tr)


def test_missing_calibration_names_what_is_missing(demo: KittiSequence, tmp_path: Path) -> None:
    with pytest.raises(DatasetError) as err:
        do_import(demo, tmp_path, BagSpec(camera_info=False, tf_static=False, tf=False))
    msg = str(err.value)
    assert (
        "missing calibration: camera intrinsics (no sensor_msgs/CameraInfo topic for camera frame "
        "'camera_optical')" in msg
    )
    assert "LiDAR → camera transform (no /tf_static chain from 'velodyne' to 'camera_optical'" in msg
    assert "--calib FILE" in msg
    assert not (tmp_path / "out" / "sequences" / "00").exists()


def test_camera_info_for_another_image_size_is_refused(demo: KittiSequence, tmp_path: Path) -> None:
    h, w = demo.frame(0).image.shape[:2]
    with pytest.raises(DatasetError) as err:
        do_import(demo, tmp_path, BagSpec(info_pad=2))
    assert (
        f"CameraInfo on /camera/camera_info is for {w}×{h + 2} images, /camera/image_raw has {w}×{h}"
        in str(err.value)
    )


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("camera:\n  P: [1, 2, 3]\n", "'camera.P' has 3 values, expected 12"),
        ("camera:\n  Q: [1]\n", "'camera.Q' is not a known key (K, P)"),
        ("lidar_to_camera:\n  translation: [0, 0, 0]\n", "needs 'translation' and 'rotation'"),
        ("lidar_to_camera:\n  translation: [0, 0, 0]\n  rotation: [0, 0, 0, 0]\n", "zero quaternion"),
        ("camera:\n  K: [1, 0, 0, 0, 1, 0, 0, 0, .nan]\n", "'camera.K' has non-finite values"),
        ("extrinsics: {}\n", "'extrinsics' is not a known key"),
        ("camera: [\n", "not valid YAML"),
    ],
)
def test_bad_calibration_yaml_names_file_and_key(tmp_path: Path, text: str, problem: str) -> None:
    path = tmp_path / "calib.yaml"
    path.write_text(text)
    with pytest.raises(DatasetError, match=str(path)) as err:
        read_calib_file(path)
    assert problem in str(err.value)


def test_calib_yaml_k_form_and_kitti_txt(demo: KittiSequence, tmp_path: Path) -> None:
    path = tmp_path / "k.yaml"
    path.write_text("camera:\n  K: [50, 0, 32, 0, 60, 24, 0, 0, 1]\n")
    got = read_calib_file(path)
    assert got.Tr is None and got.P2 is not None
    np.testing.assert_array_equal(got.P2, [[50, 0, 32, 0], [0, 60, 24, 0], [0, 0, 1, 0]])
    kitti = read_calib_file(demo.root / "calib.txt")
    assert kitti.P2 is not None and kitti.Tr is not None
    np.testing.assert_array_equal(kitti.Tr, demo.calib.Tr)


# =================================================================================== bad input
def test_missing_topic_names_it_and_lists_the_topics(demo: KittiSequence, tmp_path: Path) -> None:
    bag = write_bag(demo, tmp_path / "rec")
    cfg = RosbagImportConfig(lidar_topic="/points", camera_topic="/camera/image_raw")
    with pytest.raises(DatasetError) as err:
        import_rosbag(bag, tmp_path / "out", cfg)
    msg = str(err.value)
    assert msg.startswith(f"{bag}: no LiDAR topic '/points'; topics in the bag: ")
    assert "/velodyne_points (sensor_msgs/msg/PointCloud2)" in msg and "/tf (tf2_msgs/msg/TFMessage)" in msg
    wrong = replace(cfg, lidar_topic="/velodyne_points", camera_topic="/camera/camera_info")
    with pytest.raises(DatasetError, match="topic '/camera/camera_info' carries sensor_msgs/msg/CameraInfo"):
        import_rosbag(bag, tmp_path / "out", wrong)


@pytest.mark.parametrize("kind", ["ros1", "mcap", "sqlite3"])
def test_corrupt_bag_names_the_file(demo: KittiSequence, tmp_path: Path, kind: str) -> None:
    spec = BagSpec(kind=kind)
    bag = write_bag(demo, bag_path(tmp_path, spec), spec)
    target = bag if kind == "ros1" else next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
    data = target.read_bytes()
    target.write_bytes(data[: len(data) // 3])  # cut short, as by a full disk or a killed recorder
    cfg = RosbagImportConfig(lidar_topic="/velodyne_points", camera_topic="/camera/image_raw")
    with pytest.raises(DatasetError, match=f"^{target if kind == 'ros1' else bag}: cannot read the bag"):
        import_rosbag(bag, tmp_path / "out", cfg)
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match=f"^{garbage}: cannot read the bag"):
        import_rosbag(garbage, tmp_path / "out", cfg)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_damaged_bag_content_names_the_bag(demo: KittiSequence, tmp_path: Path, kind: str) -> None:
    """A bag that still opens but whose content is damaged: the error comes from reading its messages
    (sqlite3 storage: the header of a page in the middle overwritten, an apsw.CorruptError; mcap:
    the message type's name made invalid UTF-8, a decoding error), still one line naming the bag."""
    spec = BagSpec(kind=kind)
    bag = write_bag(demo, bag_path(tmp_path, spec), spec)
    target = next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
    data = bytearray(target.read_bytes())
    if kind == "sqlite3":
        page = int.from_bytes(data[16:18], "big")
        start = len(data) // 2 // page * page  # a page of the messages table
        data[start : start + 8] = b"\xff" * 8
    else:
        name = b"sensor_msgs/msg/PointCloud2"
        data = bytearray(bytes(data).replace(name, b"\xff" * len(name)))
    target.write_bytes(bytes(data))
    cfg = RosbagImportConfig(lidar_topic="/velodyne_points", camera_topic="/camera/image_raw")
    with pytest.raises(DatasetError, match=f"^{bag}: cannot read the bag"):
        import_rosbag(bag, tmp_path / "out", cfg)
    assert not (tmp_path / "out").exists()


def test_refuses_a_non_empty_output_without_force(demo: KittiSequence, tmp_path: Path) -> None:
    bag = write_bag(demo, tmp_path / "rec")
    out = tmp_path / "seq"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    cfg = RosbagImportConfig(lidar_topic="/velodyne_points", camera_topic="/camera/image_raw")
    with pytest.raises(DatasetError, match="output folder is not empty"):
        import_rosbag(bag, out, cfg)
    # Refused before the bag is read (a long bag is not read for nothing).
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(b"not a bag")
    with pytest.raises(DatasetError, match=f"^{out}: output folder is not empty"):
        import_rosbag(garbage, out, cfg)
    assert (out / "mine.txt").read_text() == "keep"
    # --force re-imports over a previous import, never over a user's other files.
    with pytest.raises(DatasetError, match=r"'mine\.txt', which an import does not write"):
        import_rosbag(bag, out, cfg, force=True)
    assert (out / "mine.txt").read_text() == "keep"
    (out / "mine.txt").unlink()
    import_rosbag(bag, out, cfg)
    import_rosbag(bag, out, cfg, force=True)
    assert len(KittiSequence(out)) == 5
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folders left


def test_cli_imports_and_prints_one_summary_line(demo: KittiSequence, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli

    bag = write_bag(demo, tmp_path / "rec.bag", BagSpec(kind="ros1", tf=False))
    out = tmp_path / "seq"
    runner = CliRunner()
    res = runner.invoke(
        cli,
        [
            "import",
            "rosbag",
            str(bag),
            "--lidar-topic",
            "/velodyne_points",
            "--camera-topic",
            "/camera/image_raw",
            "--out",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith(f"wrote 5 frames of 5 scans to {out} (none dropped)")
    assert f"estimate them with `leap poses {out}`" in last
    assert len(KittiSequence(out)) == 5
    bad = runner.invoke(
        cli,
        [
            "import",
            "rosbag",
            str(bag),
            "--lidar-topic",
            "/nope",
            "--camera-topic",
            "/camera/image_raw",
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert bad.exit_code == 2 and "no LiDAR topic '/nope'" in bad.output
    again = runner.invoke(
        cli,
        [
            "import",
            "rosbag",
            str(bag),
            "--lidar-topic",
            "/velodyne_points",
            "--camera-topic",
            "/camera/image_raw",
            "--out",
            str(out),
        ],
    )
    assert again.exit_code == 2 and "pass --force" in again.output


# ================================================================================== acceptance
@pytest.mark.slow
def test_imported_bags_label_like_the_source_frames(
    demo: KittiSequence, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """End to end: bags (ROS 2 mcap and ROS 1) written from demo frames with CameraInfo,
    /tf_static and /tf poses, imported, then `leap run --labeler grounded-sam` with the tiny test models:
    the same label on >= 99.9 % of points as the same run on the source frames."""
    from typer.testing import CliRunner

    from app.cli import cli
    from leap_core.datasets.kitti import read_label
    from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
    from leap_core.schema import ClassDef, Schema, save_schema

    models = make_tiny_models(tmp_path_factory.mktemp("models"), TinyModelsConfig(num_queries=12)).models_dir
    schema = Schema(
        "small",
        (
            ClassDef("car", (255, 0, 0), ("car", "automobile"), 10),
            ClassDef("road", (0, 0, 255), ("road", "street"), 40),
            ClassDef("building", (0, 255, 0), ("building", "house"), 50),
        ),
    )
    project = tmp_path / "small.yaml"
    # A low box threshold: the random-weight detector's boxes must label a good share of the points.
    save_schema(schema, project, pipeline={"grounded_sam": {"box_threshold": 0.05, "mode": "per-class"}})
    runner = CliRunner()

    def run(seq: Path, out: Path) -> list[np.ndarray]:
        res = runner.invoke(
            cli,
            [
                "run",
                str(seq),
                "--out",
                str(out),
                "--project-file",
                str(project),
                "--labeler",
                "grounded-sam",
                "--models",
                str(models),
                "--device",
                "cpu",
            ],
        )
        assert res.exit_code == 0, res.output
        return [read_label(folder(out, seq.name) / "export" / f"{i:06d}.label") for i in range(len(demo))]

    source = run(demo.root, tmp_path / "run-source")
    labeled = np.concatenate(source) > 0
    assert labeled.mean() > 0.1  # not a comparison of two empty exports (measured: 16 % labeled)
    for kind in ("mcap", "ros1"):
        spec = BagSpec(kind=kind)
        bag = write_bag(demo, bag_path(tmp_path, spec, f"demo-{kind}"), spec)
        out = tmp_path / f"import-{kind}" / "sequences" / "00"
        res = runner.invoke(
            cli,
            [
                "import",
                "rosbag",
                str(bag),
                "--lidar-topic",
                "/velodyne_points",
                "--camera-topic",
                "/camera/image_raw",
                "--out",
                str(out),
            ],
        )
        assert res.exit_code == 0, res.output
        got = run(out, tmp_path / f"run-{kind}")
        same = np.concatenate([a == b for a, b in zip(got, source, strict=True)])
        print(f"{kind}: same label on {100 * same.mean():.3f} % of {same.size} points")
        assert same.mean() >= 0.999, (kind, same.mean())
