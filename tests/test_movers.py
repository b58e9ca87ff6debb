"""A planted mover is kept out of the map: a van driving 1.5 m per scan through the tiny ray-cast street
(tests/test_pipeline.py), labeled by the simulated labeler with every noise knob off, is found by the
``motion`` stage before the fusion; the voxels it passed through do not carry its class, and its points
carry one moving id through every scan (docs/METHOD.md B.6)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from runhelpers import label
from scipy.spatial import cKDTree
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.fusion import VoxelGrid, voxel_keys, world_points
from leap_core.io_utils import read_npz
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.pipeline.context import load_observation
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.schema import builtin_schema
from leap_core.tracking import euclidean_segments, segment_summary, track_ids, track_table

MOVING_CAR = 252
DRIVER = ((24.0, 28.0, -0.8, 0.4, 0.0, 2.0, MOVING_CAR, 9), (-15.0, 0.0))
"""A van (2 m tall: its roof stays out of sight) on the road's middle line driving towards the sensor at
15 m/s, 1.5 m per scan (no parked car hides any of it)."""


def _config(exclude: bool) -> PipelineConfig:
    cfg = config_from_dict({"tracking": {"exclude_moving": exclude}}, PipelineConfig())
    return cfg.with_labeler_config(SimulatedLabelerConfig.exact())


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> KittiSequence:
    return KittiSequence(
        make_street(tmp_path_factory.mktemp("driver") / "sequences" / "00", movers=(DRIVER,))
    )


def _run(seq: KittiSequence, out: Path, exclude: bool) -> Path:
    label(seq.root, builtin_schema("semantickitti"), _config(exclude), out)
    return out / "sequences" / "00"


def _trail(seq: KittiSequence) -> np.ndarray:
    """(M, 3) the mover's points in world coordinates, over every scan."""
    pts = []
    for i in range(len(seq)):
        f = seq.frame(i)
        pts.append(world_points(f.points[(f.labels & 0xFFFF) == MOVING_CAR], f.pose))
    return np.concatenate(pts)


def _static_there(seq: KittiSequence, folder: Path, trail: np.ndarray, reach: float) -> np.ndarray:
    """Final labels of the static points within ``reach`` of where the mover was in some scan."""
    tree = cKDTree(trail)
    out = []
    for i, fid in enumerate(seq.frame_ids):
        f = seq.frame(i)
        near = np.isfinite(tree.query(world_points(f.points, f.pose), distance_upper_bound=reach)[0])
        where = near & ((f.labels & 0xFFFF) != MOVING_CAR)
        out.append(read_npz(folder / "points" / f"{fid}.npz", ("label",))["label"][where])
    return np.concatenate(out)


def _car_voxels(folder: Path, trail: np.ndarray) -> int:
    grid = VoxelGrid.load(folder / "grid.npz")
    rows = grid.lookup(trail)
    car = builtin_schema("semantickitti").index("car")
    return int((grid.logp[rows[rows >= 0]].argmax(axis=1) == car).sum())


