"""Bounded memory (docs/METHOD.md, "Memory"): chunked smoothing, streamed and memory-mapped npz files,
in-place fusion accumulators, batched view counts and on-disk 3D-CN targets give exactly the results of
the whole-array computations they replace."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import scipy.sparse
from scipy.spatial import cKDTree

from leap_core import fusion
from leap_core.consistency.selection import view_counts
from leap_core.consistency.stage import TargetFile
from leap_core.errors import DatasetError
from leap_core.fusion import FusionConfig, FusionPaths, VoxelGrid, merge_sparse, voxel_keys
from leap_core.npzio import Streamed, is_mapped, load_npz, release, save_npz
from leap_core.smoothing import SmoothedGrid, SmoothingConfig, knn_smooth, knn_weights, smooth_grid


def _reference_smooth(centres: np.ndarray, probs: np.ndarray, cfg: SmoothingConfig) -> np.ndarray:
    """The unchunked smoothing: one query of all centres, one (V × V) sparse product."""
    pts = np.asarray(centres, np.float32)
    p = np.asarray(probs, np.float32)
    v = len(pts)
    k = min(cfg.k, v)
    bound = np.inf if cfg.max_distance is None else cfg.max_distance
    d, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=bound, workers=1)
    d, idx = np.asarray(d).reshape(v, k), np.asarray(idx).reshape(v, k)
    w = knn_weights(d)
    idx = np.where(idx >= v, np.arange(v)[:, None], idx)
    mat = scipy.sparse.csr_matrix((w.reshape(-1), idx.reshape(-1), np.arange(0, v * k + 1, k)), shape=(v, v))
    return np.asarray(mat @ p, np.float32)


def _lattice_grid(c: int = 5, seed: int = 0) -> VoxelGrid:
    """A regular slab of voxels (many equidistant neighbours: tie-breaks matter) plus scattered ones."""
    rng = np.random.default_rng(seed)
    ii, jj, kk = np.meshgrid(np.arange(12), np.arange(9), np.arange(3), indexing="ij")
    lattice = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], 1) * 0.2 + 0.1
    scattered = rng.uniform(-3, 5, size=(60, 3))
    keys = np.unique(voxel_keys(np.concatenate([lattice, scattered]), 0.2))
    logp = np.clip(rng.normal(0, 4, size=(len(keys), c)), -20, None)
    logp -= logp.max(axis=1, keepdims=True)
    return VoxelGrid(keys, logp.astype(np.float16), 0.2)


@pytest.mark.parametrize("max_distance", [None, 0.6])
def test_chunked_smoothing_is_bit_identical_for_every_chunk_size(max_distance: float | None) -> None:
    grid = _lattice_grid()
    cfg = SmoothingConfig(k=9, max_distance=max_distance, workers=1)
    v = grid.num_voxels
    ref = _reference_smooth(grid.centres(), grid.probs(), cfg)
    for chunk in (1, 2, 7, 64, v - 1, v, v + 5):
        got = knn_smooth(grid.centres(), grid.probs(), cfg, chunk=chunk)
        assert got.tobytes() == ref.tobytes(), chunk
        assert smooth_grid(grid, cfg, chunk=chunk).tobytes() == ref.tobytes(), chunk


def test_streamed_smoothed_grid_file_equals_the_saved_one(tmp_path) -> None:
    grid = _lattice_grid()
    probs = knn_smooth(grid.centres(), grid.probs(), SmoothingConfig()).astype(np.float16)
    whole = tmp_path / "whole.npz"
    streamed = tmp_path / "streamed.npz"
    SmoothedGrid(grid.keys, probs, 0.2).save(whole)
    blocks = (probs[s : s + 17].astype(np.float32) for s in range(0, len(probs), 17))
    SmoothedGrid.save_blocks(streamed, grid.keys, probs.shape[1], blocks, 0.2)
    with np.load(whole) as a, np.load(streamed) as b:
        assert a.files == b.files
        for name in a.files:
            assert a[name].dtype == b[name].dtype
            assert a[name].tobytes() == b[name].tobytes()
    for mmap in (False, True):
        g = SmoothedGrid.load(streamed, mmap=mmap)
        assert g.probs.tobytes() == probs.tobytes() and g.keys.tobytes() == grid.keys.tobytes()
    # Blocks that do not add up to the announced rows are refused and leave no file behind.
    with pytest.raises(ValueError, match="rows streamed"):
        SmoothedGrid.save_blocks(tmp_path / "short.npz", grid.keys, probs.shape[1], [probs[:5]], 0.2)
    assert not (tmp_path / "short.npz").exists()
    with pytest.raises(ValueError, match="more than"):
        SmoothedGrid.save_blocks(tmp_path / "long.npz", grid.keys, probs.shape[1], [probs, probs[:1]], 0.2)


def test_mmap_load_equals_normal_load_and_old_compressed_files_still_load(tmp_path) -> None:
    grid = _lattice_grid(c=3)
    path = tmp_path / "grid.npz"
    grid.save(path)
    plain = VoxelGrid.load(path)
    mapped = VoxelGrid.load(path, mmap=True)
    assert is_mapped(mapped.logp) and is_mapped(mapped.keys) and not is_mapped(plain.logp)
    assert mapped.logp.tobytes() == plain.logp.tobytes() == grid.logp.tobytes()
    assert mapped.keys.tobytes() == plain.keys.tobytes()
    assert mapped.voxel_size == plain.voxel_size
    release(mapped.logp)  # drops pages only: the data reads back the same
    assert mapped.probs().tobytes() == plain.probs().tobytes()
    with pytest.raises(ValueError, match="read-only"):
        mapped.logp[0, 0] = 1
    # A grid written compressed (as other tools or older versions may) loads with or without mmap.
    comp = tmp_path / "compressed.npz"
    np.savez_compressed(comp, keys=grid.keys, logp=grid.logp, voxel_size=np.float64(0.2))
    with zipfile.ZipFile(comp) as zf:
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in zf.infolist())
    old = VoxelGrid.load(comp, mmap=True)
    assert not is_mapped(old.logp) and old.logp.tobytes() == grid.logp.tobytes()
    sm = tmp_path / "smooth_compressed.npz"
    np.savez_compressed(sm, keys=grid.keys, probs=grid.probs(np.float16))  # older file: no voxel_size
    old_smooth = SmoothedGrid.load(sm, voxel_size=0.2, mmap=True)
    assert old_smooth.probs.tobytes() == grid.probs(np.float16).tobytes()
    # A truncated file is named in the error.
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:100])
    with pytest.raises(DatasetError, match=r"bad\.npz"):
        VoxelGrid.load(bad, mmap=True)


def test_npzio_round_trip_of_shapes_dtypes_and_missing_names(tmp_path) -> None:
    path = tmp_path / "a.npz"
    arrays = {
        "i": np.arange(10, dtype=np.int64),
        "f": np.ones((3, 4), np.float16),
        "empty": np.zeros((0, 4), np.float32),
        "scalar": np.float64(2.5),
        "fort": np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
    }
    save_npz(path, **arrays, s=Streamed((5, 2), np.dtype(np.int16), [np.ones((2, 2)), np.zeros((3, 2))]))
    with np.load(path) as z:
        assert z["s"].tolist() == [[1, 1], [1, 1], [0, 0], [0, 0], [0, 0]]
        assert z["fort"].tolist() == arrays["fort"].tolist()
    for mmap in (False, True):
        got = load_npz(path, [*arrays, "s"], mmap=mmap)
        for name, a in arrays.items():
            assert got[name].dtype == np.asarray(a).dtype and got[name].shape == np.shape(a)
            np.testing.assert_array_equal(got[name], a)
    with pytest.raises(KeyError, match="nope"):
        load_npz(path, ["nope"])


def _zero_fill_merge(ka, aa, kb, ab):
    """The merge the in-place one replaces: a zero-filled union, a's rows copied, b's rows added."""
    keys = np.union1d(ka, kb)
    out = np.zeros((len(keys), *aa.shape[1:]), aa.dtype)
    out[np.searchsorted(keys, ka)] = aa
    out[np.searchsorted(keys, kb)] += ab
    return keys, out


def test_in_place_merge_equals_a_zero_filled_merge(monkeypatch) -> None:
    monkeypatch.setattr(fusion, "_MOVE_BLOCK", 3)  # many blocks on small data
    rng = np.random.default_rng(1)
    keys = np.zeros(0, np.int64)
    acc = np.zeros((0, 4), np.float32)
    cnt = np.zeros(0, np.int64)
    ref_k, ref_a, ref_c = keys, acc, cnt
    for step in range(12):
        kb = np.unique(rng.integers(0, 80, rng.integers(1, 30)))
        ab = rng.normal(size=(len(kb), 4)).astype(np.float32)
        cb = rng.integers(1, 5, len(kb))
        if step == 5:
            kb = keys[::2].copy()  # every key already present: added in place
            ab, cb = rng.normal(size=(len(kb), 4)).astype(np.float32), rng.integers(1, 5, len(kb))
        if len(ref_k):
            _, ref_a = _zero_fill_merge(ref_k, ref_a, kb, ab)
            ref_k, ref_c = _zero_fill_merge(ref_k, ref_c, kb, cb)
        else:
            ref_k, ref_a, ref_c = kb, ab.copy(), cb.copy()
        keys, (acc, cnt) = merge_sparse(keys, [acc, cnt], kb.copy(), [ab.copy(), cb.copy()])
        assert keys.tobytes() == ref_k.tobytes()
        assert acc.tobytes() == ref_a.tobytes()
        assert cnt.tobytes() == ref_c.tobytes()


def test_in_place_finalise_equals_a_separate_float16_grid(monkeypatch) -> None:
    monkeypatch.setattr(fusion, "_MOVE_BLOCK", 4)
    rng = np.random.default_rng(2)
    acc = rng.normal(0, 30, size=(37, 5)).astype(np.float32)
    cfg = FusionConfig(logp_clip=20.0)
    ref = acc - acc.max(axis=1, keepdims=True)
    ref = np.maximum(ref, np.float32(-20.0)).astype(np.float16)
    keys = np.arange(37, dtype=np.int64)
    owned = fusion._finalise(keys, acc.copy(), cfg)  # owns its buffer: float16 written in place
    view = fusion._finalise(keys, acc.copy()[:, :], cfg)
    borrowed = fusion._finalise(keys, np.asarray(memoryview(acc.copy())), cfg)  # not owned: a copy
    for g in (owned, view, borrowed):
        assert g.logp.dtype == np.float16 and g.logp.shape == (37, 5)
        assert g.logp.tobytes() == ref.tobytes()


def test_view_counts_do_not_depend_on_the_batch() -> None:
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 50, rng.integers(0, 40)) for _ in range(25)]
    per_frame = np.concatenate([np.unique(f) for f in frames])
    ref_k, ref_c = np.unique(per_frame, return_counts=True)
    for batch in (1, 5, 64, 10**6):
        k, c = view_counts(iter(frames), batch=batch)
        assert k.tobytes() == ref_k.astype(np.int64).tobytes()
        assert c.tobytes() == ref_c.astype(np.int64).tobytes()


def test_target_file_round_trip(tmp_path) -> None:
    targets = [np.array([1, -1, 3], np.int16), np.zeros(0, np.int16), np.array([-1, 2], np.int16)]
    store = TargetFile.write(tmp_path / "t.i16", iter(targets))
    assert len(store) == 3
    for j, t in enumerate(targets):
        got = store.read(j)
        assert got.dtype == np.int16 and got.tolist() == t.tolist()
    assert [t.tolist() for t in store] == [t.tolist() for t in targets]
    store.close()
    assert not (tmp_path / "t.i16").exists()


@pytest.mark.parametrize("weight", [1.0, 0.5, 1 / 3, 2.0])
def test_fuse_unique_equals_fuse_dense(weight: float) -> None:
    rng = np.random.default_rng(4)
    c = 4
    prior = fusion.fuse_dense(None, rng.integers(0, 40, 60), np.log(rng.dirichlet(np.ones(c), 60)), c)
    # Many voxels, so that a float32 difference of an ulp or two crosses a float16 rounding boundary
    # somewhere and shows in the stored grid.
    keys = np.unique(rng.integers(20, 40_000, 20_000)).astype(np.int64)
    logp = np.log(rng.dirichlet(np.ones(c) * 0.3, len(keys))).astype(np.float32)
    logp[0] = [-np.inf, 0.0, -0.0, -50.0]  # below the floor, zero of both signs
    logp[1] = np.float32(np.log(1e-3))  # exactly at the floor's float32 value
    for grid in (None, prior):
        ref = fusion.fuse_dense(grid, keys, logp.copy(), c, weight=weight)
        got = fusion.fuse_unique(grid, keys, logp.copy(), c, weight=weight)
        assert got.keys.tobytes() == ref.keys.tobytes()
        assert got.logp.tobytes() == ref.logp.tobytes()
    if weight == 1.0:  # the default weight is 1 in both
        ref = fusion.fuse_dense(None, keys, logp.copy(), c)
        assert fusion.fuse_unique(None, keys, logp.copy(), c).logp.tobytes() == ref.logp.tobytes()
    with pytest.raises(ValueError, match="sorted unique"):
        fusion.fuse_unique(None, keys[::-1].copy(), logp.copy(), c)
    with pytest.raises(ValueError, match="sorted unique"):  # two keys are checked too
        fusion.fuse_unique(None, keys[1::-1].copy(), logp[:2].copy(), c)
    with pytest.raises(ValueError, match="float32 expected"):
        fusion.fuse_unique(None, keys, logp.astype(np.float64), c)
    with pytest.raises(ValueError, match="float32 expected"):
        fusion.fuse_unique(None, keys[:, None], logp.copy(), c)


def _observations(seed: int, frames: int = 60, c: int = 5) -> list[fusion.Observations]:
    """Frames of points in a 3 m cube: ≈ 3 000 voxels, each observed by many frames, so summing in another
    order or another chunking changes float32 sums by an ulp here and there, which shows in some float16
    values of the stored grid."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(frames):
        n = int(rng.integers(0, 1500)) if i else 0
        keys = voxel_keys(rng.uniform(0, 3, size=(n, 3)) + i * 0.01, 0.2)
        k = int(rng.integers(1, 6))
        table = fusion.log_table(rng.dirichlet(np.ones(c), size=k), 1e-3)
        out.append(fusion.Observations(keys, rng.integers(0, k, n).astype(np.int32), table))
    return out


