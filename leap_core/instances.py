"""Which 2D instance each point of a scan falls in: the link from the labelers' per-image instances
(:class:`~leap_core.labelers.base.Instances`) to the per-scan 3D segments of docs/METHOD.md B.6.

Pure functions on arrays; reading the 2D label files and projecting the scan are the caller's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from leap_core.labelers.base import Instances


@dataclass(frozen=True)
class CameraInstances:
    """One camera's view of one scan.

    Attributes:
        idx: (P,) int64 indices into the scan of the points inside the image (``Projected.idx``).
        u: (P,) integer pixel column of each, in ``0..W-1``.
        v: (P,) integer pixel row of each, in ``0..H-1``.
        kept: (P,) bool: the point survived depth clustering (a point behind the object that a mask spills
            onto is not kept, and so takes no instance).
        instances: the camera image's instances ((H, W) ids).
    """

    idx: npt.NDArray[np.int64]
    u: npt.NDArray[np.integer]
    v: npt.NDArray[np.integer]
    kept: npt.NDArray[np.bool_]
    instances: Instances


@dataclass(frozen=True)
class ScanInstances:
    """The 2D instances of one scan's cameras as one numbering, and the instance of each point.

    Attributes:
        point: (N,) int32 instance per point of the scan; 0 = none, k = instance k (1..K).
        label: (K,) int16 class index of instance k at row k-1.
        score: (K,) float32 score of instance k at row k-1.
        camera: (K,) int32 the camera (position in the views given) whose image holds instance k.
    """

    point: npt.NDArray[np.int32]
    label: npt.NDArray[np.int16]
    score: npt.NDArray[np.float32]
    camera: npt.NDArray[np.int32]


def point_instances(n_points: int, views: Sequence[CameraInstances]) -> ScanInstances:
    """The instance each of a scan's ``n_points`` points falls in, over its cameras ``views``.

    Camera c's instance j becomes the scan's instance ``o_c + j`` with ``o_c = Σ_{c' < c} N_c'`` (N_c:
    camera c's instance count), so ids are unique across the cameras of the frame; every camera instance
    keeps its id, whether a point falls in it or not. A kept point at pixel (u, v) of camera c falls in
    camera instance ``ids_c[v, u]`` (0 = none). A point that instances of several cameras hold (where the
    images overlap) takes the highest-scoring one (ties: the earlier camera); a point no kept projection
    puts in an instance gets 0.

    Raises:
        ValueError: a view's arrays differ in length, or a pixel or point index is out of range.
    """
    point = np.zeros(n_points, np.int32)
    best = np.full(n_points, -np.inf, np.float32)
    offset = 0
    for c, view in enumerate(views):
        ins = view.instances
        h, w = ins.ids.shape
        n = view.idx.shape[0]
        if view.u.shape != (n,) or view.v.shape != (n,) or view.kept.shape != (n,):
            raise ValueError(
                f"camera {c}: idx {view.idx.shape}, u {view.u.shape}, v {view.v.shape} and kept "
                f"{view.kept.shape} must have one entry per projected point"
            )
        idx, u, v = view.idx[view.kept], view.u[view.kept], view.v[view.kept]
        if idx.size and (idx.min() < 0 or idx.max() >= n_points):
            raise ValueError(f"camera {c}: point indices must be in 0..{n_points - 1}")
        if u.size and (u.min() < 0 or u.max() >= w or v.min() < 0 or v.max() >= h):
            raise ValueError(f"camera {c}: pixels must lie in its {w}×{h} image")
        j = ins.ids[v, u]
        hit = j > 0
        idx, j = idx[hit], j[hit]
        s = ins.score[j - 1]
        better = s > best[idx]
        point[idx[better]] = offset + j[better]
        best[idx[better]] = s[better]
        offset += ins.num_instances
    if not views:
        return ScanInstances(point, np.zeros(0, np.int16), np.zeros(0, np.float32), np.zeros(0, np.int32))
    return ScanInstances(
        point,
        np.concatenate([v.instances.label for v in views]).astype(np.int16),
        np.concatenate([v.instances.score for v in views]).astype(np.float32),
        np.repeat(np.arange(len(views), dtype=np.int32), [v.instances.num_instances for v in views]),
    )


__all__ = ["CameraInstances", "ScanInstances", "point_instances"]
