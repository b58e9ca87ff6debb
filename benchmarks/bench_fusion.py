"""Benchmark: Bayesian voxel fusion throughput, kNN smoothing of 1M voxels, bytes per voxel, peak memory.

Data (synthetic, deterministic, built here so the benchmark needs no dataset):

- Fusion: a drive along a street (ground plane + two facades + scattered poles/cars) seen by ``--images``
  camera views of ``--points`` LiDAR points each (default 250 × 20,000 = 5M points), 20 classes, ~100
  table rows per image. Points thin out with range like a spinning LiDAR's. Table rows are spatially
  coherent (points of one mask share a row), as painted images are; a second run uses a random row per
  point, the worst case for the (voxel, row) reduction.
- Baselines, same process, same data, the same work as ``fuse``: from the same per-image observations
  (each point's voxel key and table row, the per-image log tables) to the same stored grid. Each numbers
  the voxels (``np.unique(return_inverse=True)``), gathers each point's log-probabilities from its table,
  accumulates them per voxel into a (V, C) float32 array and finalises as ``fuse`` does (shift to row max
  0, clip, float16); they differ in the accumulation: ``np.add.at``, ``torch.index_add_`` (which the
  project uses in ``fuse_dense``; torch's default threads) or a scipy sparse product
  ``(V × N one-hot) @ (N × C logp)``. The headline ratio is ``fuse`` against the fastest of the three
  ("best baseline"). Computing the keys from the points (``voxel_keys``) is the same for both; it is
  timed apart and added to both sides for the "from points" ratio.
- ``fuse`` runs its compiled kernels (``leap_core/fusion_kernels.py``, numba: the ``fast`` extra) when numba
  is installed; its numpy path (``FusionPaths(compiled=False)``, what runs without numba) is timed beside
  it, and the two grids must be the same bytes (checked). The kernels' one-off cost is measured in fresh
  processes: compiling them into an empty cache, and loading them from a warm one.
- Memory: peak working memory added by ``fuse``, per input point. The stored grid's size per voxel is not a
  measurement (8 B key + 2·C B float16 logp, fixed by the format), so it is printed as a fact, not a target.
- Smoothing: ~1M voxels on street surfaces (ground with steps, two facades), 20-class random posteriors.
  Baseline, same process, same data: the previous smoothing (``baseline_knn_smooth``: rows numbered with
  ``np.unique``, a CSR product per chunk), whose output bytes ``knn_smooth`` must equal (checked), with its
  weighted sums compiled (``compiled=True``) and by numpy (``compiled=False``, timed beside it).

Run: ``.venv/bin/python benchmarks/bench_fusion.py`` (``--quick`` for a small smoke run,
``--smoothing-only`` for the smoothing alone, written to ``fusion_smoothing.json``).
Writes ``benchmarks/results/fusion.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
from functools import partial
from pathlib import Path

import numpy as np
import scipy.sparse

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import peak_memory, print_table, time_it, write_results

from leap_core.fusion import (
    FusionConfig,
    FusionPaths,
    Observations,
    compiled_kernels,
    fuse,
    log_table,
    voxel_keys,
)
from leap_core.smoothing import SMOOTH_CHUNK, SmoothingConfig, knn_smooth, knn_weights

C = 20
COMPILED = FusionPaths(compiled_min_points=0)


# ---------------------------------------------------------------------------------------------- data
def _scan_points(rng: np.random.Generator, origin_x: float, n: int) -> np.ndarray:
    """(n, 3) world points visible from a camera at (origin_x, 0, 0) looking along +x, 5-45 m ahead."""
    # Range density ∝ 1/r (a spinning LiDAR's returns per metre of range fall off with distance).
    r = np.exp(rng.uniform(np.log(5.0), np.log(45.0), n))
    az = rng.uniform(-np.pi / 4, np.pi / 4, n)
    x, y = origin_x + r * np.cos(az), r * np.sin(az)
    kind = rng.random(n)
    z = np.full(n, -1.7)
    facade = (kind < 0.35) & (np.abs(y) > 6)
    y = np.where(facade, np.sign(y) * 12.0 + rng.normal(0, 0.03, n), y)
    z = np.where(facade, rng.uniform(-1.7, 8.0, n), z)
    obj = (kind >= 0.35) & (kind < 0.45)  # poles and cars: small vertical structures on a 7 m lattice
    x = np.where(obj, np.round(x / 7.0) * 7.0 + rng.normal(0, 0.4, n), x)
    y = np.where(obj, np.round(y / 7.0) * 7.0 + rng.normal(0, 0.4, n), y)
    z = np.where(obj, rng.uniform(-1.7, 1.5, n), z + rng.normal(0, 0.02, n))
    return np.stack([x, y, z], axis=1)


def make_observations(
    images: int, points: int, rows: int, coherent: bool, seed: int = 0
) -> list[Observations]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(images):
        xyz = _scan_points(rng, 0.8 * i, points)
        keys = voxel_keys(xyz, 0.2)
        if coherent:
            # Masks cover contiguous regions: a row per 3 m cell (hashed into the image's rows).
            cell = np.floor(xyz / 3.0).astype(np.int64)
            row = (cell[:, 0] * 73_856_093 ^ cell[:, 1] * 19_349_663 ^ cell[:, 2] * 83_492_791) % rows
        else:
            row = rng.integers(0, rows, points)
        table = rng.dirichlet(np.full(C, 0.3), rows).astype(np.float32)
        out.append(Observations(keys, row.astype(np.int32), log_table(table, 1e-3)))
    return out


def surface_voxel_centres(target: int, voxel: float = 0.2, seed: int = 0) -> np.ndarray:
    """~``target`` voxel centres on a straight street: stepped ground 20 m wide plus two 10 m facades."""
    rng = np.random.default_rng(seed)
    per_m = int(20 / voxel) + 2 * int(10 / voxel)
    length = int(np.ceil(target / per_m))
    ix, iy = np.meshgrid(np.arange(length), np.arange(-50, 50), indexing="ij")
    ground = np.stack([ix.ravel(), iy.ravel(), -9 + (rng.random(ix.size) < 0.2)], axis=1)
    jx, jz = np.meshgrid(np.arange(length), np.arange(-8, 42), indexing="ij")
    walls = [np.stack([jx.ravel(), np.full(jx.size, s), jz.ravel()], axis=1) for s in (-51, 51)]
    ijk = np.concatenate([ground, *walls])[:target]
    return ((ijk + 0.5) * voxel).astype(np.float32)


# --------------------------------------------------------------------------------------------- bench
def naive_inputs(obs: list[Observations]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted unique voxel keys (V,), each point's voxel index (N,) and log-probabilities (N, C)."""
    keys = np.concatenate([o.keys for o in obs])
    logp = np.concatenate([o.log_table[o.rows] for o in obs])
    uk, inv = np.unique(keys, return_inverse=True)
    return uk, inv, logp


