"""nuScenes → KITTI layout: one scene's LIDAR_TOP keyframes with one camera, read through ``nuscenes-devkit``.

What is written (``leap import nuscenes``; docs/IMPORT.md, "nuScenes"):

- **Frames = keyframes** (samples, 2 Hz). nuScenes-lidarseg labels exist only there, and only there is a
  camera image taken for the sweep (the cameras are triggered as the LiDAR sweeps across them); the 20 Hz
  sweeps between keyframes would have neither labels nor a matching image, and one unlabeled scan turns the
  run's evaluation off (``KittiSequence.has_labels`` needs every scan). The sweeps skipped are counted.
- ``velodyne/NNNNNN.bin``: x, y, z, intensity / 255 (the HDL-32E's intensity is a 0..255 byte; a fixed scale
  keeps one surface at one remission in every scan, as KITTI's remission), the ring index dropped. The
  points are re-expressed in the LiDAR's pose at the camera's exposure (:func:`camera_time_correction`):
  the image and the sweep are up to tens of milliseconds apart, at 10 m/s that is decimetres, and a KITTI
  ``calib.txt`` holds one LiDAR→camera transform. The correction is the devkit's own
  ``map_pointcloud_to_image`` chain (LiDAR → ego at the sweep → global → ego at the image → camera), so
  the points land on the pixels the devkit projects them to and on the same world coordinates.
- ``image_2/NNNNNN.jpg``: the keyframe image of ``camera``, its bytes copied (nuScenes images are already
  undistorted; re-encoding a JPEG would only lose detail).
- ``calib.txt``: ``P2 = [K | 0]`` with K the camera's ``camera_intrinsic``, ``Tr`` = camera←LiDAR from the
  ``calibrated_sensor`` records (:func:`kitti_calib`).
- ``poses.txt``: the LiDAR's global pose at each image time (ego pose · sensor extrinsic) in the KITTI
  camera-frame convention, first frame = identity (:func:`kitti_cam_poses`).
- ``times.txt``: seconds of each keyframe's LiDAR timestamp since the first.
- ``labels/NNNNNN.label`` (when nuScenes-lidarseg is installed in the dataroot): the lidarseg index
  (0..31) of each point as the semantic id, instance 0. ``projects/nuscenes.yaml`` maps these to the 16
  classes of the lidarseg benchmark.
- ``import.json`` (:data:`~leap_core.importers.folder.IMPORT_NOTE`): the source and, per frame, the
  sample / sample_data tokens and timestamps.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import (
    IMAGE_SUFFIXES,
    Calib,
    write_calib,
    write_label,
    write_poses,
    write_scan,
)
from leap_core.datasets.rig import FRAME_TR_FOLDER, RIG_FILE, Camera, camera_rig_text
from leap_core.errors import DatasetError
from leap_core.extras import MissingExtra
from leap_core.importers.folder import IMPORT_ENTRIES, IMPORT_NOTE, check_output, staged_output
from leap_core.io_utils import atomic_write_bytes
from leap_core.progress import ProgressFn, report

try:  # the nuscenes extra and the devkit: only `leap import nuscenes` imports this module
    from nuscenes.nuscenes import NuScenes  # type: ignore[import-untyped]
    from nuscenes.utils.data_classes import LidarPointCloud  # type: ignore[import-untyped]
    from nuscenes.utils.data_io import load_bin_file  # type: ignore[import-untyped]
    from nuscenes.utils.geometry_utils import transform_matrix  # type: ignore[import-untyped]
    from pyquaternion import Quaternion  # type: ignore[import-untyped]
except ModuleNotFoundError as exc:
    raise MissingExtra("nuscenes", exc.name) from None

RIG_ORDER = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
"""nuScenes' six cameras, clockwise from the front: the rig order of ``--camera all``."""
RIG_IMPORT_ENTRIES = IMPORT_ENTRIES | {RIG_FILE, FRAME_TR_FOLDER, *RIG_ORDER}
"""What a nuScenes import writes (a rig import: its camera folders, ``cameras.yaml``, ``tr_frames``)."""

