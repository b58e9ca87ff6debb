"""KITTI odometry / SemanticKITTI sequence I/O.

Format facts (docs/METHOD.md, checked against PRBonn/semantic-kitti-api):
- ``velodyne/*.bin``: float32 (x, y, z, remission) quadruples; size a multiple of 16 bytes.
- ``labels/*.label``: uint32 per point, semantic id in the low 16 bits, instance id in the high 16.
- ``calib.txt``: ``P0:``..``P3:`` 3×4 projections and ``Tr:`` 3×4 LiDAR→left camera; colour camera = P2.
  semantic-kitti-api reads only ``Tr`` (every line ``key: numbers``), so :func:`write_calib` writes only
  the lines it knows: ``P2`` and ``Tr``.
  The KITTI object / tracking variants (``R0_rect`` / ``R_rect`` 3×3 and ``Tr_velo_to_cam`` /
  ``Tr_velo_cam`` 3×4, keys with or without a colon) are read too: there Tr = R0_rect · Tr_velo_to_cam.
- ``poses.txt``: 3×4 per frame in the LEFT CAMERA frame; LiDAR pose in world = Tr⁻¹ · pose · Tr.
  Optional: a sequence recorded without poses opens, and only what needs poses fails
  (:class:`~leap_core.errors.PosesMissingError`). Estimated poses (``leap poses``, KISS-ICP) are a
  ``poses.txt`` with a ``poses_estimated.json`` note beside it saying how they were made.
- Frame numbers: when every scan's stem is a number, scan ``NNNNNN.bin`` is frame NNNNNN and takes line
  NNNNNN (0-based, blank lines skipped) of ``poses.txt`` and ``times.txt``, which may hold more lines than
  there are scans (a copied subset keeps the sequence's files; gaps in the numbering work). Otherwise the
  frame number is the scan's position and both files need exactly one line per scan. World = the LiDAR
  frame of pose line 0, so a frame's world coordinates do not depend on which other scans are present.
"""

from __future__ import annotations

import bisect
import functools
import io
import os
import re
import stat
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np
import numpy.typing as npt

from leap_core.datasets.rig import (
    FRAME_TR_FOLDER,
    GT2D_KINDS,
    PRIMARY_FOLDER,
    RIG_FILE,
    Camera,
    check_projection,
    gt2d_folder,
    kitti_camera_folders,
    read_rig_file,
)
from leap_core.errors import DatasetError, LeapError, PosesMissingError
from leap_core.io_utils import atomic_write, atomic_write_bytes
from leap_core.paths import UnusablePath, real_path, real_path_or_none

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: Written beside an estimated ``poses.txt``: JSON saying the poses are estimated, by what and how.
POSES_NOTE = "poses_estimated.json"

FRAME_FOLDERS: dict[str, tuple[str, ...]] = {
    "velodyne": (".bin",),
    "labels": (".label",),
    "image_2": IMAGE_SUFFIXES,
    "gt2d/semantic": (".png",),
    "gt2d/instance": (".png",),
    "gt2d/name": (".png",),
    "gt2d/cell": (".png",),
}
"""The folders of per-frame files a sequence is read from, with the suffixes of those files."""


# ------------------------------------------------------------------------------------- containment
LINK_OUTSIDE = "a link leading outside the sequence folder"
"""What a per-frame file that is a symbolic link to a place outside the sequence's roots is."""
NOT_REGULAR = "not a regular file (a pipe, socket or device)"
A_DIRECTORY = "a directory, not a file"
DANGLING = "a link to nothing"
A_LOOP = "a symlink loop (a link that leads back to itself, or too many links in a row)"
NEVER_READ = frozenset({LINK_OUTSIDE, NOT_REGULAR})
"""Problems of a per-frame file that refuse the sequence: the reader never opens such a file (one linked
outside may be anyone's, and reading a pipe blocks)."""
UNREADABLE_FIX = "the pipeline does not read it: put the file itself in its place (or link the whole folder)"
"""How to fix a per-frame file the reader refuses (:func:`entry_problem`)."""


def sequence_roots(root: str | Path, extra: Iterable[str] = ()) -> tuple[Path, ...]:
    """Where the per-frame files of the sequence folder ``root`` may lie: the folder itself and each of its
    folders of per-frame files (:data:`FRAME_FOLDERS`, then the relative folders ``extra``: the further
    cameras' image and 2D ground-truth folders), all resolved.

    A ``velodyne/`` linked to another disk is part of the sequence (the layout is its owner's choice, and
    the app confines these entries to its data roots); a scan inside it linked elsewhere is not.
    """
    root = Path(root)
    out = [_resolved(root)]
    for name in (*FRAME_FOLDERS, *extra):
        entry = root / name
        if entry.exists():
            out.append(_resolved(entry))
    return tuple(dict.fromkeys(out))


def _resolved(path: Path) -> Path:
    """``path`` with every link followed.

    Raises:
        DatasetError: ``path`` is (or goes through) a symbolic link loop, naming it.
    """
    try:
        return real_path(path)
    except UnusablePath as exc:
        raise DatasetError(path, f"this path {exc}") from None


def _inside(path: Path, roots: Sequence[Path]) -> bool:
    return any(path == r or path.is_relative_to(r) for r in roots)


def _followed_link(link: Path, roots: Sequence[Path]) -> str | os.stat_result:
    """The status of what the symbolic link ``link`` leads to, or why it may not be followed: a loop, a
    target outside ``roots``, no target."""
    target = real_path_or_none(link)
    if target is None:
        return A_LOOP
    if not _inside(target, roots):
        return LINK_OUTSIDE
    try:
        return link.stat()
    except OSError:
        return DANGLING


