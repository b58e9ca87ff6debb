"""ROS 1 / ROS 2 bags → the KITTI layout (``leap import rosbag``; docs/IMPORT.md).

Bags are read through the ``rosbags`` package (``AnyReader``: ROS 1 ``.bag``, ROS 2 sqlite3 ``.db3`` and
``.mcap``, with the message definitions the bag carries, else the ROS 2 Humble / ROS 1 Noetic typestore).

What is read:
- ``sensor_msgs/PointCloud2`` on the LiDAR topic: fields ``x``, ``y``, ``z`` and ``intensity`` at any offset
  and of any PointField datatype, either byte order, any ``point_step`` / ``row_step`` padding; points with a
  non-finite coordinate are dropped. Remission = a float intensity as recorded, an integer intensity divided
  by its type's maximum (``uint8`` 255 → 1.0), 0 without an intensity field.
- ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8, mono16, 8UC1, 8UC3) or
  ``sensor_msgs/CompressedImage`` (JPEG / PNG) on the camera topic. Raw images are written as PNG;
  compressed ones keep their bytes.
- Each scan takes the camera frame with the nearest header stamp if it lies within ``max_offset_ms``;
  other scans are dropped (and counted).
- Calibration: ``P2`` = ``sensor_msgs/CameraInfo.P``, ``Tr`` = the LiDAR → camera optical frame transform
  on ``/tf_static``; a YAML file (``--calib``) gives either or both instead.
- Poses: when ``/tf`` moves the LiDAR frame (a chain of transforms from a fixed frame, static and dynamic
  edges mixed), the LiDAR pose at each scan stamp (translation linear, rotation slerp between the two
  nearest samples of every dynamic edge), written in KITTI's camera frame: ``P_i = Tr · L_0⁻¹ · L_i · Tr⁻¹``.

The output is written into a fresh hidden sibling folder and renamed into place at the end, so an
interrupted import never leaves a half-written sequence.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import yaml
from scipy.spatial.transform import Rotation, Slerp

from leap_core.datasets.kitti import Calib, read_calib, write_calib, write_image, write_poses, write_scan
from leap_core.datasets.rig import MAX_CAMERAS, RIG_FILE, Camera, camera_name_problem, camera_rig_text
from leap_core.errors import ConfigError, DatasetError, LeapError
from leap_core.extras import MissingExtra
from leap_core.importers.folder import IMPORT_ENTRIES, check_output, staged_output
from leap_core.io_utils import atomic_write_bytes
from leap_core.progress import ProgressFn, report

try:  # the ros extra: only `leap import rosbag` imports this module
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore
except ModuleNotFoundError as exc:
    raise MissingExtra("ros", exc.name) from None
try:  # rosbags' sqlite3 reader, after rosbags: without the extra the message names rosbags, not this
    import apsw
except ModuleNotFoundError as exc:
    raise MissingExtra("ros", exc.name) from None

F64 = npt.NDArray[np.float64]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

#: sensor_msgs/PointField datatype → numpy type code (INT8 .. FLOAT64).
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@dataclass(frozen=True)
class RosbagImportConfig:
    """What ``leap import rosbag`` reads from a bag."""

    lidar_topic: str
    """Topic of the ``sensor_msgs/PointCloud2`` scans."""
    camera_topic: str
    """Topic of the ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` frames."""
    camera_info_topic: str | None = None
    """Topic of the camera's ``sensor_msgs/CameraInfo``; None = the CameraInfo topic whose frame is the
    images' frame (or the only one in the bag)."""
    calib_file: Path | None = None
    """YAML calibration (docs/IMPORT.md) or a KITTI ``calib.txt``; what it gives wins over the bag's."""
    max_offset_ms: float = 50.0
    """Largest difference between a scan's stamp and its camera frame's stamp (milliseconds)."""
    fixed_frame: str | None = None
    """Frame the poses are taken in; None = the root of the LiDAR frame's ``/tf`` tree."""
    more_camera_topics: tuple[str, ...] = ()
    """Further cameras of a rig (docs/IMPORT.md, "Several cameras"): image topics whose frames are written
    into a folder named after the topic (:func:`camera_folder`), calibrated from the bag (their
    ``CameraInfo`` and ``/tf_static``); a scan without a frame of such a camera within ``max_offset_ms`` is
    kept, without that camera's image."""

    def __post_init__(self) -> None:
        for name in ("lidar_topic", "camera_topic"):
            if not getattr(self, name).strip():
                raise ConfigError("must name a topic", field=(name,))
        topics = [self.camera_topic, *self.more_camera_topics]
        for k, topic in enumerate(self.more_camera_topics):
            if not topic.strip():
                raise ConfigError("must name a topic", field=("more_camera_topics", str(k)))
            if topics.index(topic) != k + 1:
                raise ConfigError(
                    f"camera topic {topic!r} is given twice", field=("more_camera_topics", str(k))
                )
        if len(topics) > MAX_CAMERAS:
            raise ConfigError(
                f"{len(topics)} cameras; a rig holds at most {MAX_CAMERAS}", field=("more_camera_topics",)
            )
        if not (math.isfinite(self.max_offset_ms) and self.max_offset_ms >= 0):
            raise ConfigError(
                f"must be a finite number >= 0, got {self.max_offset_ms}", field=("max_offset_ms",)
            )


@dataclass
class ImportSummary:
    """What an import wrote and dropped (``line()`` is the CLI's one-line summary)."""

    out: Path
    frames: int = 0
    scans: int = 0
    no_camera: int = 0
    """Scans without a camera frame within the maximum offset."""
    no_pose: int = 0
    """Scans outside the time span ``/tf`` covers (only when the bag has poses)."""
    empty: int = 0
    """Scans with no finite point."""
    nan_points: int = 0
    calib_source: str = ""
    pose_source: str | None = None
    """Where the poses came from; None = no poses.txt written."""
    notes: list[str] = field(default_factory=list)

    def line(self) -> str:
        dropped = [
            f"{n} {why}"
            for n, why in (
                (self.no_camera, "without a camera frame within the maximum offset"),
                (self.no_pose, "outside the time span of /tf"),
                (self.empty, "without a finite point"),
            )
            if n
        ]
        text = f"wrote {self.frames} frames of {self.scans} scans to {self.out}"
        text += f" (dropped {', '.join(dropped)})" if dropped else " (none dropped)"
        text += f"; calibration from {self.calib_source}"
        if self.pose_source is not None:
            text += f"; poses from {self.pose_source}"
        else:
            text += "; no poses in the bag (no poses.txt)"
        if self.nan_points:
            text += f"; {self.nan_points} non-finite points dropped"
        return "; ".join([text, *self.notes])


# ------------------------------------------------------------------------------------- point clouds
def pointcloud_xyzi(msg: Any) -> tuple[npt.NDArray[np.float32], int, bool]:
    """Points of a ``sensor_msgs/PointCloud2`` as (N, 4) float32 x, y, z, remission.

    Each field is read at its ``offset`` with its PointField datatype and the message's byte order, row by
    row of ``row_step`` bytes (``width · point_step`` of them used), so padding anywhere is skipped.
    Remission: float intensity as is, integer intensity / its type's maximum, 0 when absent.

    Returns:
        (points, number of points dropped for a non-finite coordinate, whether an intensity field exists).

    Raises:
        ValueError: a missing x/y/z field, an unknown datatype, or a data size that does not match.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        listed = ", ".join(fields) or "none"
        raise ValueError(f"PointCloud2 has no field {', '.join(missing)} (fields: {listed})")
    order = ">" if msg.is_bigendian else "<"
    wanted = ["x", "y", "z"] + (["intensity"] if "intensity" in fields else [])
    names: list[str] = []
    formats: list[str] = []
    offsets: list[int] = []
    for name in wanted:
        f = fields[name]
        code = POINTFIELD_TYPES.get(int(f.datatype))
        if code is None:
            raise ValueError(f"PointCloud2 field {name!r} has unknown datatype {f.datatype}")
        names.append(name)
        formats.append(order + code)
        offsets.append(int(f.offset))
    step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    data = np.asarray(msg.data, dtype=np.uint8)
    row_step = int(msg.row_step) if height > 1 else width * step
    if width * step > row_step or data.size < (height - 1) * row_step + width * step:
        raise ValueError(
            f"PointCloud2 data has {data.size} bytes, too few for {height}×{width} points of {step} bytes "
            f"(row_step {msg.row_step})"
        )
    rows = [data[r * row_step : r * row_step + width * step] for r in range(height)]
    records = np.concatenate(rows).view(dtype) if rows else np.zeros(0, dtype)
    out = np.zeros((records.shape[0], 4), np.float32)
    for i, name in enumerate(("x", "y", "z")):
        out[:, i] = records[name]
    has_intensity = "intensity" in fields
    if has_intensity:
        inten = records["intensity"]
        if np.issubdtype(inten.dtype, np.integer):
            out[:, 3] = inten.astype(np.float64) / np.iinfo(inten.dtype).max
        else:
            out[:, 3] = inten
        out[~np.isfinite(out[:, 3]), 3] = 0.0
    keep = np.isfinite(out[:, :3]).all(axis=1)
    return np.ascontiguousarray(out[keep]), int((~keep).sum()), has_intensity


# ------------------------------------------------------------------------------------------- images
_CHANNELS = {
    "rgb8": 3,
    "bgr8": 3,
    "8uc3": 3,
    "rgba8": 4,
    "bgra8": 4,
    "mono8": 1,
    "8uc1": 1,
    "mono16": 1,
    "16uc1": 1,
}


def image_rgb(msg: Any) -> npt.NDArray[np.uint8]:
    """A ``sensor_msgs/Image`` as (H, W, 3) uint8 RGB (rows of ``step`` bytes; 16-bit keeps the high byte).

    Raises:
        ValueError: an unsupported encoding or a data size that does not match.
    """
    enc = str(msg.encoding).lower()
    if enc not in _CHANNELS:
        raise ValueError(f"image encoding {msg.encoding!r} is not supported ({', '.join(_CHANNELS)})")
    h, w, ch = int(msg.height), int(msg.width), _CHANNELS[enc]
    depth = 2 if enc in ("mono16", "16uc1") else 1
    step = int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * ch * depth or data.size < (h - 1) * step + w * ch * depth:
        raise ValueError(
            f"image data has {data.size} bytes, too few for {h}×{w} {msg.encoding} (step {step})"
        )
    rows = np.lib.stride_tricks.as_strided(data, (h, w * ch * depth), (step, 1))
    if depth == 2:
        px = rows.copy().view(">u2" if msg.is_bigendian else "<u2")
        rows = (px >> 8).astype(np.uint8)
    img = np.ascontiguousarray(rows).reshape(h, w, ch)
    if ch == 1:
        return np.repeat(img, 3, axis=2)
    # cv_bridge reads 8UC3 as BGR too.
    if enc in ("bgr8", "8uc3", "bgra8"):
        img = img[:, :, [2, 1, 0]]
    return np.ascontiguousarray(img[:, :, :3])


def compressed_image(msg: Any) -> tuple[npt.NDArray[np.uint8], bytes, str]:
    """A ``sensor_msgs/CompressedImage``: (RGB pixels, its bytes, ``.jpg`` or ``.png``).

    Raises:
        ValueError: the bytes are not a JPEG or PNG image.
    """
    raw = np.asarray(msg.data, dtype=np.uint8)
    img = cv2.imdecode(raw, cv2.IMREAD_COLOR) if raw.size else None
    if img is None:
        raise ValueError(f"CompressedImage (format {msg.format!r}) does not decode as JPEG or PNG")
    suffix = ".png" if raw[:4].tobytes() == b"\x89PNG" else ".jpg"
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8), raw.tobytes(), suffix


# --------------------------------------------------------------------------------------- transforms
def transform_matrix(translation: npt.ArrayLike, quat_xyzw: npt.ArrayLike) -> F64:
    """(4, 4) homogeneous transform from a translation and a (normalised) ROS quaternion (x, y, z, w)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(np.asarray(quat_xyzw, np.float64)).as_matrix()
    m[:3, 3] = translation
    return m


def _frame(name: str) -> str:
    # ROS 1 frames often carry a leading slash that tf2 ignores.
    return str(name).lstrip("/")


@dataclass
class _Edge:
    """Samples of one parent → child transform: times (ns, sorted), translations (T, 3), quats (T, 4)."""

    times: list[int] = field(default_factory=list)
    trans: list[list[float]] = field(default_factory=list)
    quats: list[list[float]] = field(default_factory=list)


class TfTree:
    """The transform tree of a bag's ``/tf_static`` (static) and ``/tf`` (dynamic) messages.

    An edge maps child-frame coordinates into its parent: ``p_parent = T · p_child``.
    """

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, F64] = {}
        self.dynamic: dict[str, _Edge] = {}

    def add(self, msg: Any, *, static: bool) -> None:
        """Add every ``geometry_msgs/TransformStamped`` of a ``tf2_msgs/TFMessage``."""
        for tf in msg.transforms:
            child, parent = _frame(tf.child_frame_id), _frame(tf.header.frame_id)
            t, q = tf.transform.translation, tf.transform.rotation
            self.parent[child] = parent
            if static:
                self.static[child] = transform_matrix((t.x, t.y, t.z), (q.x, q.y, q.z, q.w))
            else:
                edge = self.dynamic.setdefault(child, _Edge())
                edge.times.append(stamp_ns(tf.header))
                edge.trans.append([t.x, t.y, t.z])
                edge.quats.append([q.x, q.y, q.z, q.w])

    def frames(self) -> list[str]:
        return sorted(set(self.parent) | set(self.parent.values()))

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root (a cycle ends the walk)."""
        out = [frame]
        while out[-1] in self.parent and self.parent[out[-1]] not in out:
            out.append(self.parent[out[-1]])
        return out

    def is_moving(self, frame: str, root: str) -> bool:
        """True when a dynamic edge lies between ``frame`` and its ancestor ``root``."""
        path = self.chain(frame)
        return any(f in self.dynamic for f in path[: path.index(root)])

    def to_ancestor(
        self, frame: str, ancestor: str, times_ns: npt.NDArray[np.int64]
    ) -> tuple[F64, npt.NDArray[np.bool_]]:
        """(T, 4, 4) transforms ``ancestor ← frame`` at ``times_ns`` and a (T,) mask of the times every
        dynamic edge on the way covers (outside its samples there is no extrapolation)."""
        n = len(times_ns)
        out = np.tile(np.eye(4), (n, 1, 1))
        valid = np.ones(n, bool)
        path = self.chain(frame)
        for child in path[: path.index(ancestor)]:
            if child in self.dynamic:
                mats, ok = _interpolate(self.dynamic[child], times_ns)
                valid &= ok
            else:
                mats = np.broadcast_to(self.static[child], (n, 4, 4))
            out = mats @ out
        return out, valid

    def lookup_static(self, target: str, source: str) -> F64 | None:
        """``target ← source`` through static edges only (None when they do not connect the two)."""
        up_s, up_t = self.chain(source), self.chain(target)
        common = next((f for f in up_s if f in up_t), None)
        if common is None:
            return None
        below = up_s[: up_s.index(common)] + up_t[: up_t.index(common)]
        if any(f in self.dynamic for f in below):
            return None
        stamp = np.zeros(1, np.int64)
        a_s, _ = self.to_ancestor(source, common, stamp)
        a_t, _ = self.to_ancestor(target, common, stamp)
        return np.asarray(np.linalg.inv(a_t[0]) @ a_s[0], np.float64)


def _interpolate(edge: _Edge, times_ns: npt.NDArray[np.int64]) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Transforms of a dynamic edge at ``times_ns``: translation linear and rotation slerp between the two
    samples around each time; (mask of times inside the sampled span)."""
    t_all = np.asarray(edge.times, np.int64)
    order = np.argsort(t_all, kind="stable")
    t_sorted, first = np.unique(t_all[order], return_index=True)  # one sample per stamp
    idx = order[first]
    ref = int(t_sorted[0])
    # Seconds relative to the first sample: float64 keeps nanoseconds over days.
    ts = (t_sorted - ref).astype(np.float64) * 1e-9
    tq = (np.asarray(times_ns, np.int64) - ref).astype(np.float64) * 1e-9
    trans = np.asarray(edge.trans, np.float64)[idx]
    rots = Rotation.from_quat(np.asarray(edge.quats, np.float64)[idx])
    valid = (tq >= ts[0]) & (tq <= ts[-1])
    tc = np.clip(tq, ts[0], ts[-1])
    out = np.tile(np.eye(4), (len(tq), 1, 1))
    if len(ts) == 1:
        out[:, :3, :3] = rots.as_matrix()[0]
        out[:, :3, 3] = trans[0]
    else:
        out[:, :3, :3] = Slerp(ts, rots)(tc).as_matrix()
        out[:, :3, 3] = np.column_stack([np.interp(tc, ts, trans[:, k]) for k in range(3)])
    return out, valid


def stamp_ns(header: Any) -> int:
    """A ``std_msgs/Header`` stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def pair_nearest(scan_ns: npt.ArrayLike, cam_ns: npt.ArrayLike, max_offset_ns: int) -> npt.NDArray[np.int64]:
    """For each scan stamp, the index of the camera stamp nearest to it (ties: the earlier one), or -1
    when none lies within ``max_offset_ns``. Stamps are integer nanoseconds; ``cam_ns`` need not be sorted.
    """
    scans = np.asarray(scan_ns, np.int64)
    cams = np.asarray(cam_ns, np.int64)
    out = np.full(scans.shape, -1, np.int64)
    if cams.size == 0:
        return out
    order = np.argsort(cams, kind="stable")
    sc = cams[order]
    right = np.clip(np.searchsorted(sc, scans), 0, len(sc) - 1)
    left = np.clip(right - 1, 0, len(sc) - 1)
    d_left, d_right = np.abs(scans - sc[left]), np.abs(scans - sc[right])
    best = np.where(d_left <= d_right, left, right)
    ok = np.minimum(d_left, d_right) <= max_offset_ns
    out[ok] = order[best[ok]]
    return out


# ---------------------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class PartialCalib:
    """Calibration parts, each possibly unknown: P2 (3, 4) and Tr (4, 4) LiDAR → camera optical frame."""

    P2: F64 | None = None
    Tr: F64 | None = None


def _numbers(path: Path, key: str, value: object, sizes: tuple[int, ...]) -> F64:
    vals = value if isinstance(value, list) else None
    if vals is None or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        raise DatasetError(path, f"'{key}' must be a list of numbers")
    arr = np.asarray(vals, np.float64)
    if arr.size not in sizes:
        raise DatasetError(path, f"'{key}' has {arr.size} values, expected {' or '.join(map(str, sizes))}")
    if not np.isfinite(arr).all():
        raise DatasetError(path, f"'{key}' has non-finite values")
    return arr


def _section(path: Path, doc: dict[str, Any], name: str, allowed: set[str]) -> dict[str, Any] | None:
    sec = doc.get(name)
    if sec is None:
        return None
    if not isinstance(sec, dict):
        raise DatasetError(path, f"'{name}' must be a mapping")
    unknown = sorted(set(sec) - allowed)
    if unknown:
        raise DatasetError(path, f"'{name}.{unknown[0]}' is not a known key ({', '.join(sorted(allowed))})")
    return sec


def _camera_part(path: Path, cam: dict[str, Any] | None) -> F64 | None:
    """P2 from the YAML ``camera`` section (``P`` 3×4, or ``K`` 3×3 giving ``[K | 0]``)."""
    if cam is None:
        return None
    if ("P" in cam) == ("K" in cam):
        raise DatasetError(path, "'camera' needs exactly one of 'P' (12 values) or 'K' (9 values)")
    if "P" in cam:
        p2 = _numbers(path, "camera.P", cam["P"], (12,)).reshape(3, 4)
    else:
        p2 = np.zeros((3, 4))
        p2[:, :3] = _numbers(path, "camera.K", cam["K"], (9,)).reshape(3, 3)
    if abs(np.linalg.det(p2[:, :3])) < 1e-9:
        raise DatasetError(path, "'camera' projection's left 3×3 block is singular")
    return p2


def _extrinsic_part(path: Path, ext: dict[str, Any] | None) -> F64 | None:
    """Tr from the YAML ``lidar_to_camera`` section (``matrix``, or ``translation`` + ``rotation``)."""
    if ext is None:
        return None
    if "matrix" in ext:
        if set(ext) != {"matrix"}:
            raise DatasetError(
                path, "'lidar_to_camera' takes 'matrix' or 'translation' + 'rotation', not both"
            )
        m = _numbers(path, "lidar_to_camera.matrix", ext["matrix"], (12, 16))
        tr = np.eye(4)
        tr[:3] = m[:12].reshape(3, 4)
        if m.size == 16 and not np.allclose(m[12:], [0, 0, 0, 1]):
            raise DatasetError(path, "'lidar_to_camera.matrix' last row must be 0 0 0 1")
    else:
        if set(ext) != {"translation", "rotation"}:
            raise DatasetError(path, "'lidar_to_camera' needs 'translation' and 'rotation' (or 'matrix')")
        t = _numbers(path, "lidar_to_camera.translation", ext["translation"], (3,))
        q = _numbers(path, "lidar_to_camera.rotation", ext["rotation"], (4,))
        if np.linalg.norm(q) < 1e-9:
            raise DatasetError(path, "'lidar_to_camera.rotation' is a zero quaternion")
        tr = transform_matrix(t, q)
    if abs(np.linalg.det(tr[:3, :3])) < 1e-6:
        raise DatasetError(path, "'lidar_to_camera' rotation is singular")
    return tr


def read_calib_file(path: str | Path) -> PartialCalib:
    """Read ``--calib``: a KITTI ``calib.txt`` (``.txt``: P2 and Tr) or the YAML format of docs/IMPORT.md::

        camera:            # P (3×4 row-major, ROS CameraInfo.P) or K (3×3; P = [K | 0])
          P: [fx, 0, cx, tx, 0, fy, cy, ty, 0, 0, 1, 0]
        lidar_to_camera:   # LiDAR points → camera optical frame (x right, y down, z forward)
          matrix: [...]    # 12 (3×4) or 16 (4×4) row-major,
                           # or translation: [x, y, z] + rotation: [qx, qy, qz, qw]

    Either section may be left out when the bag provides it (CameraInfo, /tf_static).

    Raises:
        DatasetError: naming the file and key for an unreadable file, an unknown key, a wrong count of
            numbers, non-finite values or a singular matrix.
    """
    path = Path(path)
    if path.suffix.lower() == ".txt":
        c = read_calib(path)
        return PartialCalib(P2=c.P2, Tr=c.Tr)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DatasetError(path, f"cannot read calibration ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise DatasetError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(doc, dict):
        raise DatasetError(path, "expected a mapping with 'camera' and/or 'lidar_to_camera'")
    unknown = sorted(set(doc) - {"camera", "lidar_to_camera"})
    if unknown:
        raise DatasetError(path, f"'{unknown[0]}' is not a known key (camera, lidar_to_camera)")
    p2 = _camera_part(path, _section(path, doc, "camera", {"P", "K"}))
    tr = _extrinsic_part(path, _section(path, doc, "lidar_to_camera", {"matrix", "translation", "rotation"}))
    if p2 is None and tr is None:
        raise DatasetError(path, "has neither 'camera' nor 'lidar_to_camera'")
    return PartialCalib(P2=p2, Tr=tr)


# ------------------------------------------------------------------------------------------- reading
# What a damaged bag raises past AnyReader: rosbags' sqlite3 storage reads through apsw (a page that does not
# parse is an apsw.CorruptError), a damaged mcap record can fail to decode (UnicodeDecodeError, a ValueError).
_READ_ERRORS: tuple[type[BaseException], ...] = (
    apsw.Error,
    OSError,
    KeyError,
    ValueError,
    IndexError,
    EOFError,
)


@contextlib.contextmanager
def _open_bag(bag: Path) -> Iterator[Any]:
    """An open ``AnyReader``; any failure to read becomes a DatasetError naming the bag."""
    path = bag.parent if bag.name == "metadata.yaml" else bag
    errors: tuple[type[BaseException], ...] = (AnyReaderError, *_READ_ERRORS)
    try:
        store = get_typestore(Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE)
        reader = AnyReader([path], default_typestore=store)
        reader.open()
    except LeapError:
        raise
    except errors as exc:
        raise DatasetError(bag, f"cannot read the bag ({type(exc).__name__}: {exc})") from None
    try:
        yield reader
    except LeapError:
        raise
    except errors as exc:
        raise DatasetError(bag, f"cannot read the bag ({type(exc).__name__}: {exc})") from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _topic(reader: Any, bag: Path, topic: str, types: tuple[str, ...], what: str) -> list[Any]:
    topics = reader.topics
    available = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
    if topic not in topics:
        raise DatasetError(bag, f"no {what} topic {topic!r}; topics in the bag: {available}")
    info = topics[topic]
    if info.msgtype not in types:
        expected = " or ".join(types)
        raise DatasetError(bag, f"{what} topic {topic!r} carries {info.msgtype}, expected {expected}")
    return list(info.connections)


@dataclass(frozen=True)
class _Msg:
    """A scan or camera frame seen in the first pass: header stamp (ns; the recording time when the header
    has none), recording time (ns), frame id. (recorded, stamp) finds it again in the second pass."""

    stamp: int
    recorded: int
    frame: str

    @property
    def key(self) -> tuple[int, int]:
        return (self.recorded, self.stamp)


def camera_folder(topic: str) -> str:
    """The folder of a further camera's images: its topic without the leading slash, every other character
    that may not name a camera folder a ``_`` (``/cam_left/image_raw`` → ``cam_left_image_raw``)."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", topic.strip("/")).strip("_.-")[:64] or "camera"
    return name if camera_name_problem(name) is None and name != "image_2" else f"camera_{name}"[:64]


def _first_pass(reader: Any, bag: Path, cfg: RosbagImportConfig) -> dict[str, Any]:
    """Stamps of every scan and camera frame, the transform tree and the CameraInfo messages."""
    lidar = _topic(reader, bag, cfg.lidar_topic, (POINTCLOUD2,), "LiDAR")
    camera = _topic(reader, bag, cfg.camera_topic, (IMAGE, COMPRESSED_IMAGE), "camera")
    more = [_topic(reader, bag, t, (IMAGE, COMPRESSED_IMAGE), "camera") for t in cfg.more_camera_topics]
    topics = reader.topics
    info_conns: list[Any] = []
    if cfg.camera_info_topic is not None:
        info_conns = _topic(reader, bag, cfg.camera_info_topic, (CAMERA_INFO,), "camera info")
    else:
        info_conns = [c for t in topics.values() if t.msgtype == CAMERA_INFO for c in t.connections]
    tf_conns = [
        c
        for name in (TF_TOPIC, TF_STATIC_TOPIC)
        if name in topics and topics[name].msgtype == TF_MESSAGE
        for c in topics[name].connections
    ]
    scans: list[_Msg] = []
    cams: list[_Msg] = []
    infos: dict[str, Any] = {}
    size: tuple[int, int] | None = None  # (width, height) of the first raw image
    tree = TfTree()
    lidar_ids, camera_ids = {c.id for c in lidar}, {c.id for c in camera}
    more_ids = {c.id: k for k, conns in enumerate(more) for c in conns}
    more_cams: list[list[_Msg]] = [[] for _ in more]
    more_sizes: list[tuple[int, int] | None] = [None for _ in more]
    connections = [*lidar, *camera, *(c for conns in more for c in conns), *info_conns, *tf_conns]
    for conn, log_ns, raw in reader.messages(connections=connections):
        # A raw uint8 array of an image or scan is a view: deserialising is cheap.
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.msgtype == TF_MESSAGE:
            tree.add(msg, static=conn.topic == TF_STATIC_TOPIC)
            continue
        stamp = stamp_ns(msg.header) or int(log_ns)  # drivers that leave the stamp 0: the recording time
        if conn.id in lidar_ids:
            scans.append(_Msg(stamp, int(log_ns), _frame(msg.header.frame_id)))
        elif conn.id in camera_ids:
            cams.append(_Msg(stamp, int(log_ns), _frame(msg.header.frame_id)))
            if size is None and conn.msgtype == IMAGE:
                size = (int(msg.width), int(msg.height))
        elif conn.id in more_ids:
            k = more_ids[conn.id]
            more_cams[k].append(_Msg(stamp, int(log_ns), _frame(msg.header.frame_id)))
            if more_sizes[k] is None and conn.msgtype == IMAGE:
                more_sizes[k] = (int(msg.width), int(msg.height))
        else:
            infos.setdefault(conn.topic, msg)
    return {
        "scans": scans,
        "cams": cams,
        "cam_frame": cams[0].frame if cams else "",
        "infos": infos,
        "tree": tree,
        "lidar": lidar,
        "camera": camera,
        "size": size,
        "more": more,
        "more_cams": more_cams,
        "more_sizes": more_sizes,
    }


def _camera_info(cfg: RosbagImportConfig, infos: dict[str, Any], cam_frame: str) -> tuple[str, Any] | None:
    if cfg.camera_info_topic is not None:
        msg = infos.get(cfg.camera_info_topic)
        return None if msg is None else (cfg.camera_info_topic, msg)
    matching = [(t, m) for t, m in sorted(infos.items()) if _frame(m.header.frame_id) == cam_frame]
    if len(matching) == 1:
        return matching[0]
    if not matching and len(infos) == 1:
        return next(iter(infos.items()))
    return None


def _p2_from_info(
    cfg: RosbagImportConfig,
    first: dict[str, Any],
    info: tuple[str, Any],
    problems: list[str],
    notes: list[str],
) -> F64 | None:
    """P2 = CameraInfo.P, or None with the reason appended to ``problems``."""
    topic, msg = info
    # ROS 2 names the matrices p, d; ROS 1 P, D.
    p = np.asarray(msg.p if hasattr(msg, "p") else msg.P, np.float64).reshape(3, 4)
    info_size = (int(msg.width), int(msg.height))
    if abs(np.linalg.det(p[:, :3])) < 1e-9:
        problems.append(f"camera intrinsics (CameraInfo on {topic} has no valid P matrix)")
        return None
    if first["size"] is not None and all(info_size) and info_size != first["size"]:
        problems.append(
            f"camera intrinsics (CameraInfo on {topic} is for {info_size[0]}×{info_size[1]} "
            f"images, {cfg.camera_topic} has {first['size'][0]}×{first['size'][1]})"
        )
        return None
    if np.any(np.asarray(msg.d if hasattr(msg, "d") else msg.D, np.float64) != 0):
        notes.append(
            f"CameraInfo {topic} has lens distortion: the images are used as recorded, "
            "so import a rectified image topic"
        )
    return p


def _calibration(
    bag: Path, cfg: RosbagImportConfig, first: dict[str, Any], lidar_frame: str
) -> tuple[Calib, str, list[str]]:
    """P2 and Tr from --calib where it gives them, else CameraInfo and /tf_static; a DatasetError naming
    every missing part and where it was looked for."""
    given = read_calib_file(cfg.calib_file) if cfg.calib_file is not None else PartialCalib()
    notes: list[str] = []
    sources: list[str] = []
    p2, tr = given.P2, given.Tr
    cam_frame = first["cam_frame"]
    info = _camera_info(cfg, first["infos"], cam_frame)
    if info is not None:
        cam_frame = _frame(info[1].header.frame_id) or cam_frame
    problems: list[str] = []
    if p2 is not None:
        sources.append(f"{cfg.calib_file} (camera)")
    elif info is None:
        where = (
            f"no CameraInfo message on {cfg.camera_info_topic}"
            if cfg.camera_info_topic
            else f"no sensor_msgs/CameraInfo topic for camera frame {cam_frame!r}"
        )
        problems.append(f"camera intrinsics ({where})")
    else:
        p2 = _p2_from_info(cfg, first, info, problems, notes)
        if p2 is not None:
            sources.append(f"CameraInfo {info[0]}")
    if tr is not None:
        sources.append(f"{cfg.calib_file} (lidar_to_camera)")
    else:
        tr = first["tree"].lookup_static(cam_frame, lidar_frame)
        if tr is None:
            static = ", ".join(sorted(first["tree"].static)) or "none"
            problems.append(
                f"LiDAR → camera transform (no {TF_STATIC_TOPIC} chain from {lidar_frame!r} to "
                f"{cam_frame!r}; frames with a static parent: {static})"
            )
        else:
            sources.append(f"{TF_STATIC_TOPIC} {lidar_frame} → {cam_frame}")
    if problems:
        raise DatasetError(
            bag,
            "missing calibration: "
            + "; ".join(problems)
            + "; give them with --calib FILE (YAML, see docs/IMPORT.md)",
        )
    assert p2 is not None and tr is not None
    return Calib(P2=p2, Tr=tr), " + ".join(sources), notes


def _more_calibration(
    bag: Path, cfg: RosbagImportConfig, first: dict[str, Any], lidar_frame: str
) -> list[Camera]:
    """Each further camera's ``P`` (its CameraInfo: the one whose frame is its images' frame) and ``Tr``
    (``/tf_static`` from the LiDAR frame to that frame); a DatasetError naming the topic and what is
    missing."""
    out = []
    for k, topic in enumerate(cfg.more_camera_topics):
        msgs = first["more_cams"][k]
        if not msgs:
            raise DatasetError(bag, f"camera topic {topic!r} has no messages")
        frame = msgs[0].frame
        infos = [(t, m) for t, m in sorted(first["infos"].items()) if _frame(m.header.frame_id) == frame]
        problems: list[str] = []
        p = None
        if len(infos) != 1:
            problems.append(
                f"camera intrinsics ({len(infos)} sensor_msgs/CameraInfo topics for frame {frame!r})"
            )
        else:
            one = replace(cfg, camera_topic=topic, more_camera_topics=())
            p = _p2_from_info(one, {"size": first["more_sizes"][k]}, infos[0], problems, [])
        tr = first["tree"].lookup_static(frame, lidar_frame)
        if tr is None:
            problems.append(
                f"LiDAR → camera transform (no {TF_STATIC_TOPIC} chain from {lidar_frame!r} to {frame!r})"
            )
        if problems or p is None or tr is None:
            raise DatasetError(bag, f"missing calibration of camera {topic}: " + "; ".join(problems))
        out.append(Camera(camera_folder(topic), p, tr, f"CameraInfo {infos[0][0]} + {TF_STATIC_TOPIC}"))
    names = [c.name for c in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise DatasetError(bag, f"two camera topics would share the folder {twice[0]!r}")
    return out


def _poses(
    bag: Path, cfg: RosbagImportConfig, tree: TfTree, lidar_frame: str, stamps: npt.NDArray[np.int64]
) -> tuple[F64 | None, npt.NDArray[np.bool_], str | None]:
    """(LiDAR → fixed frame per scan, mask of scans /tf covers, description) or (None, all True, None) when
    /tf does not move the LiDAR frame."""
    chain = tree.chain(lidar_frame)
    root = chain[-1] if cfg.fixed_frame is None else _frame(cfg.fixed_frame)
    if root not in chain:
        raise DatasetError(
            bag,
            f"fixed frame {root!r} is not above the LiDAR frame in /tf and /tf_static "
            f"(its chain: {' → '.join(chain)})",
        )
    if not tree.is_moving(lidar_frame, root):
        return None, np.ones(len(stamps), bool), None
    mats, ok = tree.to_ancestor(lidar_frame, root, stamps)
    return mats, ok, f"{TF_TOPIC} {root} → {lidar_frame}"


def _decode_image(conn_type: str, msg: Any) -> tuple[npt.NDArray[np.uint8], bytes | None, str]:
    if conn_type == COMPRESSED_IMAGE:
        rgb, data, suffix = compressed_image(msg)
        return rgb, data, suffix
    return image_rgb(msg), None, ".png"


def _write_image(
    seq: Path,
    frame_no: int,
    payload: tuple[npt.NDArray[np.uint8], bytes | None, str],
    folder: str = "image_2",
) -> None:
    rgb, data, suffix = payload
    path = seq / folder / f"{frame_no:06d}{suffix}"
    if data is None:
        write_image(path, rgb)
    else:
        atomic_write_bytes(path, data)  # JPEG/PNG bytes as recorded: no re-encoding loss


def import_rosbag(
    bag: str | Path,
    out: str | Path,
    cfg: RosbagImportConfig,
    *,
    force: bool = False,
    progress: ProgressFn | None = None,
) -> ImportSummary:
    """Convert a ROS 1 / ROS 2 bag into the KITTI sequence folder ``out`` (see the module docstring).

    Writes ``velodyne/NNNNNN.bin``, ``image_2/NNNNNN.png|jpg``, ``calib.txt``, ``times.txt`` (scan stamps in
    seconds after the first written scan) and ``poses.txt`` when ``/tf`` moves the LiDAR frame; frames are
    numbered 0.. over the scans kept.

    Args:
        progress: ``progress(done, total)`` over the scan and camera messages of the writing pass.

    Raises:
        DatasetError: naming the bag (unreadable, a topic missing, with the topics it has, missing
            calibration and what is missing) or the output folder (not empty without ``force``).
    """
    bag, out = Path(bag), Path(out)
    if not bag.exists():
        raise DatasetError(bag, "no such bag file or folder")
    check_output(out, force, IMPORT_ENTRIES | {RIG_FILE, *map(camera_folder, cfg.more_camera_topics)})
    summary = ImportSummary(out=out)
    with _open_bag(bag) as reader:
        first = _first_pass(reader, bag, cfg)
        scans: list[_Msg] = first["scans"]
        cams: list[_Msg] = first["cams"]
        summary.scans = len(scans)
        if not scans:
            raise DatasetError(bag, f"LiDAR topic {cfg.lidar_topic!r} has no messages")
        lidar_frame = scans[0].frame
        calib, summary.calib_source, summary.notes = _calibration(bag, cfg, first, lidar_frame)
        stamps = np.array([s.stamp for s in scans], np.int64)
        partner = pair_nearest(stamps, [c.stamp for c in cams], round(cfg.max_offset_ms * 1e6))
        lidar_world, covered, summary.pose_source = _poses(bag, cfg, first["tree"], lidar_frame, stamps)
        summary.no_camera = int((partner < 0).sum())
        summary.no_pose = int(((partner >= 0) & ~covered).sum())
        keep = (partner >= 0) & covered
        more = _more_calibration(bag, cfg, first, lidar_frame)
        # Messages are found again in the second pass by (topic, recording time, stamp), not by position,
        # as a storage may order messages of equal recording time differently per query.
        todo = {scans[s].key: int(s) for s in np.flatnonzero(keep)}
        wanted: dict[tuple[str, int, int], list[tuple[int, str]]] = {}
        for s in np.flatnonzero(keep):
            wanted.setdefault((cfg.camera_topic, *cams[int(partner[s])].key), []).append((int(s), "image_2"))
        for topic, cam, msgs in zip(cfg.more_camera_topics, more, first["more_cams"], strict=True):
            pair = pair_nearest(stamps, [c.stamp for c in msgs], round(cfg.max_offset_ms * 1e6))
            for s in np.flatnonzero(keep & (pair >= 0)):
                wanted.setdefault((topic, *msgs[int(pair[s])].key), []).append((int(s), cam.name))
            missing = int((keep & (pair < 0)).sum())
            if missing:
                summary.notes.append(f"{missing} frames without a {topic} image within the maximum offset")

        with staged_output(out, force, IMPORT_ENTRIES | {RIG_FILE, *(c.name for c in more)}) as fresh:
            camera_conns = [*first["camera"], *(c for conns in first["more"] for c in conns)]
            plan = _Plan(first["lidar"], camera_conns, todo, wanted)
            written = _write_frames(reader, bag, plan, fresh, summary, progress)
            if not written:
                raise DatasetError(
                    bag,
                    "no scan has a camera frame within "
                    f"{cfg.max_offset_ms:g} ms (or a pose): nothing to write",
                )
            kept = np.asarray(written, np.int64)
            write_calib(fresh / "calib.txt", calib)
            if more:
                rig = [Camera("image_2", calib.P2, calib.Tr), *more]
                atomic_write_bytes(fresh / RIG_FILE, camera_rig_text(rig).encode())
            times = (stamps[kept] - stamps[kept[0]]).astype(np.float64) * 1e-9
            atomic_write_bytes(fresh / "times.txt", "".join(f"{t:.9e}\n" for t in times).encode())
            if lidar_world is not None:
                rel = np.linalg.inv(lidar_world[kept[0]])[None] @ lidar_world[kept]
                tr_inv = np.linalg.inv(calib.Tr)
                write_poses(fresh / "poses.txt", calib.Tr[None] @ rel @ tr_inv[None])
    summary.frames = len(written)
    return summary


@dataclass
class _Plan:
    """What the second pass writes: ``todo`` (message key → scan index) the kept scans, numbered in the
    order they come; ``wanted`` (message key → scan indices) the camera frames they pair with."""

    lidar: list[Any]
    camera: list[Any]
    todo: dict[tuple[int, int], int]
    wanted: dict[tuple[str, int, int], list[tuple[int, str]]]
    """(topic, recording time, stamp) of a camera frame → the (scan index, image folder) it is written for."""
    frame_of: dict[int, int | None] = field(default_factory=dict)
    """Scan index → frame number (None: the scan had no finite point)."""
    waiting: dict[tuple[int, str], tuple[npt.NDArray[np.uint8], bytes | None, str]] = field(
        default_factory=dict
    )
    """(scan index, image folder) → its decoded image, when the image came before the scan."""
    written: list[int] = field(default_factory=list)
    """Scan indices written, in frame order."""


def _write_frames(
    reader: Any, bag: Path, plan: _Plan, seq: Path, summary: ImportSummary, progress: ProgressFn | None
) -> list[int]:
    """Second pass: write the kept scans and their camera frames; returns the scan indices written."""
    lidar_ids = {c.id for c in plan.lidar}
    total = len(plan.todo) + len(plan.wanted)
    done = 0
    report(progress, 0, total)
    for conn, log_ns, raw in reader.messages(connections=[*plan.lidar, *plan.camera]):
        msg = reader.deserialize(raw, conn.msgtype)
        key = (int(log_ns), stamp_ns(msg.header) or int(log_ns))
        try:
            if conn.id in lidar_ids:
                scan_i = plan.todo.get(key)
                if scan_i is None or scan_i in plan.frame_of:
                    continue
                _write_scan(plan, scan_i, pointcloud_xyzi(msg), seq, summary)
            else:
                scans = plan.wanted.pop((conn.topic, *key), None)
                if scans is None:
                    continue
                _write_camera(plan, scans, _decode_image(conn.msgtype, msg), seq)
        except ValueError as exc:
            raise DatasetError(bag, f"{conn.topic} message at {log_ns} ns: {exc}") from None
        done += 1
        report(progress, done, total)
    return plan.written


def _write_scan(
    plan: _Plan,
    scan_i: int,
    cloud: tuple[npt.NDArray[np.float32], int, bool],
    seq: Path,
    summary: ImportSummary,
) -> None:
    pts, nan, _ = cloud
    summary.nan_points += nan
    waiting = [key for key in plan.waiting if key[0] == scan_i]
    if len(pts) == 0:
        summary.empty += 1
        plan.frame_of[scan_i] = None
        for key in waiting:
            plan.waiting.pop(key)
        return
    frame_no = len(plan.written)
    write_scan(seq / "velodyne" / f"{frame_no:06d}.bin", pts)
    plan.written.append(scan_i)
    plan.frame_of[scan_i] = frame_no
    for key in waiting:
        _write_image(seq, frame_no, plan.waiting.pop(key), key[1])


def _write_camera(
    plan: _Plan,
    scans: list[tuple[int, str]],
    payload: tuple[npt.NDArray[np.uint8], bytes | None, str],
    seq: Path,
) -> None:
    # A camera frame may come before or after its scans: before, it waits for them.
    for s, folder in scans:
        if s not in plan.frame_of:
            plan.waiting[(s, folder)] = payload
        elif (no := plan.frame_of[s]) is not None:
            _write_image(seq, no, payload, folder)


__all__ = [
    "ImportSummary",
    "PartialCalib",
    "RosbagImportConfig",
    "TfTree",
    "camera_folder",
    "compressed_image",
    "image_rgb",
    "import_rosbag",
    "pair_nearest",
    "pointcloud_xyzi",
    "read_calib_file",
    "stamp_ns",
    "transform_matrix",
]
