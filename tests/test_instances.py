"""2D instances: the overlap rule of :class:`Instances`, their place in the 2D label files, and which
instance each point of a scan falls in (:func:`leap_core.instances.point_instances`)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from leap_core.instances import CameraInstances, point_instances
from leap_core.labelers.base import Instances, SoftMasks, with_flip_votes
from leap_core.pipeline.stages import _save_soft, load_soft


def _box(h: int, w: int, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    m = np.zeros((h, w), bool)
    m[rows[0] : rows[1], cols[0] : cols[1]] = True
    return m


def test_the_higher_score_takes_the_overlap_and_ids_follow_the_scores() -> None:
    # 4 × 6 image. A (class 1, score 0.5): rows 0-2, columns 0-3. B (2, 0.9): rows 0-3, columns 2-5,
    # over A in columns 2-3. C (3, 0.3): one pixel inside B, so it keeps none and is dropped.
    # D (4, 0.5, A's score, given after A): rows 2-3, columns 0-1, under A in row 2.
    a = _box(4, 6, (0, 3), (0, 4))
    b = _box(4, 6, (0, 4), (2, 6))
    c = _box(4, 6, (1, 2), (4, 5))
    d = _box(4, 6, (2, 4), (0, 2))
    ins = Instances.from_masks(np.stack([a, b, c, d]), [1, 2, 3, 4], [0.5, 0.9, 0.3, 0.5])
    want = [[2, 2, 1, 1, 1, 1], [2, 2, 1, 1, 1, 1], [2, 2, 1, 1, 1, 1], [3, 3, 1, 1, 1, 1]]
    np.testing.assert_array_equal(ins.ids, want)
    np.testing.assert_array_equal(ins.label, [2, 1, 4])
    np.testing.assert_allclose(ins.score, [0.9, 0.5, 0.5])
    # The same instances given as an id image (A = 1, B = 2, C none, D = 3) come out numbered the same.
    img = np.where(b, 2, np.where(a, 1, np.where(d, 3, 0)))
    same = Instances.from_id_image(img, [1, 2, 4], [0.5, 0.9, 0.5])
    np.testing.assert_array_equal(same.ids, want)
    np.testing.assert_array_equal(same.label, [2, 1, 4])
    with pytest.raises(ValueError, match=r"ids 0\.\.3"):
        Instances.from_id_image(img + 1, [1, 2, 4], [0.5, 0.9, 0.5])


def _soft(instances: Instances | None) -> SoftMasks:
    m = np.stack([_box(3, 5, (0, 2), (0, 3)), _box(3, 5, (1, 3), (2, 5))])
    return SoftMasks.from_dense(m, [[0.75, 0.25], [0.1, 0.9]], [0.8, 0.6], instances=instances)


def test_2d_label_files_keep_instances_and_older_files_load_without(tmp_path: Path) -> None:
    ins = Instances.from_masks(np.stack([_box(3, 5, (1, 3), (2, 5))]), [1], [0.6])
    for path, save in ((tmp_path / "a.npz", _save_soft), (tmp_path / "b.npz", lambda p, s: s.save(p))):
        save(path, _soft(ins))
        for loaded in (load_soft(path), SoftMasks.load(path)):
            assert loaded.instances is not None
            np.testing.assert_array_equal(loaded.instances.ids, ins.ids)
            np.testing.assert_array_equal(loaded.instances.label, ins.label)
            np.testing.assert_array_equal(loaded.instances.score, ins.score)
            np.testing.assert_array_equal(loaded.bits, _soft(ins).bits)
    # A labeler that gives no instances has an empty set written (not a file from before instances).
    _save_soft(tmp_path / "none.npz", _soft(None))
    none = load_soft(tmp_path / "none.npz").instances
    assert none is not None and none.num_instances == 0 and none.ids.shape == (3, 5)
    # A file written before instances existed: the same members less the instance ones.
    old = tmp_path / "old.npz"
    with old.open("wb") as fh:
        np.savez_compressed(fh, **_soft(None).arrays())
    with zipfile.ZipFile(old) as z:
        assert sorted(z.namelist()) == ["bits.npy", "confidence.npy", "probs.npy", "size.npy"]
    assert load_soft(old).instances is None and SoftMasks.load(old).instances is None
    np.testing.assert_array_equal(load_soft(old).probs, _soft(None).probs)


def test_flip_votes_keep_the_images_own_instances() -> None:
    img = np.zeros((3, 5, 3), np.uint8)
    ins = Instances.from_masks(np.stack([_box(3, 5, (0, 3), (0, 2))]), [0], [0.7])

    def label(images: list[np.ndarray]) -> list[SoftMasks]:
        return [_soft(ins) for _ in images]

    out = with_flip_votes([img], label)[0]
    assert out.num_masks == 4 and out.instances is not None
    np.testing.assert_array_equal(out.instances.ids, ins.ids)
    joined = _soft(ins).joined(_soft(ins).mirrored())
    assert joined.instances is not None and joined.instances.num_instances == 2


def _view(idx, u, v, kept, ids, label, score) -> CameraInstances:
    return CameraInstances(
        np.asarray(idx, np.int64),
        np.asarray(u),
        np.asarray(v),
        np.asarray(kept, bool),
        Instances(np.asarray(ids, np.int32), np.asarray(label, np.int16), np.asarray(score, np.float32)),
    )


def test_each_point_takes_the_instance_it_falls_in_numbered_across_cameras() -> None:
    # Camera 0: 2 × 3 image with instance 1 (class 5, 0.6) left, instance 2 (class 6, 0.9) right.
    # Camera 1: 2 × 2 image with one instance (class 7, 0.8) on its top row.
    cam0 = _view(
        idx=[0, 1, 2, 3, 4],
        u=[0, 2, 1, 2, 0],
        v=[0, 1, 1, 0, 1],
        kept=[1, 1, 1, 0, 1],  # point 3 lies in instance 2 but depth clustering dropped it
        ids=[[1, 0, 2], [1, 0, 2]],
        label=[5, 6],
        score=[0.6, 0.9],
    )
    cam1 = _view(
        idx=[4, 1, 5, 6],
        u=[0, 1, 0, 1],
        v=[0, 0, 0, 1],
        kept=[1, 1, 1, 1],
        ids=[[1, 1], [0, 0]],
        label=[7],
        score=[0.8],
    )
    got = point_instances(8, [cam0, cam1])
    # Point 4: camera 0's instance 1 (0.6) and camera 1's (0.8): the higher score, scan id 2 + 1 = 3.
    # Point 1: camera 0's instance 2 (0.9) beats camera 1's (0.8). Point 2 falls on no instance,
    # point 6 on camera 1's empty row, point 7 in no image.
    np.testing.assert_array_equal(got.point, [1, 2, 0, 0, 3, 3, 0, 0])
    np.testing.assert_array_equal(got.label, [5, 6, 7])
    np.testing.assert_allclose(got.score, [0.6, 0.9, 0.8])
    np.testing.assert_array_equal(got.camera, [0, 0, 1])
    # Equal scores: the earlier camera keeps the point.
    tie = _view([4], [0], [0], [1], [[1, 1], [0, 0]], [7], [0.6])
    np.testing.assert_array_equal(point_instances(5, [cam0, tie]).point, [1, 2, 0, 0, 1])
    assert point_instances(3, []).point.tolist() == [0, 0, 0]


def test_point_instances_refuses_pixels_outside_the_image() -> None:
    bad = _view([0], [3], [0], [1], [[1, 0, 2], [1, 0, 2]], [5, 6], [0.6, 0.9])
    with pytest.raises(ValueError, match=r"camera 0: pixels must lie in its 3×2 image"):
        point_instances(1, [bad])
    with pytest.raises(ValueError, match="point indices"):
        point_instances(0, [_view([0], [0], [0], [1], [[1]], [5], [0.6])])