@pytest.fixture(scope="module")
def kept_out(street: KittiSequence, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run with ``exclude_moving``: its sequence folder."""
    return _run(street, tmp_path_factory.mktemp("runs") / "out", exclude=True)


def test_the_mover_is_not_fused_and_keeps_one_moving_id(street: KittiSequence, kept_out: Path) -> None:
    seq, folder = street, kept_out
    vs = PipelineConfig().fusion.voxel_size
    trail = _trail(seq)
    # (a) Not one voxel the mover passed through reads car, and no static point there is labeled car.
    assert _car_voxels(folder, np.unique(voxel_keys(trail, vs))) == 0
    there = _static_there(seq, folder, trail, 2 * vs)
    assert there.size > 20 and not (there == builtin_schema("semantickitti").index("car")).any()
    # (b) One non-zero id on the mover's points in every scan, the same, with the moving id.
    per_scan = []
    for i, fid in enumerate(seq.frame_ids):
        mover = (seq.frame(i).labels & 0xFFFF) == MOVING_CAR
        out = read_label(folder / "export" / f"{fid}.label")[mover]
        per_scan.append(out)
        assert len(set(np.unique(out >> 16).tolist()) - {0}) == 1, fid
    out = np.concatenate(per_scan)
    track = int(np.bincount(out >> 16).argmax())
    assert track > 0 and ((out >> 16) == track).mean() > 0.9
    assert set(np.unique(out[(out >> 16) == track] & 0xFFFF).tolist()) == {MOVING_CAR}
    motion = SequenceTracks.load(folder / "motion.npz")
    tracks = SequenceTracks.load(folder / "tracks.npz")
    assert track <= motion.table.label.size and tracks.table.moving[track - 1]
    assert tracks.table.velocity[track - 1][0] == pytest.approx(-15, abs=1.5)
    # Static points with the mover's id: at most the few road points its 2D mask covers at its edge.
    static_ids = [
        read_label(folder / "export" / f"{fid}.label")[(seq.frame(i).labels & 0xFFFF) != MOVING_CAR] >> 16
        for i, fid in enumerate(seq.frame_ids)
    ]
    assert (np.concatenate(static_ids) == track).sum() <= 0.05 * out.size


def test_fused_without_the_switch_the_trail_reads_car(
    street: KittiSequence, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """The scene does smear when movers are fused (``exclude_moving: false``): the check above can fail."""
    folder = _run(street, tmp_path_factory.mktemp("runs") / "fused", exclude=False)
    vs = PipelineConfig().fusion.voxel_size
    trail = _trail(street)
    assert _car_voxels(folder, np.unique(voxel_keys(trail, vs))) > 50
    assert not (folder / "motion.npz").exists()


def test_reruns_follow_the_switch_and_not_the_vote(
    street: KittiSequence, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """The motion stage sits before the fusion in the fingerprints: switching ``exclude_moving`` on fuses
    again; another ``vote`` with it on redoes only the tracks and what follows, another ``segments`` the
    motion stage too; switching it off again fuses every point once more."""
    out = tmp_path_factory.mktemp("runs") / "resume"
    schema = builtin_schema("semantickitti")
    first = label(street.root, schema, _config(False), out)
    assert "motion" not in first.ran and "fuse" in first.ran
    on = label(street.root, schema, _config(True), out)
    assert on.ran == ["motion", "fuse", "smooth", "label_points", "tracks", "evaluate", "export"]
    voted = config_from_dict({"tracking": {"vote": "all"}}, _config(True))
    assert label(street.root, schema, voted, out).ran == ["tracks", "evaluate", "export"]
    # The motion stage segments too: another tracking.segments finds its movers again.
    masks = config_from_dict({"tracking": {"segments": "masks"}}, _config(True))
    assert label(street.root, schema, masks, out).ran[0] == "motion"
    off = label(street.root, schema, _config(False), out)
    assert off.ran == ["fuse", "smooth", "label_points", "tracks", "evaluate", "export"]
    assert not (out / "sequences" / "00" / "motion.npz").exists()


def test_motion_file_is_the_tracking_maths_on_the_projected_labels(
    street: KittiSequence, kept_out: Path
) -> None:
    """``motion.npz`` equals the pure functions of leap_core.tracking applied to the run's stored
    observations: the thing points of each scan's projected labels, their segments, tracks and motion."""
    schema = builtin_schema("semantickitti")
    cfg = _config(True).tracking
    things = schema.things()
    per_scan = []
    for i, fid in enumerate(street.frame_ids):
        painted, n, _ = load_observation(kept_out / "observations" / f"{fid}.npz")
        point_label = painted.point_labels(n)
        rows = np.flatnonzero(things[np.maximum(point_label, 0)] & (point_label >= 0))
        f = street.frame(i)
        xyz = world_points(f.points[rows], f.pose)
        seg = euclidean_segments(xyz, cfg.cluster_radius, cfg.min_segment_points)
        votes = np.eye(things.size)[point_label[rows]]
        per_scan.append((rows, seg, *segment_summary(xyz, seg, votes, things.size)))
    times = np.arange(len(street)) * 0.1
    ids = track_ids([s[2] for s in per_scan], times, cfg)
    table = track_table(
        ids, [s[2] for s in per_scan], [s[3] for s in per_scan], [s[4] for s in per_scan], times, cfg
    )
    motion = SequenceTracks.load(kept_out / "motion.npz")
    assert np.array_equal(motion.table.label, table.label[table.moving])
    new_id = np.cumsum(table.moving) * table.moving
    for t, fid in enumerate(street.frame_ids):
        rows, seg = per_scan[t][0], per_scan[t][1]
        track = new_id[ids[t][seg[seg >= 0]] - 1]
        obj = motion.scan(fid)
        assert np.array_equal(obj.rows, rows[seg >= 0][track > 0]), fid
        assert np.array_equal(obj.track, track[track > 0]), fid


@pytest.mark.slow
def test_a_3dcn_round_puts_no_mover_back_into_the_map(street: KittiSequence, tmp_path: Path) -> None:
    """With the 3D-CN on, the round fuses back no prediction of the movers' points: the voxels only the
    mover filled stay out of its grid as they are out of the fused one."""
    small = {
        "enabled": True,
        "iterations": 1,
        "device": "cpu",
        "num_threads": 1,
        "min_steps": 2,
        "new_voxel_margin": 0,
    }
    cfg = config_from_dict(
        {"consistency": {**small, "points_per_scan": 500, "backbone": {"channels": 16, "layers": 1}}},
        _config(True),
    )
    folder = label(street.root, builtin_schema("semantickitti"), cfg, tmp_path / "cn").folder
    trail = np.unique(voxel_keys(_trail(street), cfg.fusion.voxel_size))
    fused, cn = (VoxelGrid.load(folder / name) for name in ("grid.npz", "grid_3dcn1.npz"))
    assert cn.num_voxels > fused.num_voxels  # the network adds voxels, elsewhere
    new = np.isin(trail, cn.keys) & ~np.isin(trail, fused.keys)
    print("new trail voxels", int(new.sum()), "of", trail.size)
    # Only where a mover's point escaped its track (a point outside its segment) does the round add one.
    assert new.sum() <= 0.1 * trail.size
