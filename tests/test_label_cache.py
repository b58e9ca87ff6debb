"""The on-disk 2D result cache: keys, round trips, damaged entries (the model-level cache behaviour is
tested with real tiny models in test_grounded_sam.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from leap_core.labelers.cache import (
    LabelCache,
    PassResult,
    cache_key,
    default_cache_dir,
    image_digest,
    pass_cache_dir,
)


def make_result(h: int = 5, w: int = 7, regions: int = 2) -> PassResult:
    rng = np.random.default_rng(0)
    masks = rng.random((regions, h * w)) > 0.5
    return PassResult(
        height=h,
        width=w,
        class_names=("car", "traffic-sign"),
        boxes=rng.random((regions, 4)).astype(np.float32) * 5,
        scores=np.array([[1.5, -np.inf], [0.25, 3.0]][:regions], dtype=np.float32).reshape(regions, 2),
        bits=np.packbits(masks, axis=1),
    )


def test_image_digest_depends_on_pixels_not_on_the_array_object() -> None:
    img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    same = np.ascontiguousarray(img[:, ::-1][:, ::-1])  # a different, re-laid-out array with equal pixels
    assert image_digest(img) == image_digest(same)
    changed = img.copy()
    changed[3, 5, 2] ^= 1
    assert image_digest(changed) != image_digest(img)
    # Same bytes, other shape: another image.
    assert image_digest(img.reshape(6, 4, 3)) != image_digest(img)


def test_cache_key_ignores_key_order_but_not_values() -> None:
    a = cache_key({"image": "x", "pass": {"text": "car .", "classes": [["car", ["car"], []]]}, "t": 0.25})
    b = cache_key({"t": 0.25, "pass": {"classes": [["car", ["car"], []]], "text": "car ."}, "image": "x"})
    c = cache_key({"t": 0.2, "pass": {"classes": [["car", ["car"], []]], "text": "car ."}, "image": "x"})
    assert a == b != c
    assert len(a) == 64


def test_pass_result_round_trip_keeps_minus_inf_and_names(tmp_path: Path) -> None:
    res = make_result()
    res.save(tmp_path / "r.npz")
    back = PassResult.load(tmp_path / "r.npz")
    assert (back.height, back.width, back.class_names) == (5, 7, ("car", "traffic-sign"))
    np.testing.assert_array_equal(back.scores, res.scores)
    np.testing.assert_array_equal(back.boxes, res.boxes)
    np.testing.assert_array_equal(back.bits, res.bits)
    assert back.bits.shape == (2, 5)  # 35 pixels -> 5 bytes per mask: packed, not dense


def test_pass_result_rejects_inconsistent_shapes() -> None:
    res = make_result()
    with pytest.raises(ValueError, match="bits"):
        PassResult(5, 7, res.class_names, res.boxes, res.scores, res.bits[:, :4])
    with pytest.raises(ValueError, match="scores"):
        PassResult(5, 7, ("car",), res.boxes, res.scores, res.bits)


def test_label_cache_miss_put_hit_and_counters(tmp_path: Path) -> None:
    cache = LabelCache(tmp_path / "c")
    key = cache_key({"k": 1})
    assert cache.get(key) is None and (cache.hits, cache.misses) == (0, 1)
    assert key not in cache
    cache.put(key, make_result())
    assert key in cache
    got = cache.get(key)
    assert got is not None and got.num_regions == 2 and (cache.hits, cache.misses) == (1, 1)
    assert cache.path(key) == tmp_path / "c" / key[:2] / f"{key}.npz"
    # Atomic writes leave no temp files behind.
    assert [p.name for p in cache.path(key).parent.iterdir()] == [f"{key}.npz"]


def test_damaged_entry_is_a_miss_and_is_overwritten(tmp_path: Path) -> None:
    cache = LabelCache(tmp_path)
    key = cache_key({"k": 2})
    cache.path(key).parent.mkdir(parents=True)
    cache.path(key).write_bytes(b"PK\x03\x04 truncated")
    assert cache.get(key) is None and cache.misses == 1
    cache.put(key, make_result(regions=1))
    got = cache.get(key)
    assert got is not None and got.num_regions == 1


def test_empty_pass_result_round_trips(tmp_path: Path) -> None:
    empty = np.zeros((0, 4), np.float32)
    res = PassResult(3, 3, ("a",), empty, np.zeros((0, 1), np.float32), np.zeros((0, 2), np.uint8))
    cache = LabelCache(tmp_path)
    cache.put("ab" * 32, res)
    got = cache.get("ab" * 32)
    assert got is not None and got.num_regions == 0 and got.class_names == ("a",)


def test_default_cache_dir_lives_in_the_sequence_folder(tmp_path: Path) -> None:
    root = tmp_path / "sequences" / "00"
    assert default_cache_dir(root) == root / "leap_cache"
    assert pass_cache_dir(default_cache_dir(root)) == root / "leap_cache" / "passes"
