"""The compiled kernels (leap_core/fusion_kernels.py, numba) give the numpy path's bytes: the fused grid
(several chunks, a prior grid, a weight, the clip, both voxel numberings, the streamed file with
corrections), the smoothed grid, each kernel against the numpy operation it replaces, and fusion without
numba."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from leap_core import fusion
from leap_core.fusion import (
    FusionConfig,
    FusionPaths,
    Observations,
    fuse,
    fuse_to_file,
    log_table,
    voxel_keys,
)
from leap_core.smoothing import SmoothingConfig, knn_smooth, smooth_grid

kernels = pytest.importorskip("leap_core.fusion_kernels", exc_type=ImportError)

ROOT = Path(__file__).resolve().parents[1]
NUMPY = FusionPaths(compiled=False)
COMPILED = FusionPaths(compiled_min_points=0)


def _batches(seed: int, images: int = 6, points: int = 400, c: int = 5) -> list[Observations]:
    """Random voxels in a small box (so voxels repeat within and across images and chunks), random rows
    of tables that include near-certain rows (their sums fall below -logp_clip: the clip acts)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(images):
        coords = rng.integers(-3, 3, (points, 3))
        table = np.vstack([rng.dirichlet(np.full(c, 0.4), 9), np.eye(c)[:2] * 0.999 + 0.0002])
        rows = rng.integers(0, len(table), points).astype(np.int32)
        out.append(Observations(voxel_keys((coords + 0.5) * 0.2, 0.2), rows, log_table(table, 1e-3)))
    return out


def _same(a: fusion.VoxelGrid, b: fusion.VoxelGrid) -> None:
    assert a.keys.tobytes() == b.keys.tobytes()
    assert a.logp.dtype == b.logp.dtype == np.float16
    assert a.logp.tobytes() == b.logp.tobytes()


@pytest.mark.parametrize("pack_max_bits", [62, 0])
def test_fuse_gives_the_numpy_paths_bytes(pack_max_bits: int) -> None:
    """Chunks of ~1,000 points (so each fuse merges several), a prior grid and weights other than 1; both
    voxel numberings (packed keys, np.unique)."""
    c = 5
    cfg = FusionConfig(chunk_points=1000)
    batches = _batches(1, c=c)
    prior = fuse(_batches(2, images=2, c=c), c, cfg, paths=NUMPY)
    for grid, weight in ((None, 1.0), (prior, 0.37), (prior, 3.0)):
        ref = fuse(
            batches, c, cfg, grid, weight, paths=FusionPaths(pack_max_bits=pack_max_bits, compiled=False)
        )
        got = fuse(
            batches,
            c,
            cfg,
            grid,
            weight,
            paths=FusionPaths(pack_max_bits=pack_max_bits, compiled_min_points=0),
        )
        _same(got, ref)
        assert (ref.logp == np.float16(-cfg.logp_clip)).any()  # the clip acted


def test_fuse_to_file_with_corrections_gives_the_numpy_paths_bytes(tmp_path: Path) -> None:
    c = 5
    cfg = FusionConfig(chunk_points=700)
    batches = _batches(3, c=c)
    keys = np.concatenate([batches[0].keys[:30], voxel_keys([[50.0, 50.0, 50.0]], 0.2)])
    overrides = (keys, np.arange(len(keys)) % c, 50.0)
    for name, paths in (("numpy", NUMPY), ("compiled", COMPILED)):
        fuse_to_file(batches, c, tmp_path / f"{name}.npz", tmp_path / "spill", cfg, overrides=overrides,
                     paths=paths, block_voxels=97)  # fmt: skip
    assert (tmp_path / "numpy.npz").read_bytes() == (tmp_path / "compiled.npz").read_bytes()


@pytest.mark.parametrize("max_distance", [0.3, None])
def test_smoothing_gives_the_numpy_paths_bytes(max_distance: float | None) -> None:
    """Several chunks in two threads, distributions given whole and by rows (a fused grid)."""
    c = 5
    grid = fuse(_batches(5, images=8, c=c), c)
    cfg = SmoothingConfig(max_distance=max_distance)
    ref = knn_smooth(grid.centres(), grid.probs(), cfg, chunk=50, compiled=False)
    assert knn_smooth(grid.centres(), grid.probs(), cfg, chunk=50, compiled=True).tobytes() == ref.tobytes()
    assert smooth_grid(grid, cfg, chunk=70).tobytes() == ref.tobytes()  # the kernels are loaded: compiled