@pytest.mark.parametrize("pack_max_bits", [0, 62])
def test_fuse_to_file_writes_the_grid_fuse_and_apply_overrides_give(tmp_path, pack_max_bits: int) -> None:
    obs = _observations(5)
    c = 5
    paths = FusionPaths(pack_max_bits=pack_max_bits)
    rng = np.random.default_rng(6)
    for chunk_points in (5000, 10**7):
        cfg = FusionConfig(chunk_points=chunk_points)
        fused = fusion.fuse(iter(obs), c, cfg, paths=paths)
        # Corrections on fused voxels and on voxels no observation reached, a key corrected twice.
        ok = np.concatenate([fused.keys[::9], fused.keys[:1], voxel_keys(np.array([[50.0, 50, 50]]), 0.2)])
        oc = rng.integers(0, c, len(ok))
        for overrides in (None, (ok, oc, 50.0)):
            ref = fused if overrides is None else fusion.apply_overrides(fused, *overrides, cfg)
            for block in (997, 10**6):
                out = tmp_path / f"g{chunk_points}-{block}.npz"
                n = fusion.fuse_to_file(
                    iter(obs),
                    c,
                    out,
                    tmp_path / "spill",
                    cfg,
                    overrides=overrides,
                    paths=paths,
                    block_voxels=block,
                )
                got = VoxelGrid.load(out)
                assert n == ref.num_voxels
                assert got.keys.tobytes() == ref.keys.tobytes(), (chunk_points, block)
                assert got.logp.tobytes() == ref.logp.tobytes(), (chunk_points, block)
                assert got.voxel_size == ref.voxel_size
    assert list((tmp_path / "spill").iterdir()) == []  # chunk files are deleted
    empty = tmp_path / "empty.npz"
    assert fusion.fuse_to_file(iter([]), c, empty, tmp_path / "spill") == 0
    assert VoxelGrid.load(empty).logp.shape == (0, c)