def entry_problem(path: Path, roots: Sequence[Path]) -> str | None:
    """Why the reader may not read the per-frame file ``path``, or None for a regular file it may read.

    A symbolic link must lead inside ``roots`` (:func:`sequence_roots`), so a file linked to
    ``/etc/passwd`` is never opened; a directory, a dangling link, a link loop, a pipe, a socket or a device
    is no file of a sequence (reading a pipe would block).
    """
    try:
        st = path.lstat()
    except OSError:
        return None  # absent: whoever needs it says so
    if stat.S_ISLNK(st.st_mode):
        followed = _followed_link(path, roots)
        if isinstance(followed, str):
            return followed
        st = followed
    if stat.S_ISDIR(st.st_mode):
        return A_DIRECTORY
    if not stat.S_ISREG(st.st_mode):
        return NOT_REGULAR
    return None


def folder_problems(folder: Path, suffixes: Iterable[str], roots: Sequence[Path]) -> list[tuple[str, str]]:
    """``(name, problem)`` of each entry of ``folder`` ending in one of ``suffixes`` (case-insensitive) that
    the reader may not read (:func:`entry_problem`), in name order; [] for a missing folder."""
    allowed = tuple(s.lower() for s in suffixes)
    try:
        with os.scandir(folder) as it:
            # A plain file (the directory listing says so: no extra system call) lies in its folder.
            odd = sorted(
                e.name
                for e in it
                if e.name.lower().endswith(allowed) and not e.is_file(follow_symlinks=False)
            )
    except OSError:
        return []
    out = []
    for name in odd:
        problem = entry_problem(folder / name, roots)
        if problem is not None:
            out.append((name, problem))
    return out


# --------------------------------------------------------------------------------------------- scans
def read_scan(path: str | Path) -> npt.NDArray[np.float32]:
    """Read a ``.bin`` scan as a read-only (N, 4) float32 array (x, y, z, remission).

    Raises:
        DatasetError: naming the file when it is unreadable, not a whole number of points, or holds
            NaN / inf values.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read scan ({exc.strerror or exc})") from exc
    if len(raw) % 16:
        raise DatasetError(path, f"size {len(raw)} bytes is not a multiple of 16 (float32 x,y,z,remission)")
    pts = np.frombuffer(raw, dtype=np.float32).reshape(-1, 4)
    if not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise DatasetError(path, f"{bad} points have non-finite values (NaN or inf)")
    return pts


def scan_point_count(path: str | Path) -> int:
    """The number of points of a ``.bin`` scan, from its size alone (16 bytes a point; nothing is read).

    Raises:
        DatasetError: naming the file when it is missing or not a whole number of points.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise DatasetError(path, f"cannot read scan ({exc.strerror or exc})") from exc
    if size % 16:
        raise DatasetError(path, f"size {size} bytes is not a multiple of 16 (float32 x,y,z,remission)")
    return size // 16


def read_scan_rows(path: str | Path, rows: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """Points ``rows`` (M,) of a ``.bin`` scan as an (M, 4) float32 array, in the order given.

    Reads only the pages the rows lie on (a memory map): the fuse stage needs the ≈ 12 % of a scan's
    points its camera painted, and reading the whole scan cost 0.6-0.8 ms a frame against 0.3 ms for these.
    The same checks as :func:`read_scan`, finiteness on the rows read only.

    Raises:
        DatasetError: naming the file when it is unreadable, not a whole number of points, shorter than a
            row asks for, or one of the rows holds NaN / inf values.
    """
    path = Path(path)
    idx = np.asarray(rows, dtype=np.int64).reshape(-1)
    n = scan_point_count(path)
    outside = idx[(idx < 0) | (idx >= n)]
    if len(outside):
        raise DatasetError(path, f"point {int(outside[0])} asked for, the scan holds {n} points")
    if n == 0 or len(idx) == 0:
        return np.zeros((0, 4), np.float32)
    try:
        mm = np.memmap(path, dtype=np.float32, mode="r", shape=(n, 4))
    except OSError as exc:
        raise DatasetError(path, f"cannot read scan ({exc.strerror or exc})") from exc
    pts = np.asarray(mm[idx])
    del mm
    if not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise DatasetError(path, f"{bad} points have non-finite values (NaN or inf)")
    return pts


def write_scan(path: str | Path, points: npt.ArrayLike) -> None:
    """Write (N, 4) points as float32 ``.bin`` (atomic)."""
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float32))
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise ValueError(f"scan must be (N, 4), got {pts.shape}")
    # read_scan refuses non-finite values, so writing them would only produce an unreadable file.
    if not np.isfinite(pts).all():
        raise ValueError(f"scan for {path} has non-finite values")
    atomic_write_bytes(path, pts.tobytes())


