"""Object-scope corrections (leap_core.pipeline.object_corrections): matching a stored object to a run's
tracks by overlap, the precedence on a scan's points, the file, and a re-run that re-imposes a correction
on the tiny street's mover (tests/test_objects.py's scene)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from runhelpers import label
from test_objects import ONCOMING
from test_pipeline import make_street

from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.errors import DatasetError, LeapError
from leap_core.pipeline.object_corrections import (
    MIN_IOU,
    NO_CLASS,
    CorrectedTracks,
    Match,
    ObjectCorrections,
    ObjectEdit,
    ObjectIdentity,
    match_track,
    match_tracks,
    merge_object_corrections,
)
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.schema import builtin_schema
from leap_core.tracking import TrackingConfig, TrackTable


def _tracks(
    per_frame: dict[str, list[tuple[int, int]]], k: int, moving: tuple[bool, ...] = ()
) -> SequenceTracks:
    """Tracks from ``{frame_id: [(row, track id), ...]}`` with ``k`` tracks voted class 0."""
    ids = tuple(per_frame)
    offsets = np.cumsum([0, *(len(v) for v in per_frame.values())]).astype(np.int64)
    pairs = [p for v in per_frame.values() for p in v]
    table = TrackTable(
        label=np.zeros(k, np.int16),
        velocity=np.zeros((k, 3)),
        moving=np.asarray(moving or (False,) * k, bool),
        scans=np.ones(k, np.int64),
        sweep=np.zeros(k),
        voted=np.ones(k, bool),
    )
    rows = np.asarray([r for r, _ in pairs], np.int32)
    track = np.asarray([t for _, t in pairs], np.int32)
    return SequenceTracks(ids, offsets, rows, track, table)


def test_the_track_of_highest_iou_takes_it_above_one_half() -> None:
    # The docstring's example: the object is rows 1-4 of scan "0"; track 1 holds 1-3, track 2 holds 4, 5.
    stored = _tracks({"0": [(1, 1), (2, 1), (3, 1), (4, 1)]}, 1)
    identity = ObjectIdentity.of_track(stored, 1)
    later = _tracks({"0": [(1, 1), (2, 1), (3, 1), (4, 2), (5, 2)]}, 2)
    m = match_track(identity, later)
    assert (m.track, m.iou, m.applied) == (1, 0.75, True)
    # Split in two halves: IoU 0.5 each is not above MIN_IOU; the correction no longer matches an object.
    halves = _tracks({"0": [(1, 1), (2, 1), (3, 2), (4, 2)]}, 2)
    m = match_track(identity, halves)
    assert m.iou == MIN_IOU and not m.applied
    # No point shared: no track at all (row 2 of scan "0" is not row 2 of scan "1").
    assert match_track(identity, _tracks({"0": [(7, 1)]}, 1)).track == 0
    moved = ObjectIdentity.of_track(_tracks({"0": [(1, 1)], "1": [(2, 1)]}, 1), 1)
    assert match_track(moved, _tracks({"0": [(2, 1)], "1": [(5, 1)]}, 1)) == Match(0, 0.0)
    with pytest.raises(LeapError, match="no track 3"):
        ObjectIdentity.of_track(stored, 3)


def test_only_the_scans_both_runs_labeled_count() -> None:
    # The object was seen in scans "0" and "1" by a run of those two; a later run of scans "1" and "2"
    # sees its scan-"1" part whole (IoU 1 there), whatever the scans the first run never labeled hold.
    stored = _tracks({"0": [(1, 1), (2, 1)], "1": [(3, 1), (4, 1)]}, 1)
    identity = ObjectIdentity.of_track(stored, 1)
    later = _tracks({"1": [(3, 1), (4, 1)], "2": [(5, 1), (6, 1), (7, 1)]}, 1)
    assert match_track(identity, later).iou == 1.0
    first = identity
    # ... but a scan the first run labeled without the object there counts: a track that is somewhere else
    # in that scan is not the same object.
    stored = _tracks({"0": [(1, 1), (2, 1)], "1": [(9, 2)]}, 2)
    identity = ObjectIdentity.of_track(stored, 1)
    later = _tracks({"0": [(1, 1), (2, 1)], "1": [(3, 1), (4, 1), (5, 1)]}, 1)
    assert match_track(identity, later).iou == pytest.approx(2 / 5)
    # Several corrections are matched in one pass, each as alone.
    both = _tracks({"0": [(1, 1), (2, 1)], "1": [(3, 2), (4, 2), (5, 1)], "2": [(6, 2)]}, 2)
    assert match_tracks([first, identity], both) == [match_track(first, both), match_track(identity, both)]
    assert match_tracks([first, identity], both) == [Match(2, 0.5), Match(1, 2 / 3)]


def test_precedence_on_the_points_of_a_scan() -> None:
    # Track 1 (moving) and track 2 (static) in scan "0"; thing classes 1, 2; class 0 is stuff.
    tracks = _tracks({"0": [(0, 1), (1, 1), (2, 1), (3, 2)]}, 2, moving=(True, False))
    things = np.array([False, True, True])
    labels = np.array([0, 1, 1, 1, 0], np.int16)
    conf = np.full(5, 0.5, np.float32)
    same = ObjectIdentity.of_track(tracks, 1)
    other = ObjectIdentity.of_track(tracks, 2)
    # Track 1 → class 2 (a thing: keeps its id and motion); a later correction of track 2 to class 1, then
    # one to stuff class 0 (the later one wins: no id, no motion). Row 2 is a map / scan correction's.
    corr = merge_object_corrections([(7, 2, same), (8, 1, other), (9, 0, other)])
    out = CorrectedTracks.of(tracks, corr, things)
    assert out.track_class.tolist() == [NO_CLASS, 2, 0]
    lab, cf, inst, mov = out.point_objects("0", labels, conf, keep=np.array([2], np.int64))
    assert lab.tolist() == [2, 2, 1, 0, 0]
    assert cf.tolist() == [1, 1, 0.5, 1, 0.5]
    assert inst.tolist() == [1, 1, 0, 0, 0]
    assert mov.tolist() == [True, True, False, False, False]
    # An erase: unlabeled, confidence 0, no id.
    erased = CorrectedTracks.of(tracks, merge_object_corrections([(1, -1, same)]), things)
    lab, cf, inst, _ = erased.point_objects("0", labels, conf)
    assert lab[:3].tolist() == [-1] * 3 and cf[:3].tolist() == [0] * 3 and inst[:3].tolist() == [0] * 3
    assert out.report() == {
        "7": {"track": 1, "iou": 1.0, "applied": True},
        "8": {"track": 2, "iou": 1.0, "applied": True},
        "9": {"track": 2, "iou": 1.0, "applied": True},
    }
    assert out.changed_frames(CorrectedTracks.of(tracks, ObjectCorrections(), things)) == ["0"]


def _car_in_two() -> SequenceTracks:
    """Scans "0".."3": track 1 (static, class 0) holds rows 1-2 in "0", "1"; track 2 (moving, class 0) rows
    3-4 in "1".."3"; track 3 rows 7-8 in "0".."3" (two cars under one id: an id switch at scan "2")."""
    per = {
        "0": [(1, 1), (2, 1), (7, 3), (8, 3)],
        "1": [(1, 1), (2, 1), (3, 2), (4, 2), (7, 3), (8, 3)],
        "2": [(3, 2), (4, 2), (7, 3), (8, 3)],
        "3": [(3, 2), (4, 2), (7, 3), (8, 3)],
    }
    tracks = _tracks(per, 3, moving=(False, True, False))
    table = dataclasses.replace(tracks.table, label=np.array([2, 1, 2], np.int16), voted=tracks.table.moving)
    return dataclasses.replace(tracks, table=table)


def _ids(out: CorrectedTracks, fid: str, n: int = 10) -> list[int]:
    return out.point_objects(fid, np.zeros(n, np.int16))[2].tolist()


def test_merge_gives_one_id_class_and_motion_in_every_scan() -> None:
    tracks = _car_in_two()
    things = np.array([False, True, True])
    one, two = ObjectIdentity.of_track(tracks, 1), ObjectIdentity.of_track(tracks, 2)
    out = CorrectedTracks.of(
        tracks, merge_object_corrections([ObjectEdit(5, "merge", two, other=one)]), things
    )
    for fid in ("0", "1", "2", "3"):
        lab, _, inst, mov = out.point_objects(fid, np.zeros(10, np.int16))
        held = np.flatnonzero(np.isin(np.arange(10), [1, 2, 3, 4]) & (inst > 0))
        # Track 1's points carry track 2's id, its class 1 (the one merged into) and its motion.
        assert set(inst[held].tolist()) == {2} and set(lab[held].tolist()) == {1}, fid
        assert mov[held].all() and (inst[[7, 8]] == 3).all(), fid
    assert out.object_scans(2) == ["0", "1", "2", "3"] and out.object_scans(1) == []
    assert out.report()["5"] == {
        "track": 2,
        "iou": 1.0,
        "applied": True,
        "action": "merge",
        "other_track": 1,
        "other_iou": 1.0,
    }
    assert out.changed_frames(CorrectedTracks.of(tracks, ObjectCorrections(), things)) == ["0", "1"]
    # A later relabel of the merged object (made on its identity then: both parts) relabels both; a relabel
    # made on part 1 alone before the merge is overruled by the merged object's class.
    merged = ObjectIdentity(one.frame_ids, *_union(one, two))
    edits = [(4, 0, one), ObjectEdit(5, "merge", two, other=one), (6, 2, merged)]
    out = CorrectedTracks.of(tracks, merge_object_corrections(edits), things)
    assert out.point_objects("1", np.zeros(10, np.int16))[0][[1, 2, 3, 4]].tolist() == [2] * 4
    assert out.report()["6"]["track"] == 2 and out.report()["6"]["applied"]


def _union(a: ObjectIdentity, b: ObjectIdentity) -> tuple[np.ndarray, np.ndarray]:
    parts = [np.union1d(a.of(f), b.of(f)).astype(np.int32) for f in a.frame_ids]
    return np.cumsum([0, *(p.size for p in parts)]).astype(np.int64), np.concatenate(parts)


def test_split_gives_a_new_unique_id_from_its_scan_on() -> None:
    tracks = _car_in_two()
    things = np.array([False, True, True])
    three = ObjectIdentity.of_track(tracks, 3)
    split = ObjectEdit(9, "split", three, frame_id="2")
    out = CorrectedTracks.of(tracks, merge_object_corrections([split]), things)
    assert [_ids(out, f)[7] for f in ("0", "1", "2", "3")] == [3, 3, 4, 4]  # 4: beyond the run's 1..3
    assert out.count == 4 and out.report()["9"] == {
        "track": 3,
        "iou": 1.0,
        "applied": True,
        "action": "split",
        "new_track": 4,
    }
    assert out.changed_frames(CorrectedTracks.of(tracks, ObjectCorrections(), things)) == ["2", "3"]
    # A second split of the same object at an earlier scan cuts what is left of it: another new id.
    first = ObjectIdentity(three.frame_ids, *_rows_in(three, ("0", "1")))
    again = ObjectEdit(10, "split", first, frame_id="1")
    out = CorrectedTracks.of(tracks, merge_object_corrections([split, again]), things)
    assert [_ids(out, f)[8] for f in ("0", "1", "2", "3")] == [3, 5, 4, 4]
    # A relabel made on the split-off part reaches that part only.
    tail = ObjectIdentity(three.frame_ids, *_rows_in(three, ("2", "3")))
    out = CorrectedTracks.of(tracks, merge_object_corrections([split, (11, 1, tail)]), things)
    assert [out.point_objects(f, np.zeros(10, np.int16))[0][7] for f in ("0", "1", "2", "3")] == [0, 0, 1, 1]


def _rows_in(x: ObjectIdentity, keep: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    parts = [x.of(f) if f in keep else np.zeros(0, np.int32) for f in x.frame_ids]
    return np.cumsum([0, *(p.size for p in parts)]).astype(np.int64), np.concatenate(parts)


def test_merge_and_split_are_rematched_after_a_rerun_and_change_nothing_once_lost() -> None:
    tracks = _car_in_two()
    things = np.array([False, True, True])
    one, two, three = (ObjectIdentity.of_track(tracks, k) for k in (1, 2, 3))
    edits = [ObjectEdit(1, "merge", two, other=one), ObjectEdit(2, "split", three, frame_id="2")]
    # The re-run numbers its tracks otherwise (3 → 1, 1 → 2, 2 → 3) and holds one more point of track 3.
    per = {
        "0": [(1, 2), (2, 2), (7, 1), (8, 1)],
        "1": [(1, 2), (2, 2), (3, 3), (4, 3), (7, 1), (8, 1)],
        "2": [(3, 3), (4, 3), (7, 1), (8, 1), (9, 1)],
        "3": [(3, 3), (4, 3), (7, 1), (8, 1)],
    }
    rerun = _tracks(per, 3, moving=(False, False, True))
    out = CorrectedTracks.of(rerun, merge_object_corrections(edits), things)
    assert out.report()["1"]["track"] == 3 and out.report()["1"]["other_track"] == 2
    assert [_ids(out, "1")[r] for r in (1, 3, 7)] == [3, 3, 1]
    assert [_ids(out, f)[9] for f in ("2",)] == [4] and _ids(out, "3")[7] == 4 and _ids(out, "1")[7] == 1
    # Once the objects are gone (a re-run without track 1's points, one whose split scan is not labeled),
    # the corrections change nothing and say so.
    lost = _tracks({"0": [(7, 1), (8, 1)], "1": [(3, 2), (4, 2), (7, 1), (8, 1)]}, 2)
    out = CorrectedTracks.of(lost, merge_object_corrections(edits), things)
    plain = CorrectedTracks.of(lost, ObjectCorrections(), things)
    assert not out.report()["1"]["applied"] and out.report()["1"]["other_track"] == 0
    assert not out.report()["2"]["applied"] and out.report()["2"]["new_track"] == 0
    assert out.changed_frames(plain) == [] and out.count == 2
    for fid in ("0", "1"):
        assert [x.tolist() for x in out.point_objects(fid, np.zeros(10, np.int16))] == [
            x.tolist() for x in plain.point_objects(fid, np.zeros(10, np.int16))
        ]


def test_the_file_round_trips_and_refuses_bad_classes(tmp_path: Path) -> None:
    tracks = _tracks({"0": [(1, 1), (2, 2)], "1": [], "2": [(5, 1)]}, 2)
    corr = merge_object_corrections(
        [(3, 1, ObjectIdentity.of_track(tracks, 1)), (4, -1, ObjectIdentity.of_track(tracks, 2))]
    )
    path = tmp_path / "corrections_object.npz"
    corr.save(path)
    back = ObjectCorrections.load(path, num_classes=2)
    assert back.ids == (3, 4) and back.class_idx.tolist() == [1, -1]
    assert [i.frame_ids for i in back.identities] == [("0", "1", "2")] * 2
    assert back.identities[0].rows.tolist() == [1, 5] and back.identities[1].rows.tolist() == [2]
    assert not back.differs(corr) and corr.differs(ObjectCorrections())
    one, two = ObjectIdentity.of_track(tracks, 1), ObjectIdentity.of_track(tracks, 2)
    edits = merge_object_corrections(
        [ObjectEdit(5, "merge", one, other=two), (6, 0, two), ObjectEdit(7, "split", one, frame_id="2")]
    )
    edits.save(path)
    back = ObjectCorrections.load(path, num_classes=2)
    assert not back.differs(edits) and back.edits[0].other is not None and back.edits[2].frame_id == "2"
    assert back.edits[0].other.rows.tolist() == [2] and back.class_idx.tolist() == [NO_CLASS, 0, NO_CLASS]
    assert edits.differs(
        merge_object_corrections([*edits.edits[:2], ObjectEdit(7, "split", one, frame_id="1")])
    )
    # A file written before merges and splits existed (no 'action', no 'split_frame') holds relabels.
    corr.save(path)
    with np.load(path) as z:
        np.savez(path, **{k: z[k] for k in z.files if k not in ("action", "split_frame")})
    old = ObjectCorrections.load(path, num_classes=2)
    assert [e.action for e in old.edits] == ["relabel"] * 2 and not old.differs(corr)
    with pytest.raises(DatasetError, match=r"corrections_object.npz.*'class_idx' must be in -1..0"):
        ObjectCorrections.load(path, num_classes=1)
    empty = tmp_path / "none.npz"
    ObjectCorrections().save(empty)
    assert len(ObjectCorrections.load(empty, 2)) == 0


def test_a_rerun_reimposes_the_correction_on_the_mover(tmp_path: Path) -> None:
    root = make_street(tmp_path / "sequences" / "00", movers=(ONCOMING,))
    schema = builtin_schema("semantickitti")
    folder = label(root, schema, PipelineConfig(), tmp_path / "run").folder
    seq = KittiSequence(root)
    tracks = SequenceTracks.load(folder / "tracks.npz")
    mover = int(np.flatnonzero(tracks.table.moving)[0]) + 1
    before = {f: read_label(folder / "export" / f"{f}.label") for f in seq.frame_ids}
    stamp = (folder / "tracks.npz").stat().st_mtime_ns
    truck = schema.index("truck")
    # The correction is kept as the mover's point rows; a correction of rows no track holds comes with it.
    ghost = ObjectIdentity(tuple(seq.frame_ids), np.zeros(len(seq) + 1, np.int64), np.zeros(0, np.int32))
    merge_object_corrections([(1, truck, ObjectIdentity.of_track(tracks, mover)), (2, -1, ghost)]).save(
        folder / "corrections_object.npz"
    )
    label(root, schema, PipelineConfig(), tmp_path / "run")
    assert (folder / "tracks.npz").stat().st_mtime_ns == stamp  # neither fusion nor tracks reran
    matches = json.loads((folder / "object_matches.json").read_text())
    assert matches == {
        "1": {"track": mover, "iou": 1.0, "applied": True},
        "2": {"track": 0, "iou": 0.0, "applied": False},
    }
    moving_truck = schema.moving_export_ids()[truck]
    changed = 0
    for fid in seq.frame_ids:
        after = read_label(folder / "export" / f"{fid}.label")
        obj = tracks.scan(fid)
        mine = obj.rows[obj.track == mover]
        assert (after[mine] & 0xFFFF == moving_truck).all() and (after[mine] >> 16 == mover).all(), fid
        rest = np.setdiff1d(np.arange(after.size), mine)
        assert (after[rest] == before[fid][rest]).all(), fid
        changed += mine.size
    assert changed > 50
    # Without the correction the next run writes the export it wrote before, and a report of nothing.
    (folder / "corrections_object.npz").unlink()
    label(root, schema, PipelineConfig(), tmp_path / "run")
    assert json.loads((folder / "object_matches.json").read_text()) == {}
    for fid in seq.frame_ids:
        assert (read_label(folder / "export" / f"{fid}.label") == before[fid]).all(), fid
    # A run without objects keeps no report of an export it did not write.
    untracked = dataclasses.replace(PipelineConfig(), tracking=TrackingConfig(enabled=False))
    label(root, schema, untracked, tmp_path / "run")
    assert not (folder / "object_matches.json").exists()
