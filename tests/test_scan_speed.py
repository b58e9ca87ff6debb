"""The faster per-scan 3D stages give the bytes of the straightforward computation.

References written out plainly here (the one-call matrix products, the (M, P) membership matrix, a per-mask
depth-clustering loop, ``np.unique(axis=0)`` of packed bits, ``np.load``, ``world_points`` + ``voxel_keys`` +
a ``searchsorted`` lookup) are compared byte for byte with the blocked / pair-based / one-read code paths,
on random data and on the files of a real pipeline run. The run with 4 frame threads must write the files
of the run with 1, and a cancelled threaded run must resume to them.
"""

from __future__ import annotations

import struct
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label
from test_pipeline import make_street
from typer.testing import CliRunner

from app.cli import cli
from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence
from leap_core.errors import Cancelled, ConfigError
from leap_core.export import labels_to_raw
from leap_core.fusion import voxel_keys, world_points
from leap_core.geometry import ROW_BLOCK, affine_points, row_blocks
from leap_core.io_utils import read_npz
from leap_core.labelers.base import SoftMasks
from leap_core.pipeline import stage_status
from leap_core.pipeline.apply import frame_keys
from leap_core.pipeline.context import ordered_map
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.projection import (
    Painted,
    Projected,
    ProjectionConfig,
    depth_cluster_filter,
    paint,
    project_points,
    unique_word_rows,
)
from leap_core.runtime import Runtime
from leap_core.schema import builtin_schema
from leap_core.smoothing import SmoothedGrid
from leap_core.types import UNLABELED


# ------------------------------------------------------------------------------------- references
def ref_project(xyz: np.ndarray, m: np.ndarray, h: int, w: int, min_depth: float) -> Projected:
    """project_points as one (N, 3) × (3, 3) product."""
    cam = xyz[:, :3].astype(np.float64) @ m[:, :3].T + m[:, 3]
    d = cam[:, 2]
    front = np.flatnonzero(d > min_depth)
    cam, d = cam[front], d[front]
    u = np.floor(cam[:, 0] / d + 0.5)
    v = np.floor(cam[:, 1] / d + 0.5)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return Projected(
        front[inside].astype(np.int64),
        u[inside].astype(np.int32),
        v[inside].astype(np.int32),
        d[inside].astype(np.float32),
    )


def ref_cluster(member: np.ndarray, depth: np.ndarray, gap: float, min_points: int) -> np.ndarray:
    """Per mask, one at a time: sort its points by depth, split at gaps > ``gap``, keep the largest
    cluster (ties: the nearest); masks with fewer than ``min_points`` points stay whole."""
    d_all = np.asarray(depth, np.float64)
    out = np.zeros_like(member)
    for m in range(member.shape[0]):
        pts = np.flatnonzero(member[m])
        if len(pts) == 0:
            continue
        if len(pts) < min_points:
            out[m, pts] = True
            continue
        order = pts[np.argsort(d_all[pts], kind="stable")]
        clusters = np.split(order, np.flatnonzero(np.diff(d_all[order]) > gap) + 1)
        best = max(range(len(clusters)), key=lambda k: (len(clusters[k]), -k))
        out[m, clusters[best]] = True
    return out