# -------------------------------------------------------------------------------------------- labels
def read_label(path: str | Path, num_points: int | None = None) -> npt.NDArray[np.uint32]:
    """Read a ``.label`` file as a read-only (N,) uint32 array; check the count against the scan when given.

    Raises:
        DatasetError: naming the file when it is unreadable, not a whole number of uint32 values, or
            its count differs from ``num_points``.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(path, f"cannot read labels ({exc.strerror or exc})") from exc
    if len(raw) % 4:
        raise DatasetError(path, f"size {len(raw)} bytes is not a multiple of 4 (uint32 per point)")
    labels = np.frombuffer(raw, dtype=np.uint32)
    if num_points is not None and labels.shape[0] != num_points:
        raise DatasetError(path, f"label count {labels.shape[0]} != point count {num_points} of its scan")
    return labels


def write_label(path: str | Path, semantic: npt.ArrayLike, instance: npt.ArrayLike | None = None) -> None:
    """Write uint32 ``semantic | instance << 16`` atomically (temp file + rename).

    Args:
        semantic: (N,) integer semantic ids 0..65535.
        instance: optional (N,) integer instance ids 0..65535 (0 when omitted).
    """
    sem_in = np.asarray(semantic)
    if sem_in.ndim != 1:
        raise ValueError(f"labels must be 1-D, got {sem_in.shape}")
    if sem_in.size and (sem_in.min() < 0 or sem_in.max() > 0xFFFF):
        raise ValueError(f"semantic ids for {path} must be 0..65535")
    sem = sem_in.astype(np.uint32)
    if instance is not None:
        inst = np.asarray(instance)
        if inst.shape != sem.shape:
            raise ValueError(f"instance ids {inst.shape} do not match semantic ids {sem.shape}")
        if inst.size and (inst.min() < 0 or inst.max() > 0xFFFF):
            raise ValueError(f"instance ids for {path} must be 0..65535")
        sem = sem | (inst.astype(np.uint32) << np.uint32(16))
    atomic_write_bytes(path, np.ascontiguousarray(sem).tobytes())


# --------------------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class Calib:
    """Camera calibration of a sequence.

    Attributes:
        P2: (3, 4) float64 projection of the left colour camera (rectified frame).
        Tr: (4, 4) float64 LiDAR → left camera (rectified frame 0) transform.
    """

    P2: npt.NDArray[np.float64]
    Tr: npt.NDArray[np.float64]

    @property
    def lidar_to_image(self) -> npt.NDArray[np.float64]:
        """(3, 4) matrix M with pixel·depth = M · [x y z 1]ᵀ for LiDAR points."""
        return self.P2 @ self.Tr


def _parse_matrix(path: Path, key: str, text: str, rows: int = 3, cols: int = 4) -> npt.NDArray[np.float64]:
    try:
        vals = np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(path, f"'{key}' has a non-numeric value ({exc})") from exc
    if vals.size != rows * cols:
        raise DatasetError(
            path, f"'{key}' has {vals.size} values, expected {rows * cols} ({rows}×{cols} row-major)"
        )
    if not np.isfinite(vals).all():
        raise DatasetError(path, f"'{key}' has non-finite values")
    return vals.reshape(rows, cols)


# "KEY: values" (odometry, object) or "KEY values" (tracking); blank lines, comments and dates are skipped.
_CALIB_LINE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?::|\s)\s*(.*)$")


def _calib_entries(path: Path) -> dict[str, str]:
    """``calib.txt``'s lines as key → the text of its values."""
    try:
        lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except OSError as exc:
        raise DatasetError(path, f"cannot read calibration ({exc.strerror or exc})") from exc
    entries: dict[str, str] = {}
    for line in lines:
        match = _CALIB_LINE.match(line)
        if match:
            entries[match.group(1)] = match.group(2)
    return entries


def read_rig(root: str | Path, calib: Calib) -> tuple[Camera, ...]:
    """The cameras of the sequence folder ``root`` whose ``calib.txt`` reads as ``calib``
    (:mod:`leap_core.datasets.rig`): those of ``cameras.yaml`` when it exists, else ``image_2`` (``P2``,
    ``Tr``) and each further ``image_K/`` folder with ``PK`` and the same ``Tr``.

    Raises:
        DatasetError: naming ``cameras.yaml`` or ``calib.txt``: a malformed rig, or an ``image_K/`` folder
            without its ``PK:`` line or whose ``PK`` is a copy of ``P2``.
    """
    root = Path(root)
    if (root / RIG_FILE).is_file():
        return read_rig_file(root / RIG_FILE, calib.Tr)
    cams = [Camera(PRIMARY_FOLDER, calib.P2, calib.Tr, "calib.txt P2")]
    folders = kitti_camera_folders(root)
    if folders:
        path = root / "calib.txt"
        entries = _calib_entries(path)
        for k, name in folders:
            key = f"P{k}"
            if key not in entries:
                raise DatasetError(
                    path, f"no '{key}:' line for the camera folder {name}/ (its 3×4 projection; or remove it)"
                )
            p = _parse_matrix(path, key, entries[key])
            check_projection(path, f"'{key}'", p)
            if np.array_equal(p, calib.P2):
                # Same P and same Tr is camera 2's view: what earlier versions of write_calib wrote for
                # every camera, not a calibration of this one.
                raise DatasetError(
                    path,
                    f"'{key}' is a copy of 'P2', so {name}/ would be projected as image_2 (an earlier leap "
                    f"synth or import wrote P2 for every camera): put {name}'s own projection in '{key}:' "
                    "or remove the folder",
                )
            cams.append(Camera(name, p, calib.Tr, f"calib.txt {key}"))
    return tuple(cams)


def read_calib(path: str | Path) -> Calib:
    """Read a KITTI ``calib.txt``: P2 and the LiDAR → rectified left camera transform.

    Uses ``Tr`` (odometry format) when present, else ``R0_rect · Tr_velo_to_cam`` (object / tracking
    format, with ``R_rect`` / ``Tr_velo_cam`` accepted as aliases). Extra keys and blank lines are ignored.

    Raises:
        DatasetError: naming the file for a missing or malformed P2 / Tr, non-finite values, or a
            singular rotation or camera matrix.
    """
    path = Path(path)
    entries = _calib_entries(path)
    if "P2" not in entries:
        raise DatasetError(path, "missing 'P2:' line (the left colour camera's 3×4 projection)")
    p2 = _parse_matrix(path, "P2", entries["P2"])
    if abs(np.linalg.det(p2[:, :3])) < 1e-9:
        raise DatasetError(path, "'P2' left 3×3 block is singular (not a camera projection)")
    tr = np.eye(4)
    if "Tr" in entries:
        tr[:3] = _parse_matrix(path, "Tr", entries["Tr"])
        tr_key = "Tr"
    else:
        velo_key = next((k for k in ("Tr_velo_to_cam", "Tr_velo_cam") if k in entries), None)
        if velo_key is None:
            raise DatasetError(path, "missing 'Tr:' line (3×4 LiDAR→left camera transform)")
        tr[:3] = _parse_matrix(path, velo_key, entries[velo_key])
        rect_key = next((k for k in ("R0_rect", "R_rect") if k in entries), None)
        if rect_key is not None:
            # Object/tracking files give Tr to the unrectified camera 0; P2 expects rectified coordinates.
            rect = np.eye(4)
            rect[:3, :3] = _parse_matrix(path, rect_key, entries[rect_key], rows=3, cols=3)
            tr = rect @ tr
        tr_key = velo_key
    if abs(np.linalg.det(tr[:3, :3])) < 1e-6:
        raise DatasetError(path, f"'{tr_key}' rotation is singular")
    return Calib(P2=p2, Tr=tr)


