"""Preview images of a generated sequence: a bird's-eye view of a labelled scan and a camera image with
its ground-truth overlay (used for the README previews and for eyeballing the generator)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from leap_core.datasets.kitti import KittiSequence

SEMANTIC_KITTI_RGB: dict[int, tuple[int, int, int]] = {
    0: (0, 0, 0),
    10: (100, 150, 245),
    11: (100, 230, 245),
    18: (80, 30, 180),
    30: (255, 30, 30),
    40: (255, 0, 255),
    44: (255, 150, 255),
    48: (75, 0, 75),
    50: (255, 200, 0),
    51: (255, 120, 50),
    70: (0, 175, 0),
    71: (135, 60, 0),
    72: (150, 240, 80),
    80: (255, 240, 150),
    81: (255, 0, 0),
    252: (100, 150, 245),
    254: (255, 30, 30),
}
"""RGB colour per raw class id (the SemanticKITTI colour map; moving classes share their static colour)."""


def class_colors(semantic: npt.NDArray[np.integer]) -> npt.NDArray[np.uint8]:
    """(..., 3) uint8 RGB colour per raw class id (unknown ids grey)."""
    lut = np.full((65536, 3), 128, np.uint8)
    for k, c in SEMANTIC_KITTI_RGB.items():
        lut[k] = c
    return np.asarray(lut[np.asarray(semantic, np.int64) & 0xFFFF], dtype=np.uint8)


def bev_image(
    points: npt.NDArray[np.float32],
    semantic: npt.NDArray[np.integer],
    extent: float = 40.0,
    size: int = 800,
    background: int = 18,
) -> npt.NDArray[np.uint8]:
    """(size, size, 3) RGB bird's-eye view of a scan coloured by class, x forward (up), y left.

    Points within ``extent`` metres (square) are drawn as 2×2 pixel dots, lowest first, so taller
    structures stay on top.
    """
    img = np.full((size, size, 3), background, np.uint8)
    scale = size / (2 * extent)
    order = np.argsort(points[:, 2], kind="stable")
    pts, sem = points[order], np.asarray(semantic)[order]
    r = (size / 2 - pts[:, 0] * scale).astype(np.int64)
    c = (size / 2 - pts[:, 1] * scale).astype(np.int64)
    ok = (r >= 0) & (r < size - 1) & (c >= 0) & (c < size - 1)
    col = class_colors(sem[ok])
    # One dot = four pixels; a later (higher) point overwrites all four, so draw the dots point by point
    # in one fancy assignment over the interleaved pixel list.
    rr = (r[ok][:, None] + np.array([0, 0, 1, 1])).reshape(-1)
    cc = (c[ok][:, None] + np.array([0, 1, 0, 1])).reshape(-1)
    img[rr, cc] = np.repeat(col, 4, axis=0)
    mark = (255, 255, 255) if background < 128 else (0, 0, 0)
    cv2.circle(img, (size // 2, size // 2), 4, mark, -1)
    return img


def overlay(
    rgb: npt.NDArray[np.uint8], semantic: npt.NDArray[np.integer], alpha: float = 0.45
) -> npt.NDArray[np.uint8]:
    """The image blended with its 2D ground-truth class colours (sky left untouched)."""
    col = class_colors(semantic).astype(np.float32)
    mask = (np.asarray(semantic) > 0)[..., None]
    out = np.where(mask, rgb.astype(np.float32) * (1 - alpha) + col * alpha, rgb.astype(np.float32))
    return np.clip(out, 0, 255).astype(np.uint8)


def project_points(
    xyz: npt.NDArray[np.float32],
    lidar_to_image: npt.NDArray[np.float64],
    width: int,
    height: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_], npt.NDArray[np.float64]]:
    """Pixel (round(u), round(v)) of each point under ``P2·Tr``, a mask of points inside the image with
    depth > 0.1 m, and the depth."""
    q = xyz.astype(np.float64) @ lidar_to_image[:, :3].T + lidar_to_image[:, 3]
    z = q[:, 2]
    zs = np.where(z > 0.1, z, 1.0)
    u = np.rint(q[:, 0] / zs).astype(np.int64)
    v = np.rint(q[:, 1] / zs).astype(np.int64)
    ok = (z > 0.1) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return u, v, ok, z


def write_previews(
    seq_dir: str | Path, frame: int, image_out: str | Path, bev_out: str | Path, scale: float = 0.5
) -> None:
    """Write a README preview of one frame: the camera image above its ground-truth overlay (scaled by
    ``scale``, 6-bit colour), and the bird's-eye view of its scan coloured by class (white background)."""
    seq = KittiSequence(seq_dir)
    f = seq.frame(frame)
    img = np.concatenate([f.image, overlay(f.image, f.gt2d_semantic)], axis=0)
    size = (int(img.shape[1] * scale), int(img.shape[0] * scale))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    img = (img // 4) * 4 + 2  # 6 bits per channel: the PNG stays small (sensor noise compresses badly)
    cv2.imwrite(str(image_out), cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    bev = bev_image(f.points, f.labels & 0xFFFF, extent=40.0, size=640, background=255)
    cv2.imwrite(str(bev_out), cv2.cvtColor(bev, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