def ref_paint(soft: SoftMasks, proj: Projected, cfg: ProjectionConfig) -> Painted:
    """Painting from the dense (M, P) membership and np.unique(axis=0) of the packed covering sets."""
    c = soft.num_classes
    if soft.num_masks == 0 or len(proj) == 0:
        return Painted.empty(c)
    member = soft.dense()[:, proj.v, proj.u]
    if cfg.depth_clustering:
        member = ref_cluster(member, proj.depth, cfg.cluster_gap, cfg.min_cluster_points)
    covered = np.flatnonzero(member.any(axis=0))
    if len(covered) == 0:
        return Painted.empty(c)
    packed = np.packbits(member[:, covered], axis=0).T
    words = -(-packed.shape[1] // 8)
    padded = np.zeros((len(covered), words * 8), np.uint8)
    padded[:, : packed.shape[1]] = packed
    as_u64 = padded.view(np.uint64)
    if words == 1:
        uniq, inv = np.unique(as_u64[:, 0], return_inverse=True)
        uniq = uniq.reshape(-1, 1)
    else:
        uniq, inv = np.unique(as_u64, axis=0, return_inverse=True)
    uniq_bits = np.ascontiguousarray(uniq).view(np.uint8)[:, : packed.shape[1]]
    combos = np.unpackbits(uniq_bits, axis=1, count=soft.num_masks).astype(np.float32)
    w = combos * np.maximum(soft.confidence, np.float32(1e-6))[None, :]
    table = (w @ soft.probs) / w.sum(axis=1, keepdims=True)
    return Painted(proj.idx[covered], inv.reshape(-1).astype(np.int32), table.astype(np.float32))


def assert_same_bytes(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()


def assert_same_painting(a: Painted, b: Painted) -> None:
    assert_same_bytes(a.point_idx, b.point_idx)
    assert_same_bytes(a.rows, b.rows)
    assert_same_bytes(a.table, b.table)


# --------------------------------------------------------------------------------- random inputs
def random_soft(rng: np.random.Generator, m: int, h: int = 29, w: int = 43, c: int = 6) -> SoftMasks:
    """M masks: rectangles of random size (overlapping), plus scattered pixels; one zero confidence."""
    masks = np.zeros((m, h, w), bool)
    for k in range(m):
        r0, c0 = rng.integers(0, h), rng.integers(0, w)
        masks[k, r0 : r0 + rng.integers(1, 12), c0 : c0 + rng.integers(1, 16)] = True
        masks[k] |= rng.random((h, w)) < 0.01
    conf = rng.uniform(0.05, 1.0, m).astype(np.float32)
    if m > 2:
        conf[1] = 0.0
    probs = rng.dirichlet(np.full(c, 0.5), m) if m else np.zeros((0, c))
    return SoftMasks.from_dense(masks, probs, conf, num_classes=c)


def random_projection(rng: np.random.Generator, n: int, h: int, w: int) -> Projected:
    """Points on random pixels (several per pixel) at depths with exact ties (0.25 m steps) and gaps."""
    depth = np.abs(np.round((rng.choice([4.0, 9.0, 20.0], n) + rng.normal(0, 0.8, n)) * 4) / 4) + 0.5
    return Projected(
        np.sort(rng.choice(10 * n, n, replace=False)).astype(np.int64),
        rng.integers(0, w, n).astype(np.int32),
        rng.integers(0, h, n).astype(np.int32),
        depth.astype(np.float32),
    )


# ---------------------------------------------------------------------------------------- geometry
def test_row_blocks_never_leave_a_single_row() -> None:
    assert list(row_blocks(10, 4)) == [(0, 4), (4, 8), (8, 10)]
    assert list(row_blocks(9, 4)) == [(0, 4), (4, 9)]
    assert list(row_blocks(1, 4)) == [(0, 1)]
    assert list(row_blocks(0, 4)) == []
    for n in range(2, 40):
        blocks = list(row_blocks(n, 3))
        assert blocks[0][0] == 0 and blocks[-1][1] == n
        assert all(b - a >= 2 for a, b in blocks)
        assert all(blocks[k][1] == blocks[k + 1][0] for k in range(len(blocks) - 1))
    with pytest.raises(ValueError, match="block"):
        list(row_blocks(5, 1))


@pytest.mark.parametrize("n", [0, 1, 2, 3, 5, 17, ROW_BLOCK - 1, ROW_BLOCK + 1, 2 * ROW_BLOCK + 1, 30_001])
def test_affine_points_are_the_bytes_of_one_product(n: int) -> None:
    rng = np.random.default_rng(n)
    pts = (rng.normal(0, 20, (n, 4))).astype(np.float32)
    cam = np.array([[721.5, 0.0, 609.6, 44.9], [0.0, 721.5, 172.9, 0.2], [0.0, 0.0, 1.0, 0.003]])
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    pose = np.vstack([np.hstack([rot, rng.normal(0, 50, (3, 1))]), [0, 0, 0, 1]])
    for m in (cam, pose[:3]):
        expected = pts[:, :3].astype(np.float64) @ m[:, :3].T + m[:, 3]
        assert_same_bytes(affine_points(pts, m), expected)
        for block in (2, 3, 4, 7):  # many blocks, remainders of every size
            assert_same_bytes(affine_points(pts[:200], m, block=block), expected[:200])
    assert_same_bytes(affine_points(pts, pose[:3]), world_points(pts, pose))


def test_projection_is_the_one_product_projection() -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 15, (50_000, 4)).astype(np.float32)
    m = np.array([[609.6, -721.5, -1.2, -123.0], [172.9, 9.6, -721.5, -101.0], [1.0, 0.01, -0.002, -0.27]])
    got, want = project_points(pts, m, 375, 1242, 0.5), ref_project(pts, m, 375, 1242, 0.5)
    assert len(want) > 1000
    for name in ("idx", "u", "v", "depth"):
        assert_same_bytes(getattr(got, name), getattr(want, name))


# ---------------------------------------------------------------------------------------- painting
@pytest.mark.parametrize("num_masks", [0, 1, 5, 63, 64, 65, 130])
def test_paint_is_the_straightforward_painting(num_masks: int) -> None:
    rng = np.random.default_rng(num_masks)
    soft = random_soft(rng, num_masks)
    proj = random_projection(rng, 900, soft.height, soft.width)
    for cfg in (
        ProjectionConfig(),
        ProjectionConfig(cluster_gap=0.3, min_cluster_points=0),
        ProjectionConfig(depth_clustering=False),
    ):
        got, want = paint(soft, proj, cfg), ref_paint(soft, proj, cfg)
        assert_same_painting(got, want)
        if num_masks >= 5:
            assert len(want.table) > min(num_masks, 10)  # guard: many covering sets: row order matters


@pytest.mark.parametrize("num_masks", [1, 9, 70])
def test_depth_cluster_filter_is_the_per_mask_loop(num_masks: int) -> None:
    rng = np.random.default_rng(10 + num_masks)
    soft = random_soft(rng, num_masks)
    proj = random_projection(rng, 600, soft.height, soft.width)
    member = soft.dense()[:, proj.v, proj.u]
    removed = 0
    for gap, min_points in ((1.0, 3), (0.3, 0), (2.5, 50)):
        got = depth_cluster_filter(member, proj.depth, gap, min_points)
        np.testing.assert_array_equal(got, ref_cluster(member, proj.depth, gap, min_points))
        removed += int((got != member).sum())
    assert removed > 0  # guard: the filter removes points here


def test_unique_word_rows_is_numpys_unique_rows() -> None:
    rng = np.random.default_rng(5)
    for cols in (1, 2, 3):
        # Few distinct rows, values across the whole unsigned range (the sign bit set in some).
        pool = rng.integers(0, 2**64, (12, cols), dtype=np.uint64)
        pool[0] = 0
        pool[1, 0] = np.uint64(2**63)
        words = pool[rng.integers(0, len(pool), 3000)]
        uniq, inv = unique_word_rows(words)
        want_u, want_inv = np.unique(words, axis=0, return_inverse=True)
        assert_same_bytes(uniq, want_u)
        np.testing.assert_array_equal(inv, want_inv.reshape(-1))
    empty_u, empty_inv = unique_word_rows(np.zeros((0, 2), np.uint64))
    assert empty_u.shape == (0, 2) and empty_inv.shape == (0,)


# ------------------------------------------------------------------------------------------ read_npz
def test_read_npz_equals_np_load(tmp_path: Path) -> None:
    arrays = {
        "i16": np.arange(-5, 5, dtype=np.int16),
        "f16": np.linspace(0, 1, 7).astype(np.float16),
        "u64": np.array([0, 2**63, 2**64 - 1], np.uint64),
        "flags": np.array([True, False, True]),
        "scalar": np.asarray(42, np.int64),
        "empty": np.zeros((0, 3), np.float32),
        "fortran": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
        "big_endian": np.arange(4, dtype=">i4"),
        "bits": np.packbits(np.random.default_rng(0).random(10_000) < 0.02),
    }
    for save in (np.savez, np.savez_compressed):
        path = tmp_path / f"{save.__name__}.npz"
        save(path, **arrays)
        got = read_npz(path)
        assert sorted(got) == sorted(arrays)
        with np.load(path) as z:
            for name in arrays:
                assert_same_bytes(np.ascontiguousarray(got[name]), np.ascontiguousarray(z[name]))
                assert got[name].flags.f_contiguous == z[name].flags.f_contiguous
        some = read_npz(path, ("i16", "bits"))
        assert sorted(some) == ["bits", "i16"]
        assert_same_bytes(some["bits"], arrays["bits"])
        with pytest.raises(KeyError, match="nope"):
            read_npz(path, ("i16", "nope"))


def test_read_npz_refuses_damaged_files(tmp_path: Path) -> None:
    path = tmp_path / "a.npz"
    np.savez_compressed(path, x=np.arange(1000))
    raw = bytearray(path.read_bytes())
    info = zipfile.ZipFile(path).getinfo("x.npy")
    off = info.header_offset
    name_len, extra_len = struct.unpack("<HH", raw[off + 26 : off + 30])
    raw[off + 30 + name_len + extra_len + info.compress_size // 2] ^= 0xFF  # inside the deflated data
    bad = tmp_path / "bad.npz"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError):
        read_npz(bad)
    np.savez(path, x=np.arange(1000))  # stored: only the CRC sees a changed data byte
    raw = bytearray(path.read_bytes())
    info = zipfile.ZipFile(path).getinfo("x.npy")
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26 : info.header_offset + 30])
    raw[info.header_offset + 30 + name_len + extra_len + info.compress_size - 3] ^= 0x01
    bad.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="CRC"):
        read_npz(bad)
    bad.write_bytes(b"not a zip at all")
    with pytest.raises(ValueError, match="not an npz"):
        read_npz(bad)
    np.savez(bad, obj=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="object arrays"):
        read_npz(bad)
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("notes.txt", "hello")
    with pytest.raises(ValueError, match=r"not a \.npy"):
        read_npz(bad)


