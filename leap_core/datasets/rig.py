"""The camera rig of a sequence: which cameras a frame has, where their images lie and how LiDAR points
project into each (docs/IMPORT.md, "Several cameras").

Two ways to declare a rig, both beside ``velodyne/``:

- **KITTI** (no ``cameras.yaml``): ``image_2/`` is the first camera, projected with ``P2`` and ``Tr`` of
  ``calib.txt``; every further ``image_K/`` folder (K ≥ 3, e.g. KITTI's right colour camera ``image_3/``)
  is a camera projected with ``PK`` and the same ``Tr``. KITTI's grey cameras ``image_0/`` and
  ``image_1/`` are not read.
- **``cameras.yaml``**: named camera folders, each with its own 3×4 projection ``P`` and 3×4 LiDAR →
  camera transform ``Tr`` (row-major; ``Tr`` may be left out to take ``calib.txt``'s), in the order given.
  ``calib.txt`` keeps its role for ``poses.txt`` (whose camera frame its ``Tr`` defines).

A camera whose LiDAR → camera transform changes from frame to frame (the camera fires at another time than
the LiDAR sweep, and the vehicle moves in between: nuScenes' cameras are up to tens of milliseconds from
the sweep) has ``tr_frames/<camera>.txt``: one 3×4 row-major ``Tr`` per line, line N = frame N as in
``poses.txt``; it replaces the camera's ``Tr`` for projection.

The first camera is the *primary* one: its 2D ground truth lies in ``gt2d/<kind>/`` and its 2D labels in
the run's ``labels2d/<frame>.npz``, as for a one-camera sequence; camera ``name`` of the others uses
``gt2d/<name>/<kind>/`` and ``labels2d/<name>/<frame>.npz``. A one-camera sequence is therefore read and
labeled exactly as before the rig existed.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from leap_core.errors import DatasetError

RIG_FILE = "cameras.yaml"
"""The file naming a sequence's camera folders and their calibration (module docstring)."""
FRAME_TR_FOLDER = "tr_frames"
"""``tr_frames/<camera>.txt``: a camera's LiDAR → camera transform per frame (module docstring)."""
PRIMARY_FOLDER = "image_2"
"""The first camera's folder in the KITTI layout."""
MAX_CAMERAS = 16
"""A rig holds at most this many cameras (nuScenes has 6, Argoverse 2 has 9)."""
GT2D_KINDS = ("semantic", "instance", "name", "cell")
"""Per-frame 2D ground-truth images (``gt2d/<kind>/<frame>.png``); a camera may not be named like one."""
RESERVED_NAMES = frozenset({"velodyne", "labels", "gt2d", "predictions", "confidences", *GT2D_KINDS})
"""Folder names of a sequence that are not camera folders."""
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_KITTI_FOLDER = re.compile(r"^image_([0-9]+)$")


@dataclass(frozen=True)
class Camera:
    """One camera of a rig.

    Attributes:
        name: the folder of its images, beside ``velodyne/`` (``image_2``, ``CAM_FRONT``).
        P: (3, 4) float64 projection of the camera (pixel·depth = P · [x y z 1]ᵀ in its frame).
        Tr: (4, 4) float64 LiDAR → camera transform.
        source: where the calibration was read (``calib.txt P3``, ``cameras.yaml``), for ``leap check``.
    """

    name: str
    P: npt.NDArray[np.float64]
    Tr: npt.NDArray[np.float64]
    source: str = "calib.txt P2"

    @property
    def lidar_to_image(self) -> npt.NDArray[np.float64]:
        """(3, 4) ``M = P · Tr``: pixel·depth = M · [x y z 1]ᵀ for LiDAR points."""
        return self.P @ self.Tr


def gt2d_folder(cameras: tuple[Camera, ...] | list[Camera], camera: int, kind: str) -> str:
    """The folder (relative to the sequence) of camera ``camera``'s 2D ground truth of ``kind``:
    ``gt2d/<kind>`` for the primary camera, ``gt2d/<name>/<kind>`` for the others."""
    if camera == 0:
        return f"gt2d/{kind}"
    return f"gt2d/{cameras[camera].name}/{kind}"


def kitti_camera_folders(root: Path) -> list[tuple[int, str]]:
    """``(K, "image_K")`` of the folders ``image_K/`` with K ≥ 3 beside ``velodyne/``, by K: the KITTI
    layout's cameras after ``image_2``."""
    out = []
    try:
        names = [p.name for p in root.iterdir() if p.is_dir()]
    except OSError:
        return []
    for name in names:
        match = _KITTI_FOLDER.match(name)
        if match and int(match.group(1)) >= 3 and str(int(match.group(1))) == match.group(1):
            out.append((int(match.group(1)), name))
    return sorted(out)


def _matrix(path: Path, where: str, value: Any, shape: tuple[int, int]) -> npt.NDArray[np.float64]:
    """A row-major matrix of a ``cameras.yaml`` entry: a flat list of numbers or a list of rows."""
    flat = value
    if isinstance(value, list) and value and all(isinstance(r, list) for r in value):
        flat = [x for r in value for x in r]
    rows, cols = shape
    if not isinstance(flat, list) or not all(
        isinstance(x, int | float) and not isinstance(x, bool) for x in flat
    ):
        raise DatasetError(
            path, f"{where}: must be a list of {rows * cols} numbers ({rows}×{cols} row-major)"
        )
    if len(flat) != rows * cols:
        raise DatasetError(
            path, f"{where}: has {len(flat)} values, expected {rows * cols} ({rows}×{cols} row-major)"
        )
    if not all(math.isfinite(float(x)) for x in flat):
        raise DatasetError(path, f"{where}: has non-finite values")
    return np.asarray(flat, dtype=np.float64).reshape(rows, cols)