def test_fuse_to_file_one_voxel_blocks_and_an_override_block_no_observation_reached(tmp_path) -> None:
    """Blocks of one voxel: the last ones hold only corrected voxels that no chunk has (no chunk file is
    read for them); the spill folder is made with its parents."""
    obs = _observations(8, frames=6)
    c = 5
    cfg = FusionConfig(chunk_points=1200)
    fused = fusion.fuse(iter(obs), c, cfg)
    far = voxel_keys(np.array([[40.0, 40, 40], [41.0, 40, 40]]), 0.2)  # above every observed key
    overrides = (np.concatenate([fused.keys[:3], far]), np.array([0, 1, 2, 3, 4]), 50.0)
    ref = fusion.apply_overrides(fused, *overrides, cfg)
    out = tmp_path / "g.npz"
    spill = tmp_path / "not" / "yet" / "spill"
    assert fusion.fuse_to_file(iter(obs), c, out, spill, cfg, overrides=overrides, block_voxels=1) == len(ref)
    got = VoxelGrid.load(out)
    assert got.keys.tobytes() == ref.keys.tobytes() and got.logp.tobytes() == ref.logp.tobytes()
    assert list(spill.iterdir()) == []
    with pytest.raises(ValueError, match="block_voxels"):
        fusion.fuse_to_file(iter(obs), c, out, spill, cfg, block_voxels=0)


