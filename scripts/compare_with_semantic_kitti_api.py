#!/usr/bin/env python3
"""Check the ``.label`` files a ``leap run`` exported with semantic-kitti-api's ``evaluate_semantics.py``
(and, with ``--objects``, its ``evaluate_panoptic.py`` and ``evaluate_mos.py``).

Runs the external evaluator (an unmodified checkout, given by path; nothing of it is copied here) on the
run's ``export/`` folder against the sequence's ground truth, then prints its per-class IoU beside LeAP's
all-points figures from ``metrics.json`` and the largest absolute difference. Exit status 1 when that
difference exceeds ``--tol`` (default 0.001).

Usage::

    git clone https://github.com/PRBonn/semantic-kitti-api /tmp/ska
    .venv/bin/leap run /tmp/demo/sequences/00 --schema semantickitti --labeler simulated --out /tmp/eval_run
    .venv/bin/python scripts/compare_with_semantic_kitti_api.py \
        --evaluator /tmp/ska --sequence /tmp/demo/sequences/00 --run /tmp/eval_run

The evaluator only looks at the sequences of a config split (``valid`` = [8] in its stock config), so the
sequence and the predictions are linked into a temporary tree under that split's first sequence number;
this keeps its config untouched. Only the frames LeAP evaluated (``metrics.json`` "frames") are linked,
because the evaluator asserts equal label and prediction counts. The evaluator is asked for its
``--codalab`` scores file so the comparison uses full-precision values, not its 3-decimal printout.

``--objects``: on the same tree, ``evaluate_panoptic.py`` (its ``--output`` scores: PQ / SQ / RQ over all
classes, things and stuff) against ``metrics.json``'s ``objects.all``, and ``evaluate_mos.py`` with its
``config/semantic-kitti-mos.yaml`` (``iou_moving``) against ``objects.motion.mos_iou``; the same tolerance.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--evaluator", required=True, type=Path, help="semantic-kitti-api checkout folder")
    ap.add_argument(
        "--sequence",
        required=True,
        type=Path,
        help="ground-truth sequence folder (.../sequences/NN, with labels/)",
    )
    ap.add_argument("--run", required=True, type=Path, help="leap run folder (metrics.json, export/)")
    ap.add_argument(
        "--row",
        default=None,
        help="metrics.json row to compare (default: the final one, i.e. the labels the export stage wrote)",
    )
    ap.add_argument(
        "--datacfg",
        type=Path,
        default=None,
        help="evaluator data config (default: <evaluator>/config/semantic-kitti.yaml)",
    )
    ap.add_argument("--split", default="valid", choices=["train", "valid", "test"])
    ap.add_argument("--python", default=sys.executable, help="interpreter for the evaluator")
    ap.add_argument("--tol", type=float, default=1e-3, help="largest allowed |IoU difference|")
    ap.add_argument(
        "--objects",
        action="store_true",
        help="also compare PQ (evaluate_panoptic.py) and the moving IoU (evaluate_mos.py)",
    )
    return ap.parse_args(argv)


def _link_tree(root: Path, seq_name: str, gt_labels: list[Path], preds: list[Path]) -> None:
    """Evaluator layout: root/dataset/sequences/<seq>/labels, root/predictions/sequences/<seq>/predictions."""
    lab_dir = root / "dataset" / "sequences" / seq_name / "labels"
    pred_dir = root / "predictions" / "sequences" / seq_name / "predictions"
    lab_dir.mkdir(parents=True)
    pred_dir.mkdir(parents=True)
    for src in gt_labels:
        (lab_dir / src.name).symlink_to(src.resolve())
    for src in preds:
        (pred_dir / src.name).symlink_to(src.resolve())


def _run_evaluator(  # the evaluator, its config and the files it reads
    args: argparse.Namespace,
    script: Path,
    datacfg: Path,
    seq_name: str,
    gt_files: list[Path],
    pred_files: list[Path],
    *,
    cfg_flag: str = "--datacfg",
    scores_flag: str = "--codalab",
) -> tuple[dict[str, Any], str, str]:
    """Run one of the evaluators (``evaluate_semantics.py`` by default) on a temporary tree of links to the
    label and prediction files; ``cfg_flag`` / ``scores_flag`` are its names for the data config and the
    scores folder (``evaluate_panoptic.py``: ``--data_cfg`` / ``--output``).

    Returns its scores file, its printout and its command line (temporary folder shown as <tmp>).
    """
    with tempfile.TemporaryDirectory(prefix="ska_cmp_") as tmp:
        root = Path(tmp)
        _link_tree(root, seq_name, gt_files, pred_files)
        scores_dir = root / "scores"
        scores_dir.mkdir()
        cmd = [
            args.python,
            str(script),
            "--dataset",
            str(root / "dataset"),
            "--predictions",
            str(root / "predictions"),
            "--split",
            args.split,
            cfg_flag,
            str(datacfg),
            scores_flag,
            str(scores_dir),
        ]
        # cwd = the checkout: the evaluator imports its auxiliary/ package relative to it.
        proc = subprocess.run(cmd, cwd=script.parent, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            sys.stderr.write(proc.stdout + proc.stderr)
            sys.exit(f"error: evaluator exited with status {proc.returncode}")
        scores: dict[str, Any] = yaml.safe_load((scores_dir / "scores.txt").read_text())
    return scores, proc.stdout, " ".join(cmd[1:]).replace(tmp, "<tmp>")


def main(argv: list[str] | None = None) -> int:  # noqa: PLR0915  # one report, top to bottom
    args = _parse_args(argv)
    evaluator = args.evaluator.resolve()
    script = evaluator / "evaluate_semantics.py"
    datacfg = (args.datacfg or evaluator / "config" / "semantic-kitti.yaml").resolve()
    metrics_path = args.run / "metrics.json"
    for p in (script, datacfg, metrics_path, args.sequence / "labels", args.run / "export"):
        if not p.exists():
            sys.exit(f"error: {p} does not exist")

    metrics = json.loads(metrics_path.read_text())
    row = args.row or metrics["rows"][-1]
    if row not in metrics["all"]:
        sys.exit(f"error: {metrics_path}: no row {row!r} (rows: {', '.join(metrics['rows'])})")
    leap = metrics["all"][row]
    names: list[str] = metrics["class_names"]
    # metrics.json "frames" is [first, stop) of the frame numbers (older runs added a step).
    start, stop, *rest = metrics["frames"]
    numbers = set(range(start, stop, rest[0] if rest else 1))
    gt_files = [f for f in sorted((args.sequence / "labels").glob("*.label")) if int(f.stem) in numbers]
    pred_files = [args.run / "export" / f.name for f in gt_files]
    missing = [p.name for p in pred_files if not p.is_file()]
    if missing:
        sys.exit(f"error: {args.run / 'export'}: {len(missing)} predictions missing, e.g. {missing[0]}")

    cfg = yaml.safe_load(datacfg.read_text())
    split_seqs = cfg["split"][args.split]
    if not split_seqs:
        sys.exit(f"error: {datacfg}: split {args.split!r} lists no sequence")
    seq_name = f"{int(split_seqs[0]):02d}"

    scores, printout, shown_cmd = _run_evaluator(args, script, datacfg, seq_name, gt_files, pred_files)
    printed = re.search(r"IoU avg ([0-9.]+)", printout)
    print("$ " + shown_cmd)
    print(
        f"{len(gt_files)} scans, sequence {args.sequence} as {seq_name}, "
        f"leap row {row!r}, all-points protocol\n"
    )
    print(f"{'class':<14}  {'leap':>9}  {'evaluator':>9}  {'|diff|':>9}")
    print(f"{'-' * 14}  {'-' * 9}  {'-' * 9}  {'-' * 9}")
    worst = 0.0
    for name in names:
        key = f"iou_{name}"
        if key not in scores:
            sys.exit(
                f"error: evaluator has no class {name!r}; its classes: "
                + ", ".join(k[4:] for k in scores if k.startswith("iou_") and k != "iou_mean")
            )
        ours = leap["iou"][name]
        # LeAP leaves a class absent from gt and prediction undefined (None); the evaluator's 1e-15 in the
        # denominator turns the same 0/0 into 0, so None compares as 0.
        ours_v = 0.0 if ours is None else float(ours)
        theirs = float(scores[key])
        d = abs(ours_v - theirs)
        worst = max(worst, d)
        shown = "-" if ours is None else f"{ours_v:.6f}"
        print(f"{name:<14}  {shown:>9}  {theirs:>9.6f}  {d:>9.2e}")
    m_ours, m_theirs = float(leap["miou_all_classes"]), float(scores["iou_mean"])
    d_m = abs(m_ours - m_theirs)
    print(f"{f'mIoU (all {len(names)})':<14}  {m_ours:>9.6f}  {m_theirs:>9.6f}  {d_m:>9.2e}")
    print(
        f"\nevaluator printout: IoU avg {printed.group(1) if printed else '?'}; "
        f"leap miou_all_classes {m_ours:.6f}, miou (defined classes) {leap['miou']:.6f}"
    )
    worst = max(worst, d_m)
    if args.objects:
        worst = max(worst, _compare_objects(args, evaluator, metrics, seq_name, gt_files, pred_files))
    ok = worst <= args.tol and not math.isnan(worst)
    print(f"max |diff| = {worst:.3e}  ({'OK' if ok else 'FAIL'}, tolerance {args.tol:g})")
    return 0 if ok else 1


def _compare_objects(  # the evaluators' folder, LeAP's scores, the files
    args: argparse.Namespace,
    evaluator: Path,
    metrics: dict[str, Any],
    seq_name: str,
    gt_files: list[Path],
    pred_files: list[Path],
) -> float:
    """Print evaluate_panoptic.py's and evaluate_mos.py's scores beside ``metrics.json``'s ``objects``;
    return the largest |difference|."""
    objects = metrics.get("objects")
    if not objects:
        sys.exit("error: metrics.json has no object scores (a run with tracking.enabled: false?)")
    datacfg = (args.datacfg or evaluator / "config" / "semantic-kitti.yaml").resolve()
    pan, _, shown = _run_evaluator(
        args,
        evaluator / "evaluate_panoptic.py",
        datacfg,
        seq_name,
        gt_files,
        pred_files,
        cfg_flag="--data_cfg",
        scores_flag="--output",
    )
    mos, _, shown_mos = _run_evaluator(
        args,
        evaluator / "evaluate_mos.py",
        evaluator / "config" / "semantic-kitti-mos.yaml",
        seq_name,
        gt_files,
        pred_files,
    )
    print(f"\n$ {shown}\n$ {shown_mos}\n")
    print(f"{'score':<14}  {'leap':>9}  {'evaluator':>9}  {'|diff|':>9}")
    print(f"{'-' * 14}  {'-' * 9}  {'-' * 9}  {'-' * 9}")
    pairs = [
        (f"{q}{part}", objects["all"][f"{q}{part}"], pan[f"{q.lower()}_{name}"])
        for part, name in (("", "mean"), ("_things", "things"), ("_stuff", "stuff"))
        for q in ("PQ", "SQ", "RQ")
    ]
    pairs.append(("MOS IoU", objects["motion"]["mos_iou"], mos["iou_moving"]))
    worst = 0.0
    for name, ours, theirs in pairs:
        d = abs(float(ours if ours is not None else math.nan) - float(theirs))
        worst = max(worst, d) if not math.isnan(d) else math.nan
        print(f"{name:<14}  {float(ours or 0):>9.6f}  {float(theirs):>9.6f}  {d:>9.2e}")
    return worst


if __name__ == "__main__":
    sys.exit(main())
