"""The files of one synthetic frame, shared by every domain's generator (street: ``generator``, agri-uav:
``agri``): its scan, labels, image and 2D ground truth, and the count of its points inside the image."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import Calib, write_image, write_label, write_png16, write_scan
from leap_core.synth.camera import CameraFrame
from leap_core.synth.lidar import Scan


def write_frame(seq_dir: Path, i: int, sc: Scan, cam: CameraFrame) -> None:
    """Write frame ``i``'s scan, labels, image and 2D ground truth (name ``{i:06d}``) under ``seq_dir``."""
    stem = f"{i:06d}"
    d = seq_dir
    write_scan(d / "velodyne" / f"{stem}.bin", sc.points)
    write_label(d / "labels" / f"{stem}.label", sc.semantic, sc.instance)
    write_camera(seq_dir, i, cam, "image_2", "gt2d")


def write_camera(seq_dir: Path, i: int, cam: CameraFrame, folder: str, gt2d: str) -> None:
    """Write frame ``i``'s image of one camera into ``folder`` and its 2D ground truth into ``gt2d/<kind>``
    (both relative to ``seq_dir``; ``gt2d/<camera>`` for a rig's further cameras)."""
    stem = f"{i:06d}"
    d = seq_dir
    write_image(d / folder / f"{stem}.png", cam.rgb)
    write_png16(d / gt2d / "semantic" / f"{stem}.png", cam.semantic)
    write_png16(d / gt2d / "instance" / f"{stem}.png", cam.instance)
    write_png16(d / gt2d / "name" / f"{stem}.png", cam.name)
    write_png16(d / gt2d / "cell" / f"{stem}.png", cam.cell)


def in_image_mask(
    xyz: npt.NDArray[np.float32], calib: Calib, width: int, height: int
) -> npt.NDArray[np.bool_]:
    """(N,) bool: the point has positive depth and its rounded projection ``P2·Tr·X`` lies in the image."""
    m = calib.lidar_to_image.astype(np.float32)
    x, y, zc = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    q = [m[k, 0] * x + m[k, 1] * y + m[k, 2] * zc + m[k, 3] for k in range(3)]
    ok = q[2] > 0.1
    u = np.rint(q[0][ok] / q[2][ok])
    v = np.rint(q[1][ok] / q[2][ok])
    out = np.zeros(len(xyz), bool)
    out[np.flatnonzero(ok)] = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return out


def count_in_image(xyz: npt.NDArray[np.float32], calib: Calib, width: int, height: int) -> int:
    """Number of points with positive depth whose rounded projection ``P2·Tr·X`` lies in the image."""
    return int(in_image_mask(xyz, calib, width, height).sum())