def write_calib(path: str | Path, calib: Calib) -> None:
    """Write a KITTI ``calib.txt`` with the lines ``calib`` knows: ``P2`` and ``Tr`` (atomic).

    No ``P0``, ``P1`` or ``P3``: a copy of ``P2`` under those keys would make an ``image_3/`` folder added
    later project as if it were camera 2; without the line, :func:`read_rig` refuses that folder, naming
    the missing line.
    """

    def fmt(m: npt.NDArray[np.float64]) -> str:
        return " ".join(f"{v:.12e}" for v in m.reshape(-1))

    lines = [f"P2: {fmt(calib.P2)}", f"Tr: {fmt(calib.Tr[:3])}"]
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


# --------------------------------------------------------------------------------------------- poses
def read_poses(path: str | Path) -> npt.NDArray[np.float64]:
    """Read ``poses.txt`` as (F, 4, 4) camera-frame poses (blank lines are skipped).

    Raises:
        DatasetError: naming the file and line for a row that is not 12 finite numbers.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
        lines = [ln for ln in text.splitlines() if ln.strip()]
    except OSError as exc:
        raise DatasetError(path, f"cannot read poses ({exc.strerror or exc})") from exc
    poses = np.tile(np.eye(4), (len(lines), 1, 1))
    for i, ln in enumerate(lines):
        poses[i, :3] = _parse_matrix(path, f"line {i + 1}", ln)
    return poses


def write_poses(path: str | Path, cam_poses: npt.ArrayLike) -> None:
    """Write (F, 4, 4) or (F, 3, 4) camera-frame poses as ``poses.txt`` (atomic)."""
    poses = np.asarray(cam_poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be (F, 4, 4) or (F, 3, 4), got {poses.shape}")
    text = "\n".join(" ".join(f"{v:.12e}" for v in p[:3].reshape(-1)) for p in poses) + "\n"
    atomic_write_bytes(path, text.encode())


def lidar_poses(cam_poses: npt.NDArray[np.float64], tr: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """LiDAR→world poses from camera-frame poses: Tr⁻¹ · P · Tr, re-based on the first pose given
    (a sequence passes every line of ``poses.txt``, so world = the LiDAR frame of line 0).

    Re-basing keeps world coordinates near the origin, where float32 keeps centimetre precision.
    """
    tr_inv = np.linalg.inv(tr)
    lp = tr_inv[None] @ cam_poses @ tr[None]
    return np.linalg.inv(lp[0])[None] @ lp


# -------------------------------------------------------------------------------------------- images
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
"""The last 12 bytes of every complete PNG: its empty IEND chunk (length 0, type, CRC)."""
JPEG_START, JPEG_END = b"\xff\xd8", b"\xff\xd9"
_JPEG_FRAMES = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
"""JPEG start-of-frame markers (SOF0-SOF15 but DHT C4, JPG C8 and DAC CC): they hold the image size."""
_JPEG_ALONE = frozenset({0x01, *range(0xD0, 0xD8)})
"""JPEG markers without a length field (TEM, RST0-7)."""
_JPEG_MAX_SEGMENTS = 4096


def _png_size(fh: BinaryIO, size: int) -> tuple[int, int]:
    fh.seek(8)
    head = fh.read(16)
    if len(head) < 16 or head[4:8] != b"IHDR":
        raise ValueError("a PNG without its IHDR header chunk")
    width, height = int.from_bytes(head[8:12], "big"), int.from_bytes(head[12:16], "big")
    fh.seek(max(size - len(PNG_END), 0))
    if fh.read(len(PNG_END)) != PNG_END:
        raise ValueError("a truncated PNG (it does not end with its IEND chunk)")
    return width, height


def _jpeg_size(fh: BinaryIO, size: int) -> tuple[int, int]:
    pos = 2
    for _ in range(_JPEG_MAX_SEGMENTS):
        fh.seek(pos)
        marker = fh.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            raise ValueError(f"a truncated or damaged JPEG (no marker at byte {pos})")
        code = marker[1]
        if code == 0xFF:  # a fill byte before the marker
            pos += 1
            continue
        if code in _JPEG_ALONE:
            pos += 2
            continue
        if code in (0xD9, 0xDA):  # the end, or the scan data, before any frame header
            raise ValueError("a JPEG without a frame header")
        length = int.from_bytes(fh.read(2), "big")
        if code in _JPEG_FRAMES:
            frame = fh.read(5)
            if len(frame) < 5:
                break
            height, width = int.from_bytes(frame[1:3], "big"), int.from_bytes(frame[3:5], "big")
            fh.seek(max(size - 64, 0))
            # Some writers pad a JPEG with zero bytes after its end-of-image marker.
            if not fh.read(64).rstrip(b"\x00").endswith(JPEG_END):
                raise ValueError("a truncated JPEG (it does not end with its end-of-image marker)")
            return width, height
        if length < 2:
            raise ValueError(f"a damaged JPEG (segment length {length} at byte {pos})")
        pos += 2 + length
    raise ValueError("a truncated or damaged JPEG (no frame header)")


def read_image_size(fh: BinaryIO, size: int) -> tuple[int, int]:
    """``(width, height)`` of the PNG or JPEG in ``fh`` (``size`` bytes long), from its header alone, after
    checking that it is complete: a PNG must end with its IEND chunk, a JPEG with its end-of-image marker
    (trailing zero bytes allowed). Reads a few small pieces, never the pixel data.

    Raises:
        ValueError: what is wrong ("a truncated PNG (...)", "not a PNG or JPEG", ...).
    """
    fh.seek(0)
    magic = fh.read(len(PNG_SIGNATURE))
    if magic == PNG_SIGNATURE:
        width, height = _png_size(fh, size)
    elif magic[:2] == JPEG_START:
        width, height = _jpeg_size(fh, size)
    else:
        raise ValueError("not a PNG or JPEG image" if magic else "an empty file")
    if width <= 0 or height <= 0:
        raise ValueError(f"an image of {width}×{height} pixels")
    return width, height


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of the image file ``path``, from its header (:func:`read_image_size`).

    Raises:
        DatasetError: naming the file when it is unreadable, not a PNG or JPEG, or truncated.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return read_image_size(fh, os.fstat(fh.fileno()).st_size)
    except OSError as exc:
        raise DatasetError(path, f"cannot read image ({exc.strerror or exc})") from exc
    except ValueError as exc:
        raise DatasetError(path, f"unreadable image: {exc}") from None


def read_image(path: str | Path) -> npt.NDArray[np.uint8]:
    """Read a colour image as (H, W, 3) uint8 RGB.

    Raises:
        DatasetError: naming the file when it is missing, empty, not a PNG or JPEG, or truncated (a
            decoder fills a cut-off JPEG with grey and says nothing: it is refused here instead).
    """
    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8) if path.is_file() else None
    except OSError as exc:
        raise DatasetError(path, f"cannot read image ({exc.strerror or exc})") from exc
    if data is None or not data.size:
        raise DatasetError(path, "unreadable image (missing, empty or not a PNG/JPEG)")
    try:
        read_image_size(io.BytesIO(data.tobytes()), int(data.size))
    except ValueError as exc:
        raise DatasetError(path, f"unreadable image: {exc}") from None
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(path, "unreadable image (missing, empty or not a PNG/JPEG)")
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), dtype=np.uint8)


def write_image(path: str | Path, rgb: npt.NDArray[np.uint8]) -> None:
    """Write an (H, W, 3) uint8 RGB image; the format follows the suffix (.png lossless, .jpg lossy)."""
    path = Path(path)
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"image for {path} must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    ok, buf = cv2.imencode(path.suffix or ".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"cannot encode image for {path}")
    atomic_write_bytes(path, buf.tobytes())


def read_png16(path: str | Path) -> npt.NDArray[np.uint16]:
    """Read a single-channel 16-bit PNG (2D ground-truth masks)."""
    path = Path(path)
    try:
        data = np.fromfile(path, dtype=np.uint8) if path.is_file() else None
    except OSError as exc:
        raise DatasetError(path, f"cannot read mask ({exc.strerror or exc})") from exc
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data is not None and data.size else None
    if img is None or img.ndim != 2:
        raise DatasetError(path, "unreadable 16-bit mask PNG")
    return img.astype(np.uint16)


def write_png16(path: str | Path, arr: npt.NDArray[np.integer]) -> None:
    """Write an (H, W) integer array with values 0..65535 as a 16-bit PNG (atomic)."""
    arr = np.asarray(arr)
    if arr.ndim != 2:
        raise ValueError(f"mask for {path} must be (H, W), got {arr.shape}")
    if arr.size and (arr.min() < 0 or arr.max() > 0xFFFF):
        raise ValueError(f"mask values for {path} must be 0..65535")
    ok, buf = cv2.imencode(".png", arr.astype(np.uint16))
    if not ok:
        raise ValueError(f"cannot encode mask for {path}")
    atomic_write_bytes(path, buf.tobytes())


# ------------------------------------------------------------------------------------------ sequence
class Frame:
    """One frame of a sequence as one camera sees it; every array is read from disk on first access only.

    ``camera`` picks the camera of the rig (:attr:`KittiSequence.cameras`) whose image and 2D ground truth
    the frame's image attributes read; 0, the primary camera, is what a one-camera sequence has.
    """

    def __init__(self, seq: KittiSequence, index: int, camera: int = 0) -> None:
        self.seq = seq
        self.index = index
        self.frame_id = seq.frame_ids[index]
        self.number = seq.frame_numbers[index]
        """The frame number (:attr:`KittiSequence.frame_numbers`): what seeds and names depend on, never
        :attr:`index`, the position among the scans present."""
        if not 0 <= camera < len(seq.cameras):
            raise IndexError(f"camera {camera} out of range 0..{len(seq.cameras) - 1}")
        self.camera = camera
        """The index of the camera in :attr:`KittiSequence.cameras`."""

    @property
    def rig_camera(self) -> Camera:
        """The camera this frame's image attributes read."""
        return self.seq.cameras[self.camera]

    def cameras(self) -> list[Frame]:
        """This frame as each camera of the rig sees it, in rig order (one for a one-camera sequence)."""
        return [
            self if k == self.camera else Frame(self.seq, self.index, k) for k in range(len(self.seq.cameras))
        ]

    @functools.cached_property
    def points(self) -> npt.NDArray[np.float32]:
        """(N, 4) float32 x, y, z, remission in the LiDAR frame."""
        return read_scan(self.seq.confined(self.seq.scan_path(self.index)))

    def points_at(self, rows: npt.ArrayLike) -> npt.NDArray[np.float32]:
        """(M, 4) float32 points ``rows`` of the scan: from :attr:`points` when they were read, else only
        those rows from the file (:func:`read_scan_rows`)."""
        if "points" in self.__dict__:
            return self.points[np.asarray(rows, dtype=np.int64)]
        return read_scan_rows(self.seq.confined(self.seq.scan_path(self.index)), rows)

    @functools.cached_property
    def num_points(self) -> int:
        """N, the scan's point count: from :attr:`points` when they were read, else from the file's size
        (reading a scan only to count it was most of the bytes ``evaluate`` read per frame)."""
        if "points" in self.__dict__:
            return int(self.points.shape[0])
        return scan_point_count(self.seq.confined(self.seq.scan_path(self.index)))

    @property
    def pose(self) -> npt.NDArray[np.float64]:
        """(4, 4) LiDAR → world (world = LiDAR frame of pose line 0)."""
        return np.asarray(self.seq.poses[self.index], dtype=np.float64)

    @property
    def calib(self) -> Calib:
        """The calibration of the frame's camera: ``P2`` its projection, ``Tr`` LiDAR → that camera (for
        the primary camera of a KITTI layout, the sequence's ``calib.txt``)."""
        if (
            self.camera == 0
            and self.seq.rig_source == "calib.txt"
            and self.seq.camera_tr(self.index) is self.seq.calib.Tr
        ):
            return self.seq.calib
        return Calib(P2=self.rig_camera.P, Tr=self.seq.camera_tr(self.index, self.camera))

    @property
    def has_image(self) -> bool:
        return self.seq.image_path(self.index, self.camera) is not None

    @functools.cached_property
    def image(self) -> npt.NDArray[np.uint8]:
        """(H, W, 3) uint8 RGB of the frame's camera (the left colour camera in KITTI)."""
        p = self.seq.image_path(self.index, self.camera)
        if p is None:
            raise DatasetError(self.seq.root / self.rig_camera.name, f"no image for frame {self.frame_id}")
        return read_image(self.seq.confined(p))

    def gt2d_path(self, kind: str) -> Path:
        """The frame's 2D ground-truth image of ``kind`` (``semantic``, ``instance``, ``name``, ``cell``) for
        its camera (:func:`~leap_core.datasets.rig.gt2d_folder`)."""
        return self.seq.root / gt2d_folder(self.seq.cameras, self.camera, kind) / f"{self.frame_id}.png"

    @property
    def has_labels(self) -> bool:
        """Whether the frame has a ground-truth ``.label`` file (a regular file: a directory of that name
        is none; :meth:`KittiSequence.label_problem` says what it is)."""
        return self.seq.label_path(self.index).is_file()

    @functools.cached_property
    def labels(self) -> npt.NDArray[np.uint32]:
        """(N,) uint32 raw SemanticKITTI labels (semantic | instance << 16)."""
        return read_label(self.seq.confined(self.seq.label_path(self.index)), num_points=self.num_points)

    @functools.cached_property
    def gt2d_semantic(self) -> npt.NDArray[np.uint16]:
        """(H, W) raw semantic id per pixel (synthetic data's 2D ground truth; 0 = none)."""
        return read_png16(self.seq.confined(self.gt2d_path("semantic")))

    @functools.cached_property
    def gt2d_instance(self) -> npt.NDArray[np.uint16]:
        """(H, W) instance id per pixel (0 = none)."""
        return read_png16(self.seq.confined(self.gt2d_path("instance")))

    @functools.cached_property
    def gt2d_cell(self) -> npt.NDArray[np.uint16] | None:
        """(H, W) world cell id per pixel (``leap_core.synth.camera.world_cells``; generated data only), or
        None when the sequence has no ``gt2d/cell`` folder (real data, or generated before it existed)."""
        path = self.gt2d_path("cell")
        return read_png16(self.seq.confined(path)) if path.parent.is_dir() else None


