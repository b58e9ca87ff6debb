"""Objects end to end: a car planted to drive through the tiny ray-cast street (tests/test_pipeline.py) is
tracked with one id, exported with its moving id, and nothing static takes a moving id."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from runhelpers import label
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.pipeline.context import Ctx
from leap_core.pipeline.objects import scan_instances
from leap_core.pipeline.stages import STAGE_TABLE
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.run_layout import SequenceLayout
from leap_core.schema import builtin_schema

pytestmark = pytest.mark.slow

MOVING_CAR, CAR = 252, 10
ONCOMING = ((22.0, 26.0, -3.6, -1.8, 0.0, 1.5, MOVING_CAR, 9), (-6.0, 0.0))
"""A car in the street's right lane driving towards the sensor at 6 m/s (the street's parked cars stay)."""


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[KittiSequence, Path]:
    tmp = tmp_path_factory.mktemp("mover")
    root = make_street(tmp / "sequences" / "00", movers=(ONCOMING,))
    label(root, builtin_schema("semantickitti"), PipelineConfig(), tmp / "run")
    return KittiSequence(root), tmp / "run" / "sequences" / "00"


def _exported(seq: KittiSequence, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    gt = np.concatenate([seq.frame(i).labels for i in range(len(seq))])
    out = np.concatenate([read_label(folder / "export" / f"{fid}.label") for fid in seq.frame_ids])
    return gt, out


def test_the_mover_keeps_one_id_and_its_moving_id(run: tuple[KittiSequence, Path]) -> None:
    seq, folder = run
    gt, out = _exported(seq, folder)
    mover = (gt & 0xFFFF) == MOVING_CAR
    ids, counts = np.unique(out[mover] >> 16, return_counts=True)
    counts[ids == 0] = 0
    main = ids[counts.argmax()]
    assert main > 0 and counts.max() >= 0.6 * mover.sum()
    # Every point of its track, in every scan, says "moving car": none carries the static car id.
    assert set(np.unique(out[(out >> 16) == main] & 0xFFFF).tolist()) == {MOVING_CAR}
    tracks = SequenceTracks.load(folder / "tracks.npz")
    assert tracks.table.moving[main - 1] and tracks.table.velocity[main - 1][0] == pytest.approx(-6, abs=1)


def test_nothing_static_is_moving(run: tuple[KittiSequence, Path]) -> None:
    seq, folder = run
    gt, out = _exported(seq, folder)
    static = (gt & 0xFFFF) != MOVING_CAR
    moving_ids = np.isin(out & 0xFFFF, (MOVING_CAR, 253, 254, 255, 258, 259))
    # At most the few road points the mover's segment touches (its wheels): a parked car's partial views
    # (a few points of its front, then all of it) are no motion.
    assert (moving_ids & static).sum() <= 0.05 * (~static).sum()
    # The parked cars are objects too: tracked, with ids, static.
    parked = (gt & 0xFFFF) == CAR
    assert ((out[parked] >> 16) > 0).mean() > 0.8


def test_mask_segments_follow_the_2d_instances_and_rerun_only_the_objects(
    run: tuple[KittiSequence, Path], tmp_path: Path
) -> None:
    seq, folder = run
    out = tmp_path / "run"
    shutil.copytree(folder.parents[1], out)
    cfg = config_from_dict({"tracking": {"segments": "masks"}}, PipelineConfig())
    schema = builtin_schema("semantickitti")
    res = label(seq.root, schema, cfg, out)
    assert res.ran == ["tracks", "evaluate", "export"]
    ctx = Ctx(
        seq,
        schema,
        cfg,
        SequenceLayout(res.folder),
        range(len(seq)),
        None,
        None,
        {s.name: s for s in STAGE_TABLE},
    )
    tracks = SequenceTracks.load(res.folder / "tracks.npz")
    covered = right = 0
    for i, fid in enumerate(seq.frame_ids):
        ins = scan_instances(ctx, i)
        obj = tracks.scan(fid)
        # A mask's tracked points share one track, and two masks never share one.
        pairs = np.unique(np.c_[ins[obj.rows], obj.track][ins[obj.rows] > 0], axis=0)
        assert np.unique(pairs[:, 0]).size == np.unique(pairs[:, 1]).size == len(pairs)
        gt = seq.frame(i).labels >> 16
        assert ins.shape == gt.shape
        # Each 2D instance's points are mostly one object of the ground truth (a mask's edge bleeds onto
        # the road: the simulated labeler's noise and the depth clustering's edges).
        for k in np.unique(ins[ins > 0]):
            ids, counts = np.unique(gt[ins == k], return_counts=True)
            assert ids[counts.argmax()] > 0
            covered += int(counts.sum())
            right += int(counts.max())
    assert covered > 0 and right >= 0.9 * covered
    gt, exported = _exported(seq, res.folder)
    mover = (gt & 0xFFFF) == MOVING_CAR
    ids, counts = np.unique(exported[mover] >> 16, return_counts=True)
    counts[ids == 0] = 0
    assert ids[counts.argmax()] > 0 and counts.max() >= 0.6 * mover.sum()


def test_every_track_id_has_points(run: tuple[KittiSequence, Path]) -> None:
    # A static track whose points the map all calls stuff keeps no id: ids 1..K, each on some point.
    tracks = SequenceTracks.load(run[1] / "tracks.npz")
    assert tracks.track_life().present.min() > 0
    assert np.unique(tracks.track).tolist() == list(range(1, tracks.table.label.size + 1))