# ------------------------------------------------------------------------------- runs on the street
@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_street(tmp_path_factory.mktemp("street") / "sequences" / "00", n_frames=6)


@pytest.fixture(scope="module")
def runs(street: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[int, tuple[Path, list]]:
    """The same run with 1 and with 4 frame threads, and each one's progress calls."""
    schema = builtin_schema("semantickitti")
    out = {}
    for threads in (1, 4):
        calls: list[tuple[str, int, int]] = []
        result = label(
            street,
            schema,
            PipelineConfig(),
            tmp_path_factory.mktemp("runs") / f"t{threads}",
            runtime=Runtime(frame_threads=threads),
            progress=lambda *a, calls=calls: calls.append(a),
        )
        out[threads] = (result.folder, calls)
    return out


def _files(run_dir: Path) -> dict[str, bytes]:
    names = ["grid.npz", "grid_smooth.npz", "metrics.json"]  # metrics: evaluate reads frames on threads
    for sub in ("observations", "points", "export"):
        names += [f"{sub}/{p.name}" for p in sorted((run_dir / sub).iterdir())]
    return {n: (run_dir / n).read_bytes() for n in names}


def test_frame_threads_change_no_byte_and_no_progress_call(runs) -> None:
    (one, calls1), (four, calls4) = runs[1], runs[4]
    files = _files(one)
    assert len(files) == 3 + 6 * 4
    assert files == _files(four)
    assert calls1 == calls4


def test_run_files_are_the_reference_computation(runs, street: Path) -> None:
    """observations, points and export of a (threaded) run = the straightforward computation per frame."""
    run_dir = runs[4][0]
    seq = KittiSequence(street)
    cfg = PipelineConfig()
    schema = builtin_schema("semantickitti")
    final = SmoothedGrid.load(run_dir / "grid_smooth.npz")
    vl = final.voxel_labels()
    for i in range(len(seq)):
        frame = seq.frame(i)
        fid = frame.frame_id
        soft = SoftMasks.load(run_dir / "labels2d" / f"{fid}.npz")
        proj = ref_project(
            frame.points, seq.calib.lidar_to_image, soft.height, soft.width, cfg.projection.min_depth
        )
        want = ref_paint(soft, proj, cfg.projection)
        with np.load(run_dir / "observations" / f"{fid}.npz") as z:
            assert_same_painting(Painted(z["point_idx"], z["rows"], z["table"]), want)
            in_view = np.zeros(len(frame.points), bool)
            in_view[proj.idx] = True
            assert_same_bytes(z["in_view"], np.packbits(in_view))
        keys = voxel_keys(world_points(frame.points, frame.pose), cfg.fusion.voxel_size)
        assert_same_bytes(frame_keys(frame, cfg.fusion.voxel_size), keys)
        pos = np.minimum(np.searchsorted(vl.keys, keys), len(vl.keys) - 1)
        hit = vl.keys[pos] == keys
        label = np.where(hit, vl.label[pos], UNLABELED).astype(np.int16)
        conf = np.where(hit, vl.conf[pos], 0).astype(np.float32)
        with np.load(run_dir / "points" / f"{fid}.npz") as z:
            assert_same_bytes(z["label"], label)
            assert_same_bytes(z["conf"], conf.astype(np.float16))
            assert_same_bytes(z["point_label"], want.point_labels(len(frame.points)))
        raw = labels_to_raw(label, schema.export_ids()).astype("<u4")
        exported = np.frombuffer((run_dir / "export" / f"{fid}.label").read_bytes(), "<u4")
        # Points of a track carry its id in the upper 16 bits (a mover: its class's moving id too);
        # every other point is the map's label with instance 0.
        obj = SequenceTracks.load(run_dir / "tracks.npz").scan(fid)
        untracked = np.ones(len(frame.points), bool)
        untracked[obj.rows] = False
        assert_same_bytes(exported[untracked], raw[untracked])
        assert_same_bytes(exported[obj.rows] >> 16, obj.track.astype("<u4"))
        conf16 = conf.astype(np.float16).astype(np.float32)
        want_conf = np.where(label == UNLABELED, 0, conf16).astype("<f4")
        assert (run_dir / "export" / f"{fid}.conf").read_bytes() == want_conf.tobytes()
        assert hit.any() and (~hit).any()  # guard: labeled and unlabeled points in every scan


def test_cancelled_threaded_stage_stops_and_resumes(runs, street: Path, tmp_path: Path) -> None:
    """Cancelled from progress in a threaded stage: no frame starts after it, the stage is recorded
    cancelled, and the resumed run writes the uninterrupted run's files."""
    schema = builtin_schema("semantickitti")
    run_dir = folder(tmp_path / "cancelled")
    runtime = Runtime(frame_threads=2)

    def cancel(stage: str, done: int, total: int) -> None:
        if stage == "label_points" and done == 2:
            raise Cancelled()

    with pytest.raises(Cancelled):
        label(street, schema, PipelineConfig(), tmp_path / "cancelled", runtime=runtime, progress=cancel)
    assert stage_status(run_dir)["label_points"]["status"] == "cancelled"
    written = sorted(p.name for p in (run_dir / "points").iterdir())
    # Frames 0 and 1 reported, frame 2 in flight (it finishes); 3, 4 and 5 never started.
    assert written[:2] == ["000000.npz", "000001.npz"] and 2 <= len(written) <= 3
    assert not list((run_dir / "points").glob(".*.tmp"))
    result = label(street, schema, PipelineConfig(), tmp_path / "cancelled", runtime=runtime)
    assert result.stages["label_points"].frames_computed == 6 - len(written)
    assert _files(run_dir) == _files(runs[1][0])


def test_frame_threads_is_checked() -> None:
    assert Runtime().frame_threads == 4
    for bad in (0, -1, 65, 2.0, True):
        with pytest.raises(ConfigError, match="frame_threads") as exc:
            Runtime(frame_threads=bad)  # type: ignore[arg-type]
        assert exc.value.field == ("frame_threads",)


def test_cli_frame_threads_flag(street: Path, tmp_path: Path) -> None:
    """``leap run --frame-threads``: a bad value is a one-line error naming the flag before any stage runs."""
    out = tmp_path / "bad"
    res = CliRunner().invoke(cli, ["run", str(street), "--out", str(out), "--frame-threads", "0"])
    assert res.exit_code == 2
    assert "--frame-threads must be an integer in 1..64, got 0" in res.output
    assert not out.exists()


def test_ordered_map_keeps_order_runs_concurrently_and_stops_when_closed() -> None:
    lock = threading.Lock()
    running, peak, started = 0, 0, []

    def fn(i: int) -> int:
        nonlocal running, peak
        with lock:
            running += 1
            peak = max(peak, running)
            started.append(i)
        time.sleep(0.02 * (5 - i % 5))  # later items finish first
        with lock:
            running -= 1
        return i * i

    assert list(ordered_map(fn, range(10), 3)) == [i * i for i in range(10)]
    assert peak == 3
    assert list(ordered_map(fn, range(4), 1)) == [0, 1, 4, 9]
    started.clear()
    gen = ordered_map(fn, range(100), 2)
    assert next(gen) == 0
    gen.close()  # the consumer stops: nothing beyond the items already in flight starts
    assert sorted(started) == [0, 1]

    def boom(i: int) -> int:
        if i == 2:
            raise ValueError("frame 2")
        return i

    got = []
    with pytest.raises(ValueError, match="frame 2"):
        got.extend(ordered_map(boom, range(6), 3))
    assert got == [0, 1]