def _sort_frame_ids(stems: Iterable[str]) -> list[str]:
    """Numeric order when every stem is a number ("9" before "10"), else lexicographic."""
    ids = list(stems)
    if all(s.isdigit() for s in ids):
        return sorted(ids, key=lambda s: (int(s), s))
    return sorted(ids)


def _rows_of_frames(path: Path, n_lines: int, what: str, seq: KittiSequence) -> npt.NDArray[np.int64]:
    """(F,) the line of ``path`` (one of ``n_lines`` ``what``) that each scan takes: its frame number.

    Raises:
        DatasetError: naming ``path`` and the first scan whose number is past the end, or, for scans
            without numeric names, when the line count differs from the scan count.
    """
    rows = np.asarray(seq.frame_numbers, dtype=np.int64)
    if not seq.numbered:
        if n_lines != len(rows):
            raise DatasetError(
                path,
                f"{n_lines} {what} but {len(rows)} scans (scans without numeric names "
                "need exactly one line each, in name order)",
            )
        return rows
    past = np.flatnonzero(rows >= n_lines)
    if past.size:
        first = int(past[0])
        more = f" (and {past.size - 1} more scans past the end)" if past.size > 1 else ""
        raise DatasetError(
            path,
            f"{n_lines} {what} (frames 0..{n_lines - 1}) but scan {seq.frame_ids[first]}.bin is frame "
            f"{int(rows[first])}{more}",
        )
    return rows


