"""Objects on the demo street: what the ``motion`` and ``tracks`` stages change, against the same run without
them.

Runs the pipeline on one sequence in one run folder: first with ``tracking.enabled: false`` (the baseline:
the labels of a run without objects), then with it on and ``tracking.vote: all`` (every track's points
take its voted class), then ``tracking.vote: moving`` (only moving tracks' points do), both with
``tracking.exclude_moving: false`` (every point fused: only ``tracks``, ``evaluate`` and ``export`` run
again), then ``vote: moving`` with ``exclude_moving: true`` (the ``motion`` stage finds movers before the
fusion, which leaves them out, so the fusion and what follows run again). ``--segments euclidean,masks``
does the three objects runs once per ``tracking.segments`` setting. Prints, for each (docs/RESULTS.md
"Objects"):

- moving-person points with the right class: ground-truth raw id 254 points whose exported class is person
  (all points);
- MOS IoU (moving points, all points; evaluate_mos.py's definition), camera-view and all-points PQ of
  things, S_assoc (LSTQ), from the run's ``metrics.json``;
- stuff mIoU before / after (all points and camera view: the mean IoU of the stuff classes), mIoU and
  each thing class's IoU in camera view;
- the smear: the share of static points in voxels a moving object passed through (any scan) whose final
  label is a thing class;
- the motion and tracks stages' time per scan beside ``label_points``' (same run, same frames);
- the object review queue (docs/METHOD.md B.6, default ``ObjectQueueConfig``): objects queued for a close
  vote / a broken track / a short track, and the share of objects whose voted class differs from the
  ground-truth class most of their points carry, among the queued ones against the rest (does the queue
  find the wrong ones?).

Usage::

    .venv/bin/leap synth /tmp/demo
    .venv/bin/python benchmarks/bench_objects.py --sequence /tmp/demo/sequences/00
    .venv/bin/python benchmarks/bench_objects.py --quick     # a generated 3-frame street
    .venv/bin/python benchmarks/bench_objects.py --segments euclidean,masks   # both segmentations
    .venv/bin/python benchmarks/bench_objects.py --preset paper   # the lab's labeler fitted to the paper

``--preset paper`` labels with the research lab's ``simulated-paper`` labeler and its ``paper`` preset (the
noise fitted to the paper's point row, ``lab/paper_labeler.py``) instead of the product's simulated labeler
with its defaults (``default``).

Writes ``benchmarks/results/bench_objects.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from common import print_table, write_results

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.fusion import voxel_keys, world_points
from leap_core.io_utils import read_npz
from leap_core.object_review import BROKEN, CLOSE_VOTE, SHORT, ObjectQueueConfig
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.pipeline.metrics_file import SequenceMetrics
from leap_core.pipeline.tracks_file import SequenceTracks
from leap_core.schema import Schema, builtin_schema
from leap_core.synth import SynthConfig, generate_sequence

MOVING_PERSON = 254


def moving_right_share(seq: KittiSequence, export: Path, schema: Schema, raw_id: int) -> float:
    """Share of the points whose ground truth is ``raw_id`` exported with that id's class."""
    lut = np.full(0x10000, -1, np.int64)
    for k, c in enumerate(schema.classes):
        lut[c.export_id] = k
        if c.moving_id is not None:
            lut[c.moving_id] = k
    want = int(schema.gt_lut()[raw_id])
    right = total = 0
    for i, fid in enumerate(seq.frame_ids):
        gt = seq.frame(i).labels & 0xFFFF
        pred = lut[read_label(export / f"{fid}.label") & 0xFFFF]
        sel = gt == raw_id
        total += int(sel.sum())
        right += int((pred[sel] == want).sum())
    return right / total if total else math.nan


def trail_smear(seq: KittiSequence, folder: Path, schema: Schema, voxel_size: float) -> float:
    """Share of the static points in voxels a moving object passed through (ground truth: a SemanticKITTI
    moving id, any scan) whose final label (``points/``, the map's word) is a thing class: the smear."""
    moving = np.array([c.moving_id for c in schema.classes if c.moving_id is not None])
    trail = []
    for i in range(len(seq)):
        f = seq.frame(i)
        sel = np.isin(f.labels & 0xFFFF, moving)
        trail.append(voxel_keys(world_points(f.points[sel], f.pose), voxel_size))
    keys = np.unique(np.concatenate(trail))
    lut = np.concatenate([schema.things(), [False]])
    thing = total = 0
    for i, fid in enumerate(seq.frame_ids):
        f = seq.frame(i)
        static = ~np.isin(f.labels & 0xFFFF, moving)
        there = static & np.isin(voxel_keys(world_points(f.points, f.pose), voxel_size), keys)
        lab = read_npz(folder / "points" / f"{fid}.npz", ("label",))["label"][there]
        total += int(there.sum())
        thing += int(lut[lab].sum())
    return thing / total if total else math.nan