def test_finalise_takes_numpys_row_maxima() -> None:
    """Rows whose maximum is a zero of either sign beside a zero of the other (numpy's vector maximum picks
    one by position, which sets the sign of the shifted zeros), NaN, values below the clip; more rows than
    one SIMD vector so both the vector loop and its tail are reached."""
    rng = np.random.default_rng(7)
    acc = rng.uniform(-30, 0, (67, 4)).astype(np.float32)
    acc[::3, 1] = 0.0
    acc[::3, 2] = -0.0
    acc[1::5, 0] = -0.0
    acc[1::5, 3] = 0.0
    acc[4, 2] = np.nan
    cfg = FusionConfig()
    keys = np.arange(len(acc), dtype=np.int64)
    ref = fusion._finalise(keys, acc.copy(), cfg, compiled=False)
    got = fusion._finalise(keys, acc.copy(), cfg, compiled=True)
    assert got.logp.tobytes() == ref.logp.tobytes()
    sliced = fusion._finalise(keys[:40], acc[:40], cfg, compiled=True)  # a view: float16 into a new array
    assert sliced.logp.tobytes() == ref.logp[:40].tobytes()


def test_half_bits_are_numpys_float16_over_every_exponent() -> None:
    """Every sign and exponent with significands at and around each rounding boundary (the 13 bits a normal
    half drops, the ties to even) and random ones: subnormals, overflow, inf and NaN payloads included."""
    rng = np.random.default_rng(0)
    sig = np.concatenate(
        [
            [0, 1, 2, 0xFFF, 0x1000, 0x1001, 0x1FFF, 0x2000, 0x2FFF, 0x3000, 0x3001, 0x400000, 0x7FE000],
            [0x7FEFFF, 0x7FF000, 0x7FF001, 0x7FFFFF],
            (1 << np.arange(23)) - 1,
            1 << np.arange(23),
            rng.integers(0, 1 << 23, 64),
        ]
    ).astype(np.uint32)
    exp = np.arange(256, dtype=np.uint32)
    bits = ((exp[:, None] << 23) | sig[None, :]).reshape(-1)
    bits = np.concatenate([bits, bits | np.uint32(0x80000000)])
    with np.errstate(over="ignore", invalid="ignore"):
        ref = bits.view(np.float32).astype(np.float16).view(np.uint16)
    got = np.empty(len(bits), np.uint16)
    kernels.to_half(bits, got)
    bad = np.flatnonzero(got != ref)
    assert not len(bad), [
        (hex(int(b)), hex(int(r)), hex(int(g)))
        for b, r, g in zip(bits[bad][:5], ref[bad], got[bad], strict=False)
    ]


@pytest.mark.parametrize("bits", [0, 1, 10, 11, 23, 39, 62])
def test_radix_sort_is_np_sort(bits: int) -> None:
    rng = np.random.default_rng(bits)
    for n in (1, 2, 1000):
        a = rng.integers(0, 1 << bits, n) if bits else np.zeros(n, np.int64)
        np.testing.assert_array_equal(kernels.radix_sort(a.copy(), bits), np.sort(a))


def test_small_fusions_leave_numba_alone_and_fusion_runs_without_it(tmp_path: Path) -> None:
    """In a fresh interpreter: a fusion of fewer than ``compiled_min_points`` points per chunk does not import
    numba (its ≈ 1 s would not pay off), and where numba cannot be imported a fusion that asks for the
    kernels runs the numpy path; both give the grid the compiled path gives here."""
    c = 5
    batches = _batches(4, c=c)
    np.savez(tmp_path / "obs.npz", *[a for o in batches for a in o])
    grid = fuse(batches, c, FusionConfig(chunk_points=900), paths=COMPILED)
    digest = hashlib.sha256(grid.keys.tobytes() + grid.logp.tobytes()).hexdigest()
    code = (
        "import sys, hashlib\n"
        "import numpy as np\n"
        "from leap_core.fusion import FusionConfig, FusionPaths, Observations, fuse, compiled_kernels\n"
        f"a = list(np.load({str(tmp_path / 'obs.npz')!r}).values())\n"
        "obs = [Observations(*a[i : i + 3]) for i in range(0, len(a), 3)]\n"
        "for hide in (False, True):\n"
        "    if hide:\n"
        "        sys.modules['numba'] = None\n"
        "        assert compiled_kernels(True) is None\n"
        "    paths = FusionPaths(compiled_min_points=0 if hide else 10_000)\n"
        "    g = fuse(obs, 5, FusionConfig(chunk_points=900), paths=paths)\n"
        "    assert 'leap_core.fusion_kernels' not in sys.modules and not sys.modules.get('numba')\n"
        "    print(hashlib.sha256(g.keys.tobytes() + g.logp.tobytes()).hexdigest())\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [digest, digest]


def test_fuse_unique_never_finalises_in_a_callers_buffer() -> None:
    """Without a prior grid fuse_unique's accumulator is the caller's logp: when that is a slice of a larger
    array, the float16 grid is not written into (nor the array resized to) that array's buffer, as a
    compiled merge's accumulator with spare rows is."""
    c = 5
    big = np.full((10, c), -1.0, np.float32)
    grid = fusion.fuse_unique(None, np.arange(6, dtype=np.int64), big[:6], c)
    assert big.shape == (10, c) and big.dtype == np.float32
    np.testing.assert_array_equal(big[6:], -1.0)
    assert grid.logp.shape == (6, c)