def naive_add_at(inv: np.ndarray, logp: np.ndarray, v: int) -> np.ndarray:
    acc = np.zeros((v, C), np.float32)
    np.add.at(acc, inv, logp)
    return acc


def torch_index_add(inv: np.ndarray, logp: np.ndarray, v: int) -> np.ndarray:
    import torch

    acc = torch.zeros((v, C), dtype=torch.float32)
    acc.index_add_(0, torch.from_numpy(inv), torch.from_numpy(logp))
    out: np.ndarray = acc.numpy()
    return out


def scipy_sparse_sum(inv: np.ndarray, logp: np.ndarray, v: int) -> np.ndarray:
    n = len(inv)
    onehot = scipy.sparse.csr_matrix((np.ones(n, np.float32), (inv, np.arange(n))), shape=(v, n))
    return np.asarray(onehot @ logp, dtype=np.float32)


ACCUMULATIONS = {
    "np.add.at": naive_add_at,
    "torch.index_add_": torch_index_add,
    "scipy sparse": scipy_sparse_sum,
}
"""Per-point accumulations ``acc[inv[p]] += logp[p]`` into (V, C), given (inv, logp, V)."""


def same_work(accumulate, obs: list[Observations]) -> tuple[np.ndarray, np.ndarray]:
    """``fuse(obs, C)``'s work done plainly: number the voxels, gather per-point log-probabilities,
    ``accumulate`` them, finalise (shift to row max 0, clip, float16). Returns (keys (V,), logp (V, C))."""
    uk, inv, logp = naive_inputs(obs)
    acc = accumulate(inv, logp, len(uk))
    acc -= acc.max(axis=1, keepdims=True)
    np.maximum(acc, np.float32(-FusionConfig().logp_clip), out=acc)
    return uk, acc.astype(np.float16)