@pytest.mark.parametrize("failing", ["chunk1.keys.npy", "chunk1.sums.npy"])
def test_fuse_to_file_deletes_a_half_written_chunk_pair_when_a_write_fails(
    tmp_path, monkeypatch, failing: str
) -> None:
    """A full disk while the second chunk's keys or sums are written: the error goes up, and every chunk
    file already written is deleted (the file that failed was never made); no grid file is left."""
    obs = _observations(8, frames=6)
    real_save = np.save

    def save(file, arr, *args, **kwargs):
        if str(file).endswith(failing):
            raise OSError(28, "No space left on device")
        return real_save(file, arr, *args, **kwargs)

    monkeypatch.setattr(fusion.np, "save", save)
    spill = tmp_path / "spill"
    with pytest.raises(OSError, match="No space left"):
        fusion.fuse_to_file(iter(obs), 5, tmp_path / "g.npz", spill, FusionConfig(chunk_points=1200))
    assert list(spill.iterdir()) == []
    assert not (tmp_path / "g.npz").exists()


def test_fuse_to_file_reads_its_chunk_files_memory_mapped(tmp_path) -> None:
    """Step 2 maps the chunk files instead of reading them: traced allocations stay far below the chunks'
    summed size (read whole, every chunk file would be in memory at once)."""
    import tracemalloc

    obs = _observations(9, frames=120)
    c = 5
    cfg = FusionConfig(chunk_points=600)
    spilled = sum(len(np.unique(o.keys)) for o in obs) * (8 + 4 * c)  # the chunk files hold at most this
    tracemalloc.start()
    try:
        fusion.fuse_to_file(iter(obs), c, tmp_path / "g.npz", tmp_path / "spill", cfg, block_voxels=256)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    print(f"peak {peak / 1e6:.2f} MB, chunk files about {spilled / 1e6:.2f} MB")
    assert peak < spilled / 3