class KittiSequence:
    """A KITTI-layout sequence folder (``.../sequences/NN``), validated on open, read lazily.

    Opening checks the structure (calib, a pose and timestamp line for every scan's frame number,
    label/image pairing) and the per-frame files: none may be a link leading outside the sequence's roots
    (:func:`sequence_roots`) or a pipe, socket or device, and every scan must be a file. Per-frame data is
    read only when a :class:`Frame` attribute is accessed (each file checked again, :meth:`confined`), so a
    sequence is never held in memory.
    """

    def __init__(self, root: str | Path, poses_path: str | Path | None = None) -> None:
        """Open ``root``; ``poses_path`` reads the poses from another ``poses.txt`` (e.g. estimated
        poses kept outside a read-only dataset) instead of ``root/poses.txt``."""
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "dataset folder does not exist")
        vel = self.root / "velodyne"
        if not vel.is_dir():
            raise DatasetError(
                vel, "missing velodyne/ folder (expected a KITTI sequence folder sequences/NN)"
            )
        self.frame_ids: list[str] = _sort_frame_ids(p.stem for p in vel.glob("*.bin"))
        """File stems of the scans present, in frame order; a frame's position here is its *index*."""
        if not self.frame_ids:
            raise DatasetError(vel, "no .bin scans found")
        self.numbered = all(s.isdigit() for s in self.frame_ids)
        """True when every scan's stem is a number: the frame number is then that number."""
        self.frame_numbers: tuple[int, ...] = (
            tuple(int(s) for s in self.frame_ids) if self.numbered else tuple(range(len(self.frame_ids)))
        )
        """Per scan, its frame number: the line it takes in ``poses.txt`` / ``times.txt``, and what every
        per-frame seed depends on (increasing; equal to the index only for a complete sequence)."""
        nums = self.frame_numbers
        same = [k for k in range(1, len(nums)) if nums[k] == nums[k - 1]]
        if same:
            a, b = self.frame_ids[same[0] - 1], self.frame_ids[same[0]]
            raise DatasetError(vel, f"scans {a}.bin and {b}.bin are both frame {self.frame_numbers[same[0]]}")
        self.calib = read_calib(self.root / "calib.txt")
        self.cameras: tuple[Camera, ...] = read_rig(self.root, self.calib)
        """The rig (:mod:`leap_core.datasets.rig`): one camera (``image_2``) in the one-camera layout."""
        self.rig_source = RIG_FILE if (self.root / RIG_FILE).is_file() else "calib.txt"
        """Where the rig was read: ``calib.txt`` (the KITTI layout) or ``cameras.yaml``."""
        self.roots = sequence_roots(self.root, self.camera_folders())
        """Where its files may lie (:func:`sequence_roots`)."""
        self._refuse_unreadable_entries()
        self.poses_path = Path(poses_path) if poses_path is not None else self.root / "poses.txt"
        self._cam_poses: npt.NDArray[np.float64] | None = None
        self._poses: npt.NDArray[np.float64] | None = None
        self.pose_lines: int | None = None
        """Lines of the poses file (≥ the highest frame number + 1), None without poses."""
        if self.poses_path.is_file():
            cam_poses = read_poses(self.poses_path)
            self.pose_lines = len(cam_poses)
            rows = _rows_of_frames(self.poses_path, len(cam_poses), "poses", self)
            self._cam_poses = cam_poses[rows]
            # Re-based on line 0 before selecting, so a frame's world coordinates are the same in a copied
            # subset as in the whole sequence.
            self._poses = lidar_poses(cam_poses, self.calib.Tr)[rows]
        self._images = self._index_images()
        self._frame_tr = self._read_frame_transforms()
        self.times: npt.NDArray[np.float64] | None = self._read_times()
        """(F,) seconds per scan (the line of its frame number), when ``times.txt`` exists."""

    def _read_frame_transforms(self) -> list[npt.NDArray[np.float64] | None]:
        """Per camera, its (F, 4, 4) LiDAR → camera transform per scan from ``tr_frames/<camera>.txt``
        (:mod:`leap_core.datasets.rig`), or None: the camera's ``Tr``."""
        out: list[npt.NDArray[np.float64] | None] = []
        cams = list(self.cameras)
        for k, cam in enumerate(cams):
            path = self.root / FRAME_TR_FOLDER / f"{cam.name}.txt"
            if not path.is_file():
                out.append(None)
                continue
            every = read_poses(self.confined(path))
            trs = every[_rows_of_frames(path, len(every), "transforms", self)]
            bad = np.flatnonzero(np.abs(np.linalg.det(trs[:, :3, :3])) < 1e-6)
            if bad.size:
                raise DatasetError(
                    path, f"the transform of frame {self.frame_ids[int(bad[0])]} has a singular rotation"
                )
            out.append(trs)
            cams[k] = Camera(
                cam.name, cam.P, cam.Tr, f"{cam.source}, Tr per frame from {FRAME_TR_FOLDER}/{path.name}"
            )
        self.cameras = tuple(cams)
        return out

    def camera_tr(self, index: int, camera: int = 0) -> npt.NDArray[np.float64]:
        """(4, 4) LiDAR → camera ``camera`` for scan ``index``: its ``tr_frames`` line, else its ``Tr``."""
        per_frame = self._frame_tr[camera]
        return self.cameras[camera].Tr if per_frame is None else per_frame[index]

    def lidar_to_image(self, index: int, camera: int = 0) -> npt.NDArray[np.float64]:
        """(3, 4) ``M = P · Tr`` of camera ``camera`` for scan ``index`` (:meth:`camera_tr`)."""
        if self._frame_tr[camera] is None:
            return self.cameras[camera].lidar_to_image
        return self.cameras[camera].P @ self.camera_tr(index, camera)

    def _read_times(self) -> npt.NDArray[np.float64] | None:
        times = self.root / "times.txt"
        if not times.is_file():
            return None
        try:
            all_times = np.loadtxt(times, dtype=np.float64, ndmin=1)
        except ValueError as exc:
            raise DatasetError(times, f"malformed timestamps ({exc})") from exc
        if all_times.ndim != 1:
            raise DatasetError(times, f"expected one timestamp per line, got {all_times.shape[1]} columns")
        if not np.isfinite(all_times).all():
            raise DatasetError(times, "timestamps have non-finite values")
        return all_times[_rows_of_frames(times, all_times.shape[0], "timestamps", self)]

    def _refuse_unreadable_entries(self) -> None:
        """Refuse a per-frame file linked outside :attr:`roots` or that no file read can take (a pipe, a
        socket, a device), and a scan that is not a file: nothing of them is ever read.

        Raises:
            DatasetError: naming the first such file and what it is.
        """
        extra = {
            name: (".png",) if name.startswith("gt2d/") else IMAGE_SUFFIXES for name in self.camera_folders()
        }
        for name, suffixes in {**FRAME_FOLDERS, **extra}.items():
            for entry, problem in folder_problems(self.root / name, suffixes, self.roots):
                # A label or image folder entry that is a directory only takes that frame's file away,
                # which the stages that need it report; a scan is needed by every stage.
                if problem in NEVER_READ or name == "velodyne":
                    raise DatasetError(self.root / name / entry, f"{problem}; {UNREADABLE_FIX}")

    def confined(self, path: Path) -> Path:
        """``path`` (a per-frame file of this sequence), once checked again as it is about to be read: a
        link to a place outside :attr:`roots`, or a pipe, socket or device, is refused (such a file may
        have appeared since the sequence was opened).

        Raises:
            DatasetError: naming the file and what it is.
        """
        problem = entry_problem(path, self.roots)
        if problem in NEVER_READ:
            raise DatasetError(path, f"{problem}; {UNREADABLE_FIX}")
        return path

    def label_problem(self, index: int) -> str | None:
        """Why scan ``index`` has no ground truth although ``labels/`` holds an entry of its name (``"a
        directory, not a file"``), or None (no such entry, or a readable file)."""
        return entry_problem(self.label_path(index), self.roots)

    @property
    def pose_source(self) -> str:
        """Where the poses come from: ``"file"``, ``"estimated"`` (a :data:`POSES_NOTE` lies beside
        the poses file) or ``"missing"``."""
        if self._poses is None:
            return "missing"
        return "estimated" if (self.poses_path.parent / POSES_NOTE).is_file() else "file"

    @property
    def has_poses(self) -> bool:
        return self._poses is not None

    @property
    def cam_poses(self) -> npt.NDArray[np.float64]:
        """(F, 4, 4) camera-frame poses as read from the poses file, one per scan (its frame's line)."""
        if self._cam_poses is None:
            raise PosesMissingError(self.poses_path, "no poses: the 3D stages need one pose per scan")
        return self._cam_poses

    @property
    def poses(self) -> npt.NDArray[np.float64]:
        """(F, 4, 4) LiDAR → world per scan (world = LiDAR frame of pose line 0, present or not)."""
        if self._poses is None:
            raise PosesMissingError(self.poses_path, "no poses: the 3D stages need one pose per scan")
        return self._poses

    def camera_folders(self) -> list[str]:
        """The per-frame folders of the cameras besides ``image_2`` and ``gt2d/<kind>`` (relative to the
        sequence): the other cameras' image folders and their 2D ground-truth folders."""
        out = [c.name for c in self.cameras if c.name != PRIMARY_FOLDER]
        out += [
            gt2d_folder(self.cameras, k, kind) for k in range(1, len(self.cameras)) for kind in GT2D_KINDS
        ]
        return out

    def _index_images(self) -> list[dict[str, Path]]:
        """Per camera, frame id → its image."""
        out = []
        for cam in self.cameras:
            img_dir = self.root / cam.name
            found = {}
            if img_dir.is_dir():
                found = {p.stem: p for p in sorted(img_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
            out.append(found)
        return out

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __iter__(self) -> Iterator[Frame]:
        return (Frame(self, i) for i in range(len(self)))

    def select(self, numbers: range | None) -> range:
        """The indices of the scans whose frame number lies in ``numbers`` (a range of frame numbers,
        step 1, e.g. ``--frames 10:20``); None = every scan.

        Raises:
            LeapError: for a step other than 1, an empty range, or one reaching before the first or past
                the last frame number (gaps inside are fine: their scans are simply absent).
        """
        n = len(self)
        if numbers is None:
            return range(n)
        if not isinstance(numbers, range):
            raise LeapError(f"frames must be a range, got {type(numbers).__name__}")
        first, last = self.frame_numbers[0], self.frame_numbers[-1]
        label = f"frames {numbers.start}:{numbers.stop}"
        if numbers.step != 1:
            raise LeapError(f"{label}: step {numbers.step} not supported (frames are a range A:B)")
        if len(numbers) == 0:
            raise LeapError(f"{label} select no frame (the sequence has frames {first}..{last})")
        if numbers.start < first or numbers.stop - 1 > last:
            raise LeapError(f"{label} out of range: the sequence has frames {first}..{last}")
        lo = bisect.bisect_left(self.frame_numbers, numbers.start)
        hi = bisect.bisect_left(self.frame_numbers, numbers.stop)
        if lo == hi:
            raise LeapError(f"{label} select no frame: no scan is numbered in that range")
        return range(lo, hi)

    def frame(self, index: int, camera: int = 0) -> Frame:
        """Scan ``index`` as camera ``camera`` sees it (:class:`Frame`)."""
        if not 0 <= index < len(self):
            raise IndexError(f"frame {index} out of range 0..{len(self) - 1}")
        return Frame(self, index, camera)

    def scan_path(self, index: int) -> Path:
        return self.root / "velodyne" / f"{self.frame_ids[index]}.bin"

    def label_path(self, index: int) -> Path:
        return self.root / "labels" / f"{self.frame_ids[index]}.label"

    def image_path(self, index: int, camera: int = 0) -> Path | None:
        """Scan ``index``'s image from camera ``camera`` (None: that camera has none for the frame)."""
        return self._images[camera].get(self.frame_ids[index])

    @property
    def has_labels(self) -> bool:
        """True when every scan has a ground-truth ``.label`` file."""
        return all(self.label_path(i).is_file() for i in range(len(self)))

    @property
    def has_images(self) -> bool:
        """Whether some camera has images."""
        return any(self._images)

    @property
    def has_gt2d(self) -> bool:
        return any(
            (self.root / gt2d_folder(self.cameras, k, "semantic")).is_dir() for k in range(len(self.cameras))
        )

    def camera_has_gt2d(self, camera: int) -> bool:
        """Whether camera ``camera`` has a 2D ground-truth folder."""
        return (self.root / gt2d_folder(self.cameras, camera, "semantic")).is_dir()


__all__ = [
    "FRAME_FOLDERS",
    "LINK_OUTSIDE",
    "NEVER_READ",
    "POSES_NOTE",
    "Calib",
    "Camera",
    "Frame",
    "KittiSequence",
    "atomic_write",
    "entry_problem",
    "folder_problems",
    "image_size",
    "lidar_poses",
    "read_calib",
    "read_image",
    "read_image_size",
    "read_label",
    "read_png16",
    "read_poses",
    "read_rig",
    "read_scan",
    "scan_point_count",
    "sequence_roots",
    "write_calib",
    "write_image",
    "write_label",
    "write_png16",
    "write_poses",
    "write_scan",
]