def check_projection(path: Path, where: str, p: npt.NDArray[np.float64]) -> None:
    """Refuse a projection whose left 3×3 block is singular (no camera projects so)."""
    if abs(np.linalg.det(p[:, :3])) < 1e-9:
        raise DatasetError(path, f"{where}: left 3×3 block is singular (not a camera projection)")


def check_transform(path: Path, where: str, tr: npt.NDArray[np.float64]) -> None:
    """Refuse a LiDAR → camera transform whose rotation is singular."""
    if abs(np.linalg.det(tr[:3, :3])) < 1e-6:
        raise DatasetError(path, f"{where}: rotation is singular")


def camera_name_problem(name: object) -> str | None:
    """Why ``name`` cannot name a camera folder, or None."""
    if not isinstance(name, str) or not _NAME.match(name):
        return "a camera name is a folder name of letters, digits, '_', '.' and '-' (at most 64)"
    if name in RESERVED_NAMES:
        return f"{name!r} is a folder of the sequence layout, not a camera folder"
    return None


def read_rig_file(path: Path, default_tr: npt.NDArray[np.float64]) -> tuple[Camera, ...]:
    """Read ``cameras.yaml``::

        cameras:
          CAM_FRONT:                  # the folder of its images
            P: [fx, 0, cx, 0,  0, fy, cy, 0,  0, 0, 1, 0]   # 3×4 row-major (or three rows)
            Tr: [...]                 # 3×4 row-major LiDAR → camera; omitted: calib.txt's Tr
          CAM_BACK: {...}

    Raises:
        DatasetError: naming the file and the camera or field (with what is expected) for anything else.
    """
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8-sig"))
    except OSError as exc:
        raise DatasetError(path, f"cannot read the camera rig ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise DatasetError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, Mapping) or not isinstance(data.get("cameras"), Mapping) or not data["cameras"]:
        raise DatasetError(path, "expected 'cameras:' mapping each camera folder name to its P (and Tr)")
    extra = sorted(str(k) for k in data if k != "cameras")
    if extra:
        raise DatasetError(path, f"unknown key {extra[0]!r} (the file holds only 'cameras:')")
    cams = data["cameras"]
    if len(cams) > MAX_CAMERAS:
        raise DatasetError(path, f"{len(cams)} cameras; a rig holds at most {MAX_CAMERAS}")
    out = []
    for name, entry in cams.items():
        problem = camera_name_problem(name)
        if problem:
            raise DatasetError(path, f"cameras.{name}: {problem}")
        where = f"cameras.{name}"
        if not isinstance(entry, Mapping) or "P" not in entry:
            raise DatasetError(path, f"{where}: expected a mapping with 'P' (and optionally 'Tr')")
        unknown = sorted(str(k) for k in entry if k not in ("P", "Tr"))
        if unknown:
            raise DatasetError(path, f"{where}: unknown key {unknown[0]!r} (expected 'P' and 'Tr')")
        p = _matrix(path, f"{where}.P", entry["P"], (3, 4))
        check_projection(path, f"{where}.P", p)
        tr = np.array(default_tr, dtype=np.float64)
        if "Tr" in entry:
            tr = np.eye(4)
            tr[:3] = _matrix(path, f"{where}.Tr", entry["Tr"], (3, 4))
            check_transform(path, f"{where}.Tr", tr)
        out.append(Camera(str(name), p, tr, source=RIG_FILE))
    return tuple(out)


def rig_entries(root: Path) -> list[str]:
    """The entries of the sequence folder ``root`` a camera rig adds to what is read (``cameras.yaml``,
    ``tr_frames``, the ``image_K/`` folders and the camera folders ``cameras.yaml`` names), for a caller
    that confines each entry; never raises (a malformed ``cameras.yaml`` is the reader's to refuse)."""
    out = [RIG_FILE, FRAME_TR_FOLDER, *(name for _, name in kitti_camera_folders(root))]
    try:
        data = yaml.safe_load((root / RIG_FILE).read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return out
    cams = data.get("cameras") if isinstance(data, Mapping) else None
    if isinstance(cams, Mapping):
        out += [str(name) for name in cams if camera_name_problem(name) is None]
    return list(dict.fromkeys(out))


def camera_rig_text(cameras: list[Camera] | tuple[Camera, ...]) -> str:
    """``cameras.yaml`` text for ``cameras`` (the format :func:`read_rig_file` reads; 12 significant
    digits, as ``calib.txt``)."""

    def row(m: npt.NDArray[np.float64]) -> str:
        return "[" + ", ".join(f"{v:.12e}" for v in np.asarray(m[:3], dtype=np.float64).reshape(-1)) + "]"

    lines = ["cameras:"]
    for cam in cameras:
        lines += [f"  {cam.name}:", f"    P: {row(cam.P)}", f"    Tr: {row(cam.Tr)}"]
    return "\n".join(lines) + "\n"


__all__ = [
    "FRAME_TR_FOLDER",
    "GT2D_KINDS",
    "MAX_CAMERAS",
    "PRIMARY_FOLDER",
    "RIG_FILE",
    "Camera",
    "camera_name_problem",
    "camera_rig_text",
    "check_projection",
    "check_transform",
    "gt2d_folder",
    "kitti_camera_folders",
    "read_rig_file",
    "rig_entries",
]