LIDAR_CHANNEL = "LIDAR_TOP"
"""nuScenes' only LiDAR (the five radars are not LiDARs)."""

INTENSITY_SCALE = 255.0
"""LIDAR_TOP intensity is a 0..255 byte stored as float32; remission = intensity / this, clipped to 0..1."""

LIDARSEG_NAMES: tuple[str, ...] = (
    "noise",
    "animal",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.stroller",
    "human.pedestrian.wheelchair",
    "movable_object.barrier",
    "movable_object.debris",
    "movable_object.pushable_pullable",
    "movable_object.trafficcone",
    "static_object.bicycle_rack",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.car",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.motorcycle",
    "vehicle.trailer",
    "vehicle.truck",
    "flat.driveable_surface",
    "flat.other",
    "flat.sidewalk",
    "flat.terrain",
    "static.manmade",
    "static.other",
    "static.vegetation",
    "vehicle.ego",
)
"""The 32 nuScenes-lidarseg categories by their ``index`` in nuScenes v1.0's ``category.json`` (the raw ids
the ``.label`` files hold; ``projects/nuscenes.yaml``'s ``gt_ids`` assume them). An import whose
``category.json`` numbers them otherwise says so in its summary."""


# ------------------------------------------------------------------------------------------- maths
def intensity_to_remission(intensity: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """(N,) LIDAR_TOP intensity 0..255 → (N,) float32 remission ``clip(intensity / 255, 0, 1)``."""
    return np.clip(np.asarray(intensity, dtype=np.float64) / INTENSITY_SCALE, 0.0, 1.0).astype(np.float32)


def kitti_calib(
    lidar_to_ego: npt.NDArray[np.float64], cam_to_ego: npt.NDArray[np.float64], intrinsic: npt.ArrayLike
) -> Calib:
    """KITTI calibration from nuScenes sensor extrinsics (4×4 sensor → ego) and a 3×3 camera intrinsic K.

    ``P2 = [K | 0]`` (3×4) and ``Tr = (cam_to_ego)⁻¹ · lidar_to_ego`` (4×4, LiDAR → camera). Both frames
    agree on the camera axes (x right, y down, z forward), so no axis change is needed.

    Raises:
        ValueError: K is not 3×3 or is singular.
    """
    k = np.asarray(intrinsic, dtype=np.float64)
    if k.shape != (3, 3) or abs(np.linalg.det(k)) < 1e-9:
        raise ValueError(f"camera intrinsic must be a non-singular 3×3 matrix, got {k.tolist()}")
    p2 = np.zeros((3, 4))
    p2[:, :3] = k
    return Calib(P2=p2, Tr=np.linalg.inv(cam_to_ego) @ lidar_to_ego)


def camera_time_correction(
    ego_at_sweep: npt.NDArray[np.float64],
    ego_at_image: npt.NDArray[np.float64],
    lidar_to_ego: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """4×4 M taking a sweep's points into the LiDAR frame at the image's time: ``M = (E_i · S)⁻¹ · E_s · S``.

    ``E_s`` / ``E_i`` are the ego → global poses at the sweep / image timestamps, ``S`` the LiDAR → ego
    extrinsic. ``M · p`` has the same global position as ``p`` (``E_i S M p = E_s S p``), seen from where the
    LiDAR was when the image was taken; identity when the two ego poses are equal.
    """
    return np.asarray(np.linalg.inv(ego_at_image @ lidar_to_ego) @ ego_at_sweep @ lidar_to_ego)


def kitti_cam_poses(
    lidar_to_global: npt.NDArray[np.float64], tr: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """(F, 4, 4) KITTI ``poses.txt`` poses from (F, 4, 4) LiDAR → global poses ``G``; ``Tr``: LiDAR→camera.

    ``P_i = Tr · G_0⁻¹ · G_i · Tr⁻¹``: camera i → camera 0 (frame 0 is the identity), the inverse of
    ``kitti.lidar_poses`` (``Tr⁻¹ · P_i · Tr = G_0⁻¹ · G_i``). Re-basing on frame 0 also keeps nuScenes'
    global map coordinates (hundreds of metres) out of the files.
    """
    rel = np.linalg.inv(lidar_to_global[0])[None] @ lidar_to_global
    return np.asarray(tr[None] @ rel @ np.linalg.inv(tr)[None])


# ----------------------------------------------------------------------------------------- summary
@dataclass
class ImportSummary:
    """What :func:`import_nuscenes` wrote."""

    out: Path
    """The sequence folder."""
    scene: str
    """Scene name."""
    camera: str
    """Camera channel."""
    frames: int = 0
    """Scans written (one per keyframe)."""
    images: int = 0
    """Frames with a camera image."""
    labels: int = 0
    """Frames with a lidarseg ``.label``."""
    lidarseg: bool = False
    """nuScenes-lidarseg is installed in the dataroot."""
    skipped_sweeps: int = 0
    """LIDAR_TOP sweeps between keyframes, not written (no image, no labels there)."""
    cameras: int = 1
    """Cameras written (a rig import: two or more)."""
    max_offset_ms: float = 0.0
    """Largest |image − sweep| timestamp difference, compensated with the ego poses."""
    notes: list[str] = field(default_factory=list)
    """Anything the user should know (frames without an image or labels, unusual category indices)."""

    def line(self) -> str:
        """The one-line summary the CLI prints."""
        labels = f"{self.labels} lidarseg labels" if self.lidarseg else "no labels (lidarseg not installed)"
        images = f"{self.images} {self.camera} images"
        if self.cameras > 1:
            images = f"{self.images} images of {self.cameras} cameras: {self.camera}"
        text = (
            f"wrote {self.frames} frames of {self.scene} to {self.out} ({images}, "
            f"{labels}); skipped {self.skipped_sweeps} {LIDAR_CHANNEL} sweeps between keyframes (no image or "
            f"labels there); image-sweep offset up to {self.max_offset_ms:.0f} ms, compensated with the ego "
            "poses"
        )
        return text + "".join(f"; {n}" for n in self.notes)


# ---------------------------------------------------------------------------------------- importer
def _load(dataroot: Path, version: str) -> Any:
    """The devkit's ``NuScenes`` for ``dataroot``/``version``; every way it fails becomes a DatasetError."""
    if not dataroot.is_dir():
        raise DatasetError(dataroot, "nuScenes dataroot does not exist")
    if not (dataroot / version).is_dir():
        found = sorted(p.name for p in dataroot.iterdir() if (p / "scene.json").is_file())
        raise DatasetError(
            dataroot / version,
            f"no nuScenes version {version!r} here (versions in {dataroot}: {', '.join(found) or 'none'})",
        )
    try:
        return NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    except (AssertionError, KeyError, IndexError, OSError, ValueError, TypeError) as exc:
        detail = str(exc) or type(exc).__name__
        if isinstance(exc, KeyError):
            detail = f"missing key or token {exc}"
        raise DatasetError(dataroot / version, f"the nuScenes devkit cannot load it: {detail}") from exc


def _matrix(nusc: Any, table: str, token: str) -> npt.NDArray[np.float64]:
    """4×4 of a ``calibrated_sensor`` or ``ego_pose`` record (sensor → ego, ego → global)."""
    rec = nusc.get(table, token)
    return np.asarray(
        transform_matrix(np.asarray(rec["translation"], dtype=np.float64), Quaternion(rec["rotation"])),
        dtype=np.float64,
    )


def _one_calibration(nusc: Any, tokens: Sequence[str], channel: str, where: Path) -> npt.NDArray[np.float64]:
    """The sensor's one extrinsic over the scene (a KITTI sequence has one ``calib.txt``)."""
    mats = [_matrix(nusc, "calibrated_sensor", t) for t in dict.fromkeys(tokens)]
    if any(not np.allclose(m, mats[0], atol=1e-9) for m in mats[1:]):
        raise DatasetError(
            where / "calibrated_sensor.json",
            f"{channel} has {len(mats)} different calibrations within the scene; a KITTI sequence holds one",
        )
    return mats[0]


def _scene(nusc: Any, name: str, where: Path) -> dict[str, Any]:
    scenes: dict[str, dict[str, Any]] = {s["name"]: s for s in nusc.scene}
    if name not in scenes:
        names = sorted(scenes)
        shown = ", ".join(names[:20]) + (f", … ({len(names)} scenes)" if len(names) > 20 else "")
        raise DatasetError(where / "scene.json", f"no scene {name!r} (scenes: {shown or 'none'})")
    return scenes[name]


def _check_channels(nusc: Any, camera: str, where: Path) -> None:
    channels = {s["channel"]: s["modality"] for s in nusc.sensor}
    cameras = sorted(c for c, m in channels.items() if m == "camera")
    if channels.get(camera) != "camera":
        raise DatasetError(
            where / "sensor.json", f"no camera {camera!r} (cameras: {', '.join(cameras) or 'none'})"
        )
    if channels.get(LIDAR_CHANNEL) != "lidar":
        raise DatasetError(where / "sensor.json", f"no {LIDAR_CHANNEL} LiDAR sensor")


def _read_points(nusc: Any, token: str) -> npt.NDArray[np.float32]:
    """(N, 4) x, y, z, intensity of a LIDAR_TOP file, read by the devkit (which drops the ring index)."""
    path = Path(nusc.get_sample_data_path(token))
    if not path.is_file():
        raise DatasetError(path, "LiDAR file is missing")
    try:
        pts = np.asarray(LidarPointCloud.from_file(str(path)).points.T, dtype=np.float32)
    except (AssertionError, ValueError) as exc:
        raise DatasetError(
            path, f"not a nuScenes LiDAR file (float32 x, y, z, intensity, ring): {exc}"
        ) from exc
    if not np.isfinite(pts).all():
        raise DatasetError(path, "points with non-finite values")
    return pts


def _read_labels(nusc: Any, lidar_token: str, n_points: int) -> npt.NDArray[np.uint8] | None:
    """(N,) lidarseg indices of a keyframe sweep, or None when it has no lidarseg record."""
    try:
        record = nusc.get("lidarseg", lidar_token)  # lidarseg records share their sweep's token
    except KeyError:
        return None
    path = Path(nusc.dataroot) / record["filename"]
    try:
        labels = np.asarray(load_bin_file(str(path), type="lidarseg"), dtype=np.uint8)
    except (AssertionError, OSError) as exc:
        raise DatasetError(path, f"cannot read lidarseg labels ({exc})") from exc
    if labels.shape != (n_points,):
        raise DatasetError(path, f"{labels.size} lidarseg labels but {n_points} points in the sweep")
    return labels


def _read_image_bytes(path: Path) -> bytes:
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise DatasetError(path, f"camera image is not a {'/'.join(IMAGE_SUFFIXES)} file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read camera image ({exc.strerror or exc})") from exc
    # Decoding (at 1/8 size, cheaply) catches a truncated or mislabelled file before it is copied.
    buf = np.frombuffer(data, dtype=np.uint8)
    if not buf.size or cv2.imdecode(buf, cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
        raise DatasetError(path, "unreadable camera image (empty or not a JPEG/PNG)")
    return data


@dataclass
class _Scene:
    """The keyframes of one scene and its calibration, looked up in the tables before anything is written."""

    record: dict[str, Any]
    lidar: list[dict[str, Any]]
    """LIDAR_TOP keyframe ``sample_data`` records in time order."""
    cameras: list[dict[str, Any] | None]
    """The (first) camera's keyframe ``sample_data`` of each LiDAR keyframe's sample (None where it has
    none)."""
    lidar_to_ego: npt.NDArray[np.float64]
    calib: Calib
    """The (first) camera's calibration."""
    rig: dict[str, tuple[list[dict[str, Any] | None], Calib]] = field(default_factory=dict)
    """Per camera of a rig import (two or more cameras), its keyframe records and its calibration, in rig
    order; empty for a one-camera import."""


def camera_channels(nusc: Any, camera: str, where: Path) -> list[str]:
    """The camera channels ``camera`` names: one channel, several separated by commas, or ``all`` (every
    camera of the sensor table, nuScenes' six in clockwise order from ``CAM_FRONT`` first).

    Raises:
        DatasetError: naming ``sensor.json`` and listing the cameras, for a channel that is not a camera.
    """
    present = [s["channel"] for s in nusc.sensor if s["modality"] == "camera"]
    if camera.strip() == "all":
        return [c for c in RIG_ORDER if c in present] + sorted(c for c in present if c not in RIG_ORDER)
    names = list(dict.fromkeys(c.strip() for c in camera.split(",") if c.strip()))
    for name in names or [camera]:
        _check_channels(nusc, name, where)
    return names


def _plan_rig(nusc: Any, scene: str, channels: list[str], tables: Path, summary_notes: list[str]) -> _Scene:
    """:func:`_plan` of each camera of a rig import; a camera without keyframe images in the scene is left
    out (noted), and a rig with none left is refused."""
    rig: dict[str, tuple[list[dict[str, Any] | None], Calib]] = {}
    first: _Scene | None = None
    for name in channels:
        try:
            plan = _plan(nusc, scene, name, tables)
        except DatasetError as exc:
            if "keyframe images" not in exc.problem:
                raise
            summary_notes.append(f"{name} has no keyframe images in the scene: not imported")
            continue
        first = first or plan
        rig[name] = (plan.cameras, plan.calib)
    if first is None:
        raise DatasetError(
            tables / "sample_data.json", f"scene {scene!r} has no keyframe images of {channels}"
        )
    first.rig = rig
    return first


def _plan(nusc: Any, scene: str, camera: str, tables: Path) -> _Scene:
    _check_channels(nusc, camera, tables)
    rec = _scene(nusc, scene, tables)
    samples = []
    token = rec["first_sample_token"]
    while token:
        samples.append(nusc.get("sample", token))
        token = samples[-1]["next"]
    with_lidar = [s for s in samples if LIDAR_CHANNEL in s["data"]]
    if not with_lidar:
        raise DatasetError(tables / "sample_data.json", f"scene {scene!r} has no {LIDAR_CHANNEL} keyframes")
    lidar = [nusc.get("sample_data", s["data"][LIDAR_CHANNEL]) for s in with_lidar]
    cameras = [
        nusc.get("sample_data", s["data"][camera]) if camera in s["data"] else None for s in with_lidar
    ]
    cam_tokens = [c["calibrated_sensor_token"] for c in cameras if c is not None]
    if not cam_tokens:
        raise DatasetError(tables / "sample_data.json", f"scene {scene!r} has no {camera} keyframe images")
    lidar_to_ego = _one_calibration(
        nusc, [sd["calibrated_sensor_token"] for sd in lidar], LIDAR_CHANNEL, tables
    )
    cam_to_ego = _one_calibration(nusc, cam_tokens, camera, tables)
    try:
        calib = kitti_calib(
            lidar_to_ego, cam_to_ego, nusc.get("calibrated_sensor", cam_tokens[0])["camera_intrinsic"]
        )
    except ValueError as exc:
        raise DatasetError(tables / "calibrated_sensor.json", f"{camera}: {exc}") from exc
    return _Scene(rec, lidar, cameras, lidar_to_ego, calib)


def _new_summary(nusc: Any, plan: _Scene, out: Path, camera: str) -> ImportSummary:
    summary = ImportSummary(
        out=out, scene=plan.record["name"], camera=camera, lidarseg=hasattr(nusc, "lidarseg")
    )
    in_scene = {sd["sample_token"] for sd in plan.lidar}
    summary.skipped_sweeps = sum(
        1
        for sd in nusc.sample_data
        if sd["channel"] == LIDAR_CHANNEL and not sd["is_key_frame"] and sd["sample_token"] in in_scene
    )
    if summary.lidarseg and {int(c["index"]): c["name"] for c in nusc.category} != dict(
        enumerate(LIDARSEG_NAMES)
    ):
        summary.notes.append(
            "category.json numbers the lidarseg classes differently from nuScenes v1.0: check the gt_ids of "
            "projects/nuscenes.yaml against it"
        )
    return summary


def _sweep_entry(sd: dict[str, Any], fid: str) -> dict[str, Any]:
    """A frame's ``import.json`` entry: which keyframe and LiDAR sweep it holds."""
    return {
        "frame": fid,
        "sample_token": sd["sample_token"],
        "lidar_token": sd["token"],
        "lidar_timestamp_us": int(sd["timestamp"]),
    }


def _write_frame(
    nusc: Any, plan: _Scene, i: int, stage: Path, summary: ImportSummary
) -> tuple[npt.NDArray[np.float64], dict[str, Any]]:
    """Write frame ``i``'s scan, image and labels into ``stage``; return its LiDAR → global pose at the image
    time and its ``import.json`` entry."""
    sd, cam = plan.lidar[i], plan.cameras[i]
    fid = f"{i:06d}"
    ego_sweep = _matrix(nusc, "ego_pose", sd["ego_pose_token"])
    pts = _read_points(nusc, sd["token"])
    entry = _sweep_entry(sd, fid)
    ego_image = ego_sweep
    if cam is not None:
        ego_image = _matrix(nusc, "ego_pose", cam["ego_pose_token"])
        image = _read_image_bytes(Path(nusc.get_sample_data_path(cam["token"])))
        atomic_write_bytes(stage / "image_2" / f"{fid}{Path(cam['filename']).suffix.lower()}", image)
        summary.images += 1
        summary.max_offset_ms = max(summary.max_offset_ms, abs(cam["timestamp"] - sd["timestamp"]) / 1e3)
        entry.update(camera_token=cam["token"], camera_timestamp_us=int(cam["timestamp"]))
    corr = camera_time_correction(ego_sweep, ego_image, plan.lidar_to_ego)
    xyz = pts[:, :3].astype(np.float64) @ corr[:3, :3].T + corr[:3, 3]
    write_scan(stage / "velodyne" / f"{fid}.bin", np.column_stack([xyz, intensity_to_remission(pts[:, 3])]))
    if summary.lidarseg:
        labels = _read_labels(nusc, sd["token"], len(pts))
        if labels is not None:
            write_label(stage / "labels" / f"{fid}.label", labels)
            summary.labels += 1
    summary.frames += 1
    return ego_image @ plan.lidar_to_ego, entry


def _write_rig_frame(
    nusc: Any, plan: _Scene, i: int, stage: Path, summary: ImportSummary
) -> tuple[npt.NDArray[np.float64], dict[str, Any], dict[str, npt.NDArray[np.float64]]]:
    """Frame ``i`` of a rig import: its scan as the LiDAR saw it at the sweep, each camera's image, its
    labels; returns its LiDAR → global pose at the sweep, its ``import.json`` entry and per camera the
    LiDAR → camera transform at that camera's image (the devkit's chain, :func:`camera_time_correction`)."""
    sd = plan.lidar[i]
    fid = f"{i:06d}"
    ego_sweep = _matrix(nusc, "ego_pose", sd["ego_pose_token"])
    pts = _read_points(nusc, sd["token"])
    entry: dict[str, Any] = {**_sweep_entry(sd, fid), "cameras": {}}
    trs: dict[str, npt.NDArray[np.float64]] = {}
    for name, (records, calib) in plan.rig.items():
        cam = records[i]
        trs[name] = calib.Tr
        if cam is None:
            continue
        ego_image = _matrix(nusc, "ego_pose", cam["ego_pose_token"])
        image = _read_image_bytes(Path(nusc.get_sample_data_path(cam["token"])))
        atomic_write_bytes(stage / name / f"{fid}{Path(cam['filename']).suffix.lower()}", image)
        summary.images += 1
        summary.max_offset_ms = max(summary.max_offset_ms, abs(cam["timestamp"] - sd["timestamp"]) / 1e3)
        entry["cameras"][name] = {"token": cam["token"], "timestamp_us": int(cam["timestamp"])}
        trs[name] = calib.Tr @ camera_time_correction(ego_sweep, ego_image, plan.lidar_to_ego)
    xyz = pts[:, :3].astype(np.float64)
    write_scan(stage / "velodyne" / f"{fid}.bin", np.column_stack([xyz, intensity_to_remission(pts[:, 3])]))
    if summary.lidarseg:
        labels = _read_labels(nusc, sd["token"], len(pts))
        if labels is not None:
            write_label(stage / "labels" / f"{fid}.label", labels)
            summary.labels += 1
    summary.frames += 1
    return ego_sweep @ plan.lidar_to_ego, entry, trs


def _write_times(stage: Path, lidar: list[dict[str, Any]]) -> None:
    """``times.txt``: each sweep's time in seconds after the first (nuScenes timestamps are µs)."""
    t0 = lidar[0]["timestamp"]
    text = "".join(f"{(sd['timestamp'] - t0) / 1e6:.6f}\n" for sd in lidar)
    atomic_write_bytes(stage / "times.txt", text.encode())


def _note_head(root: Path, version: str, scene: str, record: dict[str, Any]) -> dict[str, Any]:
    """The fields of the import note that name the source scene (one camera or a rig)."""
    return {
        "importer": "nuscenes",
        "dataroot": str(root.resolve()),
        "version": version,
        "scene": scene,
        "scene_token": record["token"],
        "lidar": LIDAR_CHANNEL,
    }


def import_nuscenes(
    dataroot: str | Path,
    out: str | Path,
    *,
    version: str = "v1.0-mini",
    scene: str,
    camera: str = "CAM_FRONT",
    force: bool = False,
    progress: ProgressFn | None = None,
) -> ImportSummary:
    """Write the keyframes of one nuScenes scene as a KITTI-layout sequence folder ``out`` (module docstring).

    Args:
        dataroot: the nuScenes folder (holding ``samples/``, ``sweeps/``, ``v1.0-mini/``, ``lidarseg/``).
        out: the sequence folder to write; replaced whole at the end (:func:`staged_output`).
        version: the table folder (``v1.0-mini``, ``v1.0-trainval``).
        scene: scene name (``scene-0061``).
        camera: camera channel whose keyframe images are written; several separated by commas, or ``all``,
            write a rig (docs/IMPORT.md, "Several cameras"): each camera's images in a folder named after
            its channel, ``cameras.yaml`` with each camera's ``P = [K | 0]`` and ``Tr``, and
            ``tr_frames/<channel>.txt`` with each frame's LiDAR → camera transform at that camera's image
            (the points stay as the LiDAR saw them at the sweep).
        force: replace a previous import in ``out``.
        progress: ``progress(done, total)`` per frame.

    Raises:
        DatasetError: naming the folder, table or file: missing dataroot / version / scene / camera (listing
            what exists), tables the devkit cannot load, a calibration that changes within the scene,
            unreadable LiDAR, image or label files, a non-empty ``out`` without ``force``.
    """
    root, out = Path(dataroot), Path(out)
    check_output(
        out, force, RIG_IMPORT_ENTRIES
    )  # before the minutes the tables of a full release take to load
    nusc = _load(root, version)
    channels = camera_channels(nusc, camera, root / version)
    if len(channels) > 1:
        return _import_rig(nusc, root, out, version, scene, channels, force, progress)
    camera = channels[0] if channels else camera
    try:
        plan = _plan(nusc, scene, camera, root / version)
        summary = _new_summary(nusc, plan, out, camera)
        n = len(plan.lidar)
        lidar_global = np.zeros((n, 4, 4))
        entries: list[dict[str, Any]] = []
        with staged_output(out, force, RIG_IMPORT_ENTRIES) as stage:
            for i in range(n):
                lidar_global[i], entry = _write_frame(nusc, plan, i, stage, summary)
                entries.append(entry)
                report(progress, i + 1, n)
            write_calib(stage / "calib.txt", plan.calib)
            write_poses(stage / "poses.txt", kitti_cam_poses(lidar_global, plan.calib.Tr))
            _write_times(stage, plan.lidar)
            note = {
                **_note_head(root, version, scene, plan.record),
                "camera": camera,
                "remission": f"intensity / {INTENSITY_SCALE:g}, clipped to 0..1",
                "points": "LiDAR frame at the camera image's timestamp (ego-motion compensated)",
                "labels": "nuScenes-lidarseg index per point" if summary.lidarseg else None,
                "frames": entries,
            }
            atomic_write_bytes(stage / IMPORT_NOTE, (json.dumps(note, indent=2) + "\n").encode())
    except KeyError as exc:  # nusc.get of a token its table lacks (e.g. an ego_pose the loader never checks)
        raise DatasetError(root / version, f"a record refers to a token its table lacks: {exc}") from exc
    if summary.images < n:
        summary.notes.append(f"{n - summary.images} keyframes have no {camera} image")
    if summary.lidarseg and summary.labels < n:
        summary.notes.append(
            f"{n - summary.labels} keyframes have no lidarseg record (evaluation needs labels on every scan)"
        )
    return summary


def _import_rig(  # noqa: PLR0917  # import_nuscenes' arguments, passed on
    nusc: Any,
    root: Path,
    out: Path,
    version: str,
    scene: str,
    channels: list[str],
    force: bool,
    progress: ProgressFn | None,
) -> ImportSummary:
    """:func:`import_nuscenes` of several cameras."""
    notes: list[str] = []
    try:
        plan = _plan_rig(nusc, scene, channels, root / version, notes)
        names = list(plan.rig)
        summary = _new_summary(nusc, plan, out, ", ".join(names))
        summary.cameras = len(names)
        summary.notes += notes
        n = len(plan.lidar)
        lidar_global = np.zeros((n, 4, 4))
        trs = {name: np.zeros((n, 4, 4)) for name in names}
        entries: list[dict[str, Any]] = []
        with staged_output(out, force, RIG_IMPORT_ENTRIES) as stage:
            for i in range(n):
                lidar_global[i], entry, frame_trs = _write_rig_frame(nusc, plan, i, stage, summary)
                for name, tr in frame_trs.items():
                    trs[name][i] = tr
                entries.append(entry)
                report(progress, i + 1, n)
            write_calib(stage / "calib.txt", plan.calib)
            write_poses(stage / "poses.txt", kitti_cam_poses(lidar_global, plan.calib.Tr))
            rig = [Camera(name, calib.P2, calib.Tr) for name, (_, calib) in plan.rig.items()]
            atomic_write_bytes(stage / RIG_FILE, camera_rig_text(rig).encode())
            for name in names:
                write_poses(stage / FRAME_TR_FOLDER / f"{name}.txt", trs[name])
            _write_times(stage, plan.lidar)
            note = {
                **_note_head(root, version, scene, plan.record),
                "cameras": names,
                "remission": f"intensity / {INTENSITY_SCALE:g}, clipped to 0..1",
                "points": "LiDAR frame at the sweep's timestamp; each camera's LiDAR → camera transform "
                f"at its image's timestamp is in {FRAME_TR_FOLDER}/",
                "labels": "nuScenes-lidarseg index per point" if summary.lidarseg else None,
                "frames": entries,
            }
            atomic_write_bytes(stage / IMPORT_NOTE, (json.dumps(note, indent=2) + "\n").encode())
    except KeyError as exc:
        raise DatasetError(root / version, f"a record refers to a token its table lacks: {exc}") from exc
    for name, (records, _) in plan.rig.items():
        missing = sum(r is None for r in records)
        if missing:
            summary.notes.append(f"{missing} keyframes have no {name} image")
    if summary.lidarseg and summary.labels < n:
        summary.notes.append(
            f"{n - summary.labels} keyframes have no lidarseg record (evaluation needs labels on every scan)"
        )
    return summary


__all__ = [
    "INTENSITY_SCALE",
    "LIDARSEG_NAMES",
    "LIDAR_CHANNEL",
    "ImportSummary",
    "camera_channels",
    "camera_time_correction",
    "import_nuscenes",
    "intensity_to_remission",
    "kitti_calib",
    "kitti_cam_poses",
]