def bench_fusion(images: int, points: int, rows: int, repeat: int) -> tuple[list, dict]:
    n = images * points
    results: dict = {
        "points": n,
        "images": images,
        "points_per_image": points,
        "rows_per_image": rows,
        "classes": C,
    }
    table_rows = []
    for coherent in (True, False):
        label = "coherent rows" if coherent else "random rows (worst case)"
        obs = make_observations(images, points, rows, coherent)
        xyz = _xyz_cache(images, points)
        t_keys = time_it(partial(voxel_keys, xyz, 0.2), repeat=3)
        # The kernels whatever the size (a --quick run's chunks are below compiled_min_points).
        t_fuse = time_it(partial(fuse, obs, C, paths=COMPILED), repeat=repeat)
        numpy_path = FusionPaths(compiled=False)
        t_numpy = time_it(partial(fuse, obs, C, paths=numpy_path), repeat=repeat)
        grid, mem = peak_memory(partial(fuse, obs, C, paths=COMPILED))
        plain = fuse(obs, C, paths=numpy_path)
        same_bytes = (
            grid.keys.tobytes() == plain.keys.tobytes() and grid.logp.tobytes() == plain.logp.tobytes()
        )
        assert same_bytes, "the compiled and numpy paths gave different grids"
        del plain
        base_t, base_diff = {}, {}
        for name, fn in ACCUMULATIONS.items():
            base_t[name] = time_it(partial(same_work, fn, obs), repeat=max(1, repeat // 2))
            keys, logp16 = same_work(fn, obs)
            assert np.array_equal(keys, grid.keys), f"{name}: other voxels than fuse"
            base_diff[name] = float(np.abs(logp16.astype(np.float32) - grid.logp.astype(np.float32)).max())
        del keys, logp16
        best = min(base_t, key=lambda k: base_t[k].median)
        best_best = min(base_t, key=lambda k: base_t[k].best)
        t_best = base_t[best].median
        results["coherent" if coherent else "random_rows"] = {
            "fuse": t_fuse.to_dict(),
            "baselines_same_work": {
                k: {**t.to_dict(), "max_abs_diff_vs_fuse": base_diff[k]} for k, t in base_t.items()
            },
            "best_baseline": best,
            "voxel_keys": {**t_keys.to_dict(), "points_per_s": len(xyz) / t_keys.median},
            "points_per_s": n / t_fuse.median,
            "points_per_s_best": n / t_fuse.best,
            "points_per_cpu_s": n / t_fuse.cpu_median,
            "ratio_vs_best_baseline": t_best / t_fuse.median,
            "ratio_vs_best_baseline_best": base_t[best_best].best / t_fuse.best,
            "ratio_vs_naive_add_at": base_t["np.add.at"].median / t_fuse.median,
            "ratio_from_points_vs_best_baseline": (t_keys.median + t_best) / (t_keys.median + t_fuse.median),
            "compiled": compiled_kernels(True) is not None,
            "numpy_path": t_numpy.to_dict(),
            "ratio_vs_numpy_path": t_numpy.median / t_fuse.median,
            "identical_to_numpy_path": same_bytes,
            "voxels": len(grid),
            "stored_bytes_per_voxel": grid.nbytes / len(grid),
            "peak_memory_added_bytes": mem.added,
            "peak_memory_added_bytes_per_point": mem.added / n,
            "peak_memory_exact": mem.exact,
        }
        compiled = "compiled" if compiled_kernels(True) is not None else "numba missing: numpy"
        table_rows.append(_row(f"fuse ({compiled}), {label}", t_fuse, n, t_best, mem.added))
        table_rows.append(_row("  fuse, numpy path (without numba; same bytes)", t_numpy, n, t_best, None))
        for name, t in base_t.items():
            mark = " (best)" if name == best else ""
            table_rows.append(_row(f"  {name}, same work{mark}", t, n, t_best, None))
        table_rows.append(_row("  voxel_keys (xyz → key), same points", t_keys, len(xyz), None, None))
        diffs = ", ".join(f"{k} {d:.3g}" for k, d in base_diff.items())
        table_rows.append(
            [f"  {len(grid):,} voxels, working memory {mem.added / n:.1f} B/point; max|Δ| vs fuse: {diffs}"]
            + [""] * 6
        )
    return table_rows, results


_COMPILE_PROBE = """
import time
t0 = time.perf_counter()
from leap_core.fusion import compiled_kernels
kern = compiled_kernels(True)
t1 = time.perf_counter()
import numpy as np
from leap_core.fusion import FusionConfig, FusionPaths, Observations, fuse, log_table
rng = np.random.default_rng(0)
obs = [Observations(rng.integers(0, 1 << 20, 5000), rng.integers(0, 50, 5000).astype(np.int32),
                    log_table(rng.dirichlet(np.ones(20), 50), 1e-3)) for _ in range(4)]
paths = FusionPaths(compiled_min_points=0)
t2 = time.perf_counter()
fuse(obs, 20, FusionConfig(chunk_points=12_000), paths=paths)
t3 = time.perf_counter()
fuse(obs, 20, FusionConfig(chunk_points=12_000), paths=paths)
t4 = time.perf_counter()
print(kern is not None, t1 - t0, (t3 - t2) - (t4 - t3))
"""


def bench_compile(quick: bool) -> dict:
    """The kernels' one-off cost in fresh processes: importing numba and the kernels module, then the first
    ``fuse`` less a second one (compiling, or loading from the cache), with an empty cache folder
    (``NUMBA_CACHE_DIR``) and again with it filled (``quick``: only the latter, with the default cache)."""
    import subprocess
    import tempfile

    out: dict = {}
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "PYTHONPATH": str(root)}
        if not quick:
            env["NUMBA_CACHE_DIR"] = cache
        for name in ("warm_cache",) if quick else ("empty_cache", "warm_cache"):
            res = subprocess.run(
                [sys.executable, "-c", _COMPILE_PROBE], env=env, capture_output=True, text=True, check=True
            )
            compiled, t_import, t_first = res.stdout.split()
            out[name] = {"import_s": float(t_import), "first_call_extra_s": float(t_first)}
            out["compiled"] = compiled == "True"
    return out


def _row(what: str, t, n: int, baseline_s: float | None, mem: int | None) -> list:
    """Table row: median s, best s, CPU s, M items/s (median), ratio to the baseline, peak MiB."""
    return [
        what,
        t.median,
        t.best,
        t.cpu_median,
        n / t.median / 1e6,
        "" if baseline_s is None else baseline_s / t.median,
        "" if mem is None else mem / 2**20,
    ]


_XYZ: dict = {}


def _xyz_cache(images: int, points: int) -> np.ndarray:
    if (images, points) not in _XYZ:
        rng = np.random.default_rng(0)
        _XYZ[(images, points)] = np.concatenate([_scan_points(rng, 0.8 * i, points) for i in range(images)])
    return _XYZ[(images, points)]


def baseline_knn_smooth(centres: np.ndarray, probs: np.ndarray, cfg: SmoothingConfig) -> np.ndarray:
    """The smoothing before ``knn_mix`` (same output bytes), kept as the same-work baseline: one tree, chunks
    of ``SMOOTH_CHUNK`` voxels queried with ``cfg.workers`` threads, the rows they hit numbered with
    ``np.unique`` and mixed as a (n × R) CSR @ (R × C) float32 product."""
    from scipy.spatial import cKDTree

    p = np.asarray(probs, np.float32)
    v = len(centres)
    k = min(cfg.k, v)
    bound = np.inf if cfg.max_distance is None else float(cfg.max_distance)
    tree = cKDTree(np.asarray(centres, np.float32))
    out = np.empty(p.shape, np.float32)
    for s in range(0, v, SMOOTH_CHUNK):
        e = min(v, s + SMOOTH_CHUNK)
        n = e - s
        dists, idx = tree.query(tree.data[s:e], k=k, distance_upper_bound=bound, workers=cfg.workers)
        w = knn_weights(dists)
        idx = np.where(idx >= v, np.arange(s, e)[:, None], idx)
        cols, inv = np.unique(idx, return_inverse=True)
        mat = scipy.sparse.csr_matrix(
            (w.reshape(-1), inv.reshape(-1), np.arange(0, n * k + 1, k)), shape=(n, len(cols))
        )
        out[s:e] = mat @ p[cols]
    return out


def bench_smoothing(voxels: int, repeat: int) -> tuple[list, dict]:
    centres = surface_voxel_centres(voxels)
    rng = np.random.default_rng(1)
    probs = rng.dirichlet(np.full(C, 0.3), len(centres)).astype(np.float32)
    rows, res = [], {"voxels": len(centres)}
    for name, cfg in (
        ("default (k 9, max 0.6 m, 2 workers)", SmoothingConfig()),
        ("paper (k 9, unbounded, 2 workers)", SmoothingConfig(max_distance=None)),
    ):
        load = os.getloadavg()[0]
        t_base = time_it(lambda cfg=cfg: baseline_knn_smooth(centres, probs, cfg), repeat=repeat)
        t = time_it(lambda cfg=cfg: knn_smooth(centres, probs, cfg, compiled=True), repeat=repeat)
        t_np = time_it(lambda cfg=cfg: knn_smooth(centres, probs, cfg, compiled=False), repeat=repeat)
        _, mem = peak_memory(lambda cfg=cfg: knn_smooth(centres, probs, cfg, compiled=True))
        base = baseline_knn_smooth(centres, probs, cfg).tobytes()
        same = knn_smooth(centres, probs, cfg, compiled=True).tobytes() == base
        same_np = knn_smooth(centres, probs, cfg, compiled=False).tobytes() == base
        key = "bounded" if cfg.max_distance else "unbounded"
        res[key] = {
            **t.to_dict(),
            "peak_memory_added_bytes": mem.added,
            "max_distance": cfg.max_distance,
            "baseline": t_base.to_dict(),
            "ratio_vs_baseline": t_base.median / t.median,
            "identical_to_baseline": same,
            "numpy_path": t_np.to_dict(),
            "numpy_path_identical_to_baseline": same_np,
            "load_average_1min": [load, os.getloadavg()[0]],
        }
        v = len(centres)
        rows.append(_row(f"knn_smooth {v:,} voxels, {name}", t, v, t_base.median, mem.added))
        rows.append(_row("  knn_smooth, numpy path (without numba)", t_np, v, t_base.median, None))
        rows.append(_row("  baseline (np.unique + CSR product), same work", t_base, v, None, None))
        loads = f"{load:.1f} → {os.getloadavg()[0]:.1f}"
        rows.append(
            [f"  output bytes identical to the baseline: {same} (numpy path {same_np}); load average {loads}"]
            + [""] * 6
        )
    from scipy.spatial import cKDTree

    d, _ = cKDTree(centres).query(centres, k=9, workers=2)
    res["ninth_neighbour_distance_m"] = {q: float(np.quantile(d[:, 8], q / 100)) for q in (50, 99, 100)}
    return rows, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=250)
    ap.add_argument("--points", type=int, default=20_000)
    ap.add_argument("--rows", type=int, default=100)
    ap.add_argument("--voxels", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    ap.add_argument("--smoothing-only", action="store_true", help="only the smoothing against its baseline")
    args = ap.parse_args()
    if args.quick:
        args.images, args.points, args.voxels, args.repeat = 20, 5000, 50_000, 2
    header = ["what", "median s", "best s", "CPU s", "M items/s", "× baseline", "peak MiB added"]
    if args.smoothing_only:
        srows, sres = bench_smoothing(args.voxels, args.repeat)
        print_table(f"Smoothing ({os.cpu_count()} cores)", header, srows)
        name = "fusion_smoothing" + ("_quick" if args.quick else "")
        print(f"wrote {write_results(name, {'args': vars(args), 'smoothing': sres})}")
        return

    load_start = os.getloadavg()
    frows, fres = bench_fusion(args.images, args.points, args.rows, args.repeat)
    fres["compile"] = comp = bench_compile(args.quick)
    srows, sres = bench_smoothing(args.voxels, args.repeat)
    load = os.getloadavg()
    print_table(
        f"Fusion: {fres['points']:,} points, {C} classes, {args.rows} table rows per image "
        f"(load average at start {load_start[0]:.1f}, now {load[0]:.1f} on {os.cpu_count()} cores)",
        [*header[:5], "× best baseline", header[6]],
        frows,
    )
    print_table("Smoothing", header, srows)

    co, rnd = fres["coherent"], fres["random_rows"]
    sm = sres["bounded"]
    targets = [
        ["fusion ≥ 30 M points/s", co["points_per_s"] / 1e6, co["points_per_s_best"] / 1e6, 30.0],
        [
            f"fusion ≥ 1× best baseline ({co['best_baseline']})",
            co["ratio_vs_best_baseline"],
            co["ratio_vs_best_baseline_best"],
            1.0,
        ],
        [
            f"  random rows, ≥ 1× best ({rnd['best_baseline']})",
            rnd["ratio_vs_best_baseline"],
            rnd["ratio_vs_best_baseline_best"],
            1.0,
        ],
        ["smoothing 1M voxels ≤ 0.7 s", sm["median_s"], sm["best_s"], 0.7],
        ["  (unbounded kNN, paper)", sres["unbounded"]["median_s"], sres["unbounded"]["best_s"], 0.7],
    ]
    for t in targets:
        lower_is_better = t[0].startswith(("smoothing", "  (unb"))
        t.append("yes" if (t[1] <= t[3] if lower_is_better else t[1] >= t[3]) else "no")
        t.append("yes" if (t[2] <= t[3] if lower_is_better else t[2] >= t[3]) else "no")
        if args.quick:
            t[-2:] = ["(quick)", "(quick)"]
    print_table("Targets", ["target", "median", "best", "limit", "met (median)", "met (best)"], targets)
    print(
        f"Ratio to the best same-work baseline (coherent rows): {co['ratio_vs_best_baseline']:.2f}× "
        f"{co['best_baseline']} (np.add.at: {co['ratio_vs_naive_add_at']:.1f}×); from the points "
        f"(voxel_keys added to both): {co['ratio_from_points_vs_best_baseline']:.2f}×."
    )
    if comp["compiled"]:
        w = comp["warm_cache"]
        e = comp.get("empty_cache")
        cold = (
            ""
            if e is None
            else f"empty cache {e['import_s']:.2f} s import + {e['first_call_extra_s']:.2f} s compile; "
        )
        print(
            f"Compiled kernels: {co['ratio_vs_numpy_path']:.2f}× the numpy path (coherent rows; random rows "
            f"{rnd['ratio_vs_numpy_path']:.2f}×), same bytes: {co['identical_to_numpy_path']}. One-off cost "
            f"in a fresh process: {cold}warm cache {w['import_s']:.2f} s import + "
            f"{w['first_call_extra_s']:.2f} s load."
        )
    else:
        print("numba is not installed: fuse ran its numpy path (pip install 'leap-studio[fast]').")
    print(
        f"Stored grid: {co['stored_bytes_per_voxel']:.0f} B/voxel = 8 B key + 2·{C} B float16 logp (fixed "
        f"by the format, not a measurement); fuse's working memory: "
        f"{co['peak_memory_added_bytes_per_point']:.1f} B per input point (peak RSS added)."
    )
    path = write_results(
        "fusion" if not args.quick else "fusion_quick",
        {
            "args": vars(args),
            "fusion": fres,
            "smoothing": sres,
            "load_average_start": load_start,
            "targets": [
                {
                    "target": t[0],
                    "median": t[1],
                    "best": t[2],
                    "limit": t[3],
                    "met_median": t[4],
                    "met_best": t[5],
                }
                for t in targets
            ],
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
