"""Reading a finished run for review: the final voxel grid, per-scan labels, camera geometry.

The run's files of the sequence come from :class:`leap_core.run_layout.SequenceLayout`: the final grid (a
:class:`~leap_core.smoothing.SmoothedGrid`) is the map, else the fused ``VoxelGrid``;
``points/<frame_id>.npz`` holds per-point ``label`` (final), ``conf`` and ``point_label`` (camera projection
only). Arrays are read once and kept; per-class probability columns are extracted on demand and cached.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.viewer import view_logic as vl
from app.viewer.region_logic import disagreement_rate
from leap_core.config import config_from_dict
from leap_core.consistency.selection import lookup_counts, view_counts
from leap_core.errors import DatasetError, LeapError
from leap_core.fusion import VoxelGrid, rows_in_sorted, voxel_keys, world_points
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.projection import project_points
from leap_core.run_layout import SequenceLayout
from leap_core.smoothing import SmoothedGrid


def _read_npz(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    try:
        with np.load(path) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise DatasetError(path, f"missing array(s) {', '.join(missing)} (has {', '.join(z.files)})")
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as exc:
        raise DatasetError(path, f"unreadable run output ({exc})") from exc


def final_grid_path(run_dir: str | Path, pipeline: Mapping[str, Any] | None = None) -> Path:
    """The final grid of the run's sequence folder ``run_dir`` (:meth:`SequenceLayout.final_grid`) under
    the run's pipeline parameters, or, without usable parameters, the one found in the folder
    (:meth:`SequenceLayout.final_grid_on_disk`)."""
    layout = SequenceLayout(Path(run_dir))
    if pipeline:
        try:
            return layout.final_grid(config_from_dict(pipeline).consistency)
        except LeapError:
            pass  # parameters of an older version: fall back to what the folder holds
    return layout.final_grid_on_disk()


class ReviewGrid:
    """The voxel map shown by the viewer: a :class:`SmoothedGrid` with its centres and labels at hand.

    Attributes:
        grid: the smoothed grid (keys, probs, voxel_size).
        keys: (V,) int64 sorted voxel keys (:func:`leap_core.fusion.voxel_keys` packing).
        centres: (V, 3) float32 voxel centres in world metres.
        probs: (V, C) float16 normalised posteriors.
        label: (V,) int16 argmax class.
        conf: (V,) float32 probability of the argmax class.
        voxel_size: voxel edge in metres.
        num_voxels, num_classes: V, C.
        source: file the posteriors came from.
    """

    def __init__(self, grid: SmoothedGrid, source: str) -> None:
        labels = grid.voxel_labels()
        self.grid = grid
        self.keys = grid.keys
        self.centres = grid.centres()
        self.probs = grid.probs
        self.label = labels.label
        self.conf = labels.conf
        self.voxel_size = float(grid.voxel_size)
        self.num_voxels = grid.num_voxels
        self.num_classes = grid.num_classes
        self.source = source
        self._columns: dict[int, npt.NDArray[np.float32]] = {}
        self._lock = threading.Lock()

    def class_prob(self, c: int) -> npt.NDArray[np.float32]:
        """(V,) float32 posterior of class ``c`` (cached: switching back to a class costs nothing)."""
        if not 0 <= c < self.num_classes:
            raise IndexError(f"class index {c} out of range 0..{self.num_classes - 1}")
        with self._lock:
            col = self._columns.get(c)
            if col is None:
                col = self.probs[:, c].astype(np.float32)
                self._columns[c] = col
            return col

    def rows_of(self, keys: npt.ArrayLike) -> npt.NDArray[np.int64]:
        """(N,) row of each key in this grid, -1 where absent."""
        return rows_in_sorted(self.keys, np.asarray(keys, dtype=np.int64).reshape(-1))

    @classmethod
    def from_arrays(
        cls, keys: npt.ArrayLike, probs: npt.ArrayLike, voxel_size: float, source: str = "<arrays>"
    ) -> ReviewGrid:
        """Build from sorted keys and (V, C) probabilities (stored as float16)."""
        try:
            p16 = np.asarray(probs).astype(np.float16, copy=False)
            grid = SmoothedGrid(np.asarray(keys, dtype=np.int64), p16, float(voxel_size))
        except ValueError as exc:
            raise DatasetError(source, str(exc)) from exc
        return cls(grid, source)

    @classmethod
    def load(cls, run_dir: str | Path, pipeline: Mapping[str, Any] | None = None) -> ReviewGrid:
        """The final grid of a run (see :func:`final_grid_path`), else the fused grid (softmax of logp).

        Args:
            run_dir: the run's folder of the sequence shown.
            pipeline: the run's pipeline parameters (to know whether 3D-CN made the final grid).

        Raises:
            DatasetError: the run has no grid, or a grid file is malformed.
        """
        layout = SequenceLayout(Path(run_dir))
        final_path = final_grid_path(layout.folder, pipeline)
        fused = VoxelGrid.load(layout.grid) if layout.grid.is_file() else None
        if final_path.is_file():
            vs = None if fused is None else fused.voxel_size
            return cls(SmoothedGrid.load(final_path, voxel_size=vs), str(final_path))
        if fused is None:
            missing = f"{final_path.name} or {layout.grid.name}"
            raise DatasetError(layout.folder, f"run has no voxel grid ({missing}); has it finished?")
        return cls(SmoothedGrid.from_voxel_grid(fused), str(layout.grid))


@dataclass(frozen=True)
class ScanView:
    """One scan prepared for display.

    Attributes:
        frame_id: file stem.
        points: (N, 3) float32 world positions.
        label: (N,) int16 final class per point (-1 unlabeled).
        cam_position: (3,) camera centre in world.
        cam_wxyz: (4,) camera orientation (OpenCV convention, +z forward).
        fov_y: vertical field of view in radians.
        aspect: image width / height.
        overlay: (H, W, 3) uint8 camera image with the projected labels drawn over it, or None.
        ego_pose: (4, 4) sensor-to-world pose of the scan (where the camera follows the ego vehicle to).
        camera: the image folder of the camera whose image and pose these are (a rig has several).
        instance: (N,) uint32 track id per point (0: no object), or None when the run has no objects.
        moving: (N,) bool whether the point's track moves, or None when the run has no objects.
    """

    frame_id: str
    points: npt.NDArray[np.float32]
    label: npt.NDArray[np.int16]
    cam_position: npt.NDArray[np.float64]
    cam_wxyz: npt.NDArray[np.float64]
    fov_y: float
    aspect: float
    overlay: npt.NDArray[np.uint8] | None
    ego_pose: npt.NDArray[np.float64] | None = None
    camera: str = "image_2"
    instance: npt.NDArray[np.uint32] | None = None
    moving: npt.NDArray[np.bool_] | None = None


def matrix_to_wxyz(rot: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Unit quaternion (w, x, y, z) of a 3×3 rotation (Shepperd's method: pivot on the largest term)."""
    m = np.asarray(rot, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    out = np.asarray(q, dtype=np.float64)
    unit: npt.NDArray[np.float64] = out / np.linalg.norm(out)
    return unit


class RunOutputs:
    """Lazy access to a run's per-scan outputs and the dataset it labelled."""

    def __init__(self, run_dir: str | Path, dataset: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.layout = SequenceLayout(self.run_dir)
        self.seq = self.layout.open_sequence(dataset)
        points_dir = self.layout.points_dir
        done = {p.stem for p in points_dir.glob("*.npz")} if points_dir.is_dir() else set()
        self.frame_indices: list[int] = [i for i, f in enumerate(self.seq.frame_ids) if f in done]
        """Indices of the frames that have per-point labels in this run, in sequence order."""
        self._disagreement: tuple[ReviewGrid, np.ndarray, np.ndarray] | None = None
        self._views: tuple[ReviewGrid, npt.NDArray[np.int64]] | None = None
        self._tracks: SequenceTracks | None = None
        self._tracks_read = False
        self._lock = threading.Lock()

    def tracks(self) -> SequenceTracks | None:
        """The run's objects (``tracks.npz``, read once), or None when it tracked none."""
        with self._lock:
            if not self._tracks_read:
                path = self.layout.tracks
                self._tracks = SequenceTracks.load(path) if path.is_file() else None
                self._tracks_read = True
            return self._tracks

    def scan_objects(
        self, frame_id: str, n: int
    ) -> tuple[npt.NDArray[np.uint32] | None, npt.NDArray[np.bool_] | None]:
        """``(instance (n,), moving (n,))`` of one scan's points, or ``(None, None)`` without objects."""
        tracks = self.tracks()
        if tracks is None:
            return None, None
        obj = tracks.scan(frame_id)
        if obj.rows.size and int(obj.rows.max()) >= n:
            raise DatasetError(self.layout.tracks, f"scan {frame_id} has point rows past its {n} points")
        instance = np.zeros(n, np.uint32)
        moving = np.zeros(n, bool)
        instance[obj.rows] = obj.track.astype(np.uint32)
        moving[obj.rows] = tracks.table.moving[obj.track.astype(np.int64) - 1]
        return instance, moving

    def point_arrays(self, index: int) -> dict[str, np.ndarray]:
        return _read_npz(self.layout.points(self.seq.frame_ids[index]), ("label",))

    def world_points(self, index: int) -> npt.NDArray[np.float32]:
        """(N, 3) float32 world positions of scan ``index`` (:func:`leap_core.fusion.world_points`)."""
        frame = self.seq.frame(index)
        return world_points(frame.points, frame.pose).astype(np.float32)

    def camera_names(self) -> list[str]:
        """The image folders of the sequence's cameras, primary first (one for a one-camera sequence)."""
        return [c.name for c in self.seq.cameras]

    def scan_view(
        self, index: int, palette: npt.ArrayLike, *, overlay_radius: int = 1, camera: int = 0
    ) -> ScanView:
        """Points with final labels, camera pose and the labelled camera image of frame ``index``, as the
        rig's camera ``camera`` sees it (0: the primary one; a camera the sequence lacks: the primary)."""
        camera = camera if 0 <= camera < len(self.seq.cameras) else 0
        frame = self.seq.frame(index, camera)
        arrays = self.point_arrays(index)
        label = arrays["label"].astype(np.int16)
        if label.shape[0] != frame.points.shape[0]:
            raise DatasetError(
                self.layout.points(frame.frame_id),
                f"{label.shape[0]} labels but the scan has {frame.points.shape[0]} points",
            )
        calib = frame.calib
        cam_to_world = frame.pose @ np.linalg.inv(calib.Tr)
        fy = float(calib.P2[1, 1])
        overlay = None
        height, width = 375, 1242
        if frame.has_image:
            image = frame.image
            height, width = image.shape[:2]
            proj = project_points(frame.points, calib.lidar_to_image, height, width)
            uv = np.stack([proj.u, proj.v], axis=1)
            overlay = vl.draw_label_overlay(
                image, uv, label[proj.idx], palette, radius=overlay_radius, depth=proj.depth
            )
        instance, moving = self.scan_objects(frame.frame_id, label.shape[0])
        return ScanView(
            frame_id=frame.frame_id,
            points=self.world_points(index),
            label=label,
            cam_position=cam_to_world[:3, 3].copy(),
            cam_wxyz=matrix_to_wxyz(cam_to_world[:3, :3]),
            fov_y=float(2.0 * np.arctan(height / (2.0 * fy))),
            aspect=float(width / height),
            overlay=overlay,
            ego_pose=np.asarray(frame.pose, dtype=np.float64).copy(),
            camera=frame.rig_camera.name,
            instance=instance,
            moving=moving,
        )

    def disagreement(self, grid: ReviewGrid) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int64]]:
        """Per-voxel share of camera-labelled points whose final label differs (see
        :func:`app.viewer.region_logic.disagreement_rate`), over every labelled scan of the run.

        Reads every scan once; the result is kept for this grid. Only the points the camera labelled
        (``point_label ≥ 0``, a tenth of a scan or less: the camera sees a narrow wedge) can disagree, so
        only they are moved to the world and looked up in the grid; transforming and searching every point
        made the demo's disagreement queue take 5.7 s.
        """
        cached = self._disagreement
        if cached is not None and cached[0] is grid:
            return cached[1], cached[2]

        rows_all, cam_all, fin_all = [], [], []
        for i in self.frame_indices:
            arrays = self.point_arrays(i)
            if "point_label" not in arrays:
                continue
            cam = arrays["point_label"]
            seen = np.flatnonzero(cam >= 0)
            frame = self.seq.frame(i)
            if cam.shape[0] != frame.points.shape[0]:
                raise DatasetError(
                    self.layout.points(frame.frame_id),
                    f"{cam.shape[0]} labels but the scan has {frame.points.shape[0]} points",
                )
            keys = voxel_keys(world_points(frame.points[seen], frame.pose), grid.voxel_size)
            rows_all.append(grid.rows_of(keys))
            cam_all.append(cam[seen].astype(np.int16))
            fin_all.append(arrays["label"][seen].astype(np.int16))
        if not rows_all:
            rate, observed = np.zeros(grid.num_voxels, np.float32), np.zeros(grid.num_voxels, np.int64)
        else:
            rate, observed = disagreement_rate(
                np.concatenate(rows_all), np.concatenate(cam_all), np.concatenate(fin_all), grid.num_voxels
            )
        self._disagreement = (grid, rate, observed)
        return rate, observed

    def region_observers(
        self, index: int, keys: npt.NDArray[np.int64], voxel_size: float, camera: int | None = 0
    ) -> tuple[int, int, npt.NDArray[np.float64]]:
        """How scan ``index`` saw a region: ``(points in the region's voxels, of them in its image, their
        pixel coordinates (n, 2))``.

        Args:
            keys: sorted voxel keys of the region.
            voxel_size: edge of those keys.
            camera: the rig camera whose image counts; None = the camera that saw the most of the region
                (:meth:`best_camera`).
        """
        if camera is None:
            camera = self.best_camera(index, keys, voxel_size)
        camera = camera if 0 <= camera < len(self.seq.cameras) else 0
        frame = self.seq.frame(index, camera)
        inside = np.flatnonzero(
            rows_in_sorted(keys, voxel_keys(world_points(frame.points, frame.pose), voxel_size)) >= 0
        )
        if inside.size == 0 or not frame.has_image:
            return int(inside.size), 0, np.zeros((0, 2))
        h, w = frame.image.shape[:2]
        proj = project_points(frame.points[inside], frame.calib.lidar_to_image, h, w)
        uv = np.stack([proj.u, proj.v], axis=1).astype(np.float64)
        return int(inside.size), int(uv.shape[0]), uv

    def best_camera(self, index: int, keys: npt.NDArray[np.int64], voxel_size: float) -> int:
        """The rig camera in whose image scan ``index`` shows the most points of the region ``keys``
        (ties: the first; 0 for a one-camera sequence)."""
        if len(self.seq.cameras) == 1:
            return 0
        seen = [self.region_observers(index, keys, voxel_size, k)[1] for k in range(len(self.seq.cameras))]
        return int(np.argmax(seen))

    def view_counts(self, grid: ReviewGrid) -> npt.NDArray[np.int64]:
        """(V,) number of this run's scans that observed each voxel of ``grid``.

        A scan observed a voxel when at least one of its camera-painted points (``point_label ≥ 0`` in
        ``points/<frame_id>.npz``, the points the fusion took evidence from) falls in it: the count the
        3D-CN ranks its training voxels by (:func:`leap_core.consistency.selection.view_counts`), which the
        pipeline keeps in memory only, so it is counted again here from the run's per-frame files. Voxels
        only smoothing or the 3D-CN labelled count 0. Reads every scan once; the result is kept for this grid.
        """
        with self._lock:
            cached = self._views
            if cached is not None and cached[0] is grid:
                return cached[1]
            frame_keys = []
            for i in self.frame_indices:
                arrays = self.point_arrays(i)
                if "point_label" not in arrays:
                    continue
                painted = arrays["point_label"] >= 0
                frame_keys.append(voxel_keys(self.world_points(i)[painted], grid.voxel_size))
            keys, counts = view_counts(frame_keys)
            out = lookup_counts(grid.keys, keys, counts)
            self._views = (grid, out)
            return out


__all__ = ["ReviewGrid", "RunOutputs", "ScanView", "final_grid_path", "matrix_to_wxyz"]