def queue_quality(seq: KittiSequence, folder: Path, schema: Schema) -> dict[str, Any]:
    """The object review queue of the run's ``tracks.npz``: counts per reason, and the share of objects
    whose voted class is not the ground-truth class most of their tracked points carry (points without
    ground truth not counted), among the queued and the other thing objects with points."""
    tracks = SequenceTracks.load(folder / "tracks.npz")
    k = tracks.table.label.size
    gt_lut = schema.gt_lut()
    c = schema.num_classes
    hist = np.zeros((k, c + 1), np.int64)
    for i, fid in enumerate(seq.frame_ids):
        obj = tracks.scan(fid)
        if not obj.rows.size:
            continue
        gt = gt_lut[seq.frame(i).labels[obj.rows] & 0xFFFF]
        np.add.at(hist, (obj.track.astype(np.int64) - 1, np.where(gt >= 0, gt, c)), 1)
    known = hist[:, :c].sum(axis=1) > 0
    wrong = known & (hist[:, :c].argmax(axis=1) != tracks.table.label)
    ids, reasons = tracks.review_queue(schema.things(), ObjectQueueConfig())
    queued = np.zeros(k, bool)
    queued[ids - 1] = True
    life = tracks.track_life()
    rest = ~queued & (life.present > 0) & schema.things()[tracks.table.label] & known

    def share(sel: np.ndarray) -> float:
        n = int((sel & known).sum())
        return float((sel & wrong).sum() / n) if n else math.nan

    return {
        "objects": int(((life.present > 0) & schema.things()[tracks.table.label]).sum()),
        "queued": int(ids.size),
        "close_vote": int(((reasons & CLOSE_VOTE) > 0).sum()),
        "broken": int(((reasons & BROKEN) > 0).sum()),
        "short": int(((reasons & SHORT) > 0).sum()),
        "wrong_queued": share(queued),
        "wrong_close_vote": share(np.isin(np.arange(1, k + 1), ids[(reasons & CLOSE_VOTE) > 0])),
        "wrong_rest": share(rest),
    }


def stuff_miou(m: SequenceMetrics, protocol: str, row: str, schema: Schema) -> float:
    iou = m.table(protocol)[row].iou
    vals = [iou[c.name] for c in schema.classes if not c.thing and iou[c.name] is not None]
    return float(np.mean(vals)) if vals else math.nan


def pct(x: float | None) -> str:
    return "-" if x is None or math.isnan(x) else f"{100 * x:.1f}"


def ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequence", default="/tmp/demo/sequences/00", help="KITTI-layout sequence folder.")
    ap.add_argument("--quick", action="store_true", help="A generated 3-frame street instead.")
    ap.add_argument("--work", default=None, help="Folder for the run (default: a temp folder).")
    ap.add_argument(
        "--tracking",
        default="{}",
        help="JSON of further tracking settings for every run (e.g. '{\"moving_distance\": 2}').",
    )
    ap.add_argument(
        "--segments",
        default="euclidean",
        help="Comma-separated tracking.segments settings to run each objects run with (e.g. "
        "'euclidean,masks': every objects run once per setting, the column names say which).",
    )
    ap.add_argument(
        "--preset",
        choices=("default", "paper"),
        default="default",
        help="Simulated labels: the product's simulated labeler (default) or the lab's simulated-paper "
        "labeler with its paper preset.",
    )
    args = ap.parse_args()
    labeler: dict[str, Any] = {}
    if args.preset == "paper":
        import lab  # noqa: F401  registers the simulated-paper labeler

        labeler = {"labeler": "simulated-paper", "simulated_paper": {"preset": "paper"}}

    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_objects_"))
    if args.quick:
        seq_dir = generate_sequence(work / "data", SynthConfig(frames=3)).path
    else:
        seq_dir = Path(args.sequence)
        if not (seq_dir / "velodyne").is_dir():
            sys.exit(f"{seq_dir}: not a sequence folder; generate the demo first: leap synth /tmp/demo")
    seq = KittiSequence(seq_dir)
    schema = builtin_schema("semantickitti")
    out = work / "run"
    results: dict[str, Any] = {}
    extra = json.loads(args.tracking)
    settings = [x.strip() for x in args.segments.split(",") if x.strip()]
    runs = [("without objects", False, "moving", False, settings[0])]
    for seg in settings:
        tag = f" ({seg})" if len(settings) > 1 else ""
        runs += [
            (f"vote all{tag}", True, "all", False, seg),
            (f"vote moving{tag}", True, "moving", False, seg),
            (f"movers kept out{tag}", True, "moving", True, seg),
        ]
    for name, enabled, vote, exclude, seg in runs:
        cfg = config_from_dict(
            {
                **labeler,
                "tracking": {
                    **extra,
                    "enabled": enabled,
                    "vote": vote,
                    "exclude_moving": exclude,
                    "segments": seg,
                },
            },
            PipelineConfig(),
        )
        res = run_pipeline([SequenceSpec.of(seq_dir)], schema, cfg, out).only()
        assert res.metrics is not None, "the sequence has no ground truth"
        row = "objects" if enabled else "voxel"
        lay = res.layout if hasattr(res, "layout") else None
        state = json.loads(
            ((lay.folder if lay else out / "sequences" / seq_dir.name) / "stages.json").read_text()
        )
        obj = res.metrics.objects or {}
        results[name] = {
            "moving_person_right_class": moving_right_share(
                seq,
                (lay.folder if lay else out / "sequences" / seq_dir.name) / "export",
                schema,
                MOVING_PERSON,
            ),
            "trail_smear": trail_smear(
                seq, (lay.folder if lay else out / "sequences" / seq_dir.name), schema, cfg.fusion.voxel_size
            ),
            "mos_iou": obj.get("motion", {}).get("mos_iou"),
            "pq_things_camera": obj.get("camera", {}).get("PQ_things"),
            "pq_things_all": obj.get("all", {}).get("PQ_things"),
            "pq_camera": obj.get("camera", {}).get("PQ"),
            "s_assoc": obj.get("motion", {}).get("s_assoc"),
            "stuff_miou_all": stuff_miou(res.metrics, "all", row, schema),
            "stuff_miou_camera": stuff_miou(res.metrics, "camera", row, schema),
            "miou_all": res.metrics.miou("all", row),
            "miou_camera": res.metrics.miou("camera", row),
            "things_camera": {
                c.name: res.metrics.table("camera")[row].iou[c.name] for c in schema.classes if c.thing
            },
            "tracks_ms_per_scan": 1000 * state["tracks"].get("seconds", 0.0) / len(seq) if enabled else None,
            "motion_ms_per_scan": 1000 * state["motion"].get("seconds", 0.0) / len(seq) if exclude else None,
            "fuse_ms_per_scan": 1000 * state["fuse"]["seconds"] / len(seq),
            "moving_before_fusion": state["tracks"].get("moving_before_fusion"),
            "label_points_ms_per_scan": 1000 * state["label_points"]["seconds"] / len(seq),
            "tracks": state["tracks"].get("tracks"),
            "moving_tracks": state["tracks"].get("moving_tracks"),
            "queue": queue_quality(seq, lay.folder if lay else out / "sequences" / seq_dir.name, schema)
            if enabled
            else None,
        }
    keys = [
        ("moving-person points, right class %", "moving_person_right_class"),
        ("MOS IoU % (all points)", "mos_iou"),
        ("static points in movers' voxels labeled a thing %", "trail_smear"),
        ("PQ things % (camera view)", "pq_things_camera"),
        ("PQ things % (all points)", "pq_things_all"),
        ("PQ % (camera view)", "pq_camera"),
        ("S_assoc %", "s_assoc"),
        ("stuff mIoU % (all points)", "stuff_miou_all"),
        ("stuff mIoU % (camera view)", "stuff_miou_camera"),
        ("mIoU % (all points)", "miou_all"),
        ("mIoU % (camera view)", "miou_camera"),
    ]
    rows = [[label, *(pct(results[n][k]) for n in results)] for label, k in keys]
    things = [c.name for c in schema.classes if c.thing]
    rows += [
        [f"IoU % {t} (camera view)", *(pct(results[n]["things_camera"][t]) for n in results)] for t in things
    ]

    def each(fmt: Any) -> list[str]:
        return [fmt(results[n]) for n in results]

    rows.append(
        [
            "tracks / moving tracks",
            *each(lambda r: "-" if r["tracks"] is None else f"{r['tracks']} / {r['moving_tracks']}"),
        ]
    )
    rows.append(
        [
            "review queue: queued / objects (close vote, broken, short)",
            *each(
                lambda r: (
                    "-"
                    if r["queue"] is None
                    else "{queued} / {objects} ({close_vote}, {broken}, {short})".format(**r["queue"])
                )
            ),
        ]
    )
    rows.append(
        [
            "objects of the wrong class %: queued / close vote / rest",
            *each(
                lambda r: (
                    "-"
                    if r["queue"] is None
                    else " / ".join(
                        pct(r["queue"][k]) for k in ("wrong_queued", "wrong_close_vote", "wrong_rest")
                    )
                )
            ),
        ]
    )
    rows.append(["movers found before fusion", *each(lambda r: str(r["moving_before_fusion"] or "-"))])
    rows.append(["motion stage ms/scan", *each(lambda r: ms(r["motion_ms_per_scan"]))])
    rows.append(["tracks stage ms/scan", *each(lambda r: ms(r["tracks_ms_per_scan"]))])
    rows.append(["fuse ms/scan", *each(lambda r: ms(r["fuse_ms_per_scan"]))])
    rows.append(["label_points ms/scan (baseline)", *each(lambda r: ms(r["label_points_ms_per_scan"]))])
    print_table(f"Objects on {seq_dir} ({len(seq)} frames, {args.preset} preset)", ["", *results], rows)
    write_results(
        "bench_objects" if args.preset == "default" else f"bench_objects_{args.preset}",
        {"sequence": str(seq_dir), "frames": len(seq), "preset": args.preset, "results": results},
    )


if __name__ == "__main__":
    main()
