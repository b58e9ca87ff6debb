"""Benchmark of the dataset check (``leap check``, the app's dataset list and project pages) on long
sequences.

The check lists the folder's entries, stats the scans, reads calib.txt and opens the folder with the KITTI
reader (which reads poses.txt and times.txt); it never reads a scan. The app caches a report per
``dataset_stamp`` (mtimes of the folder and its entries), so a listing pays the check once per dataset
state and then only the stamp.

Baseline, in the same process on the same folder: opening it with ``KittiSequence`` (what every run and the
old dataset listing did anyway). Sequences are written with tiny files (16-byte scans, 1×1 images, empty
label files) so a 4,541-frame SemanticKITTI-length sequence takes seconds to generate; the check's cost
depends on the number of files, not their size.

Usage::

    .venv/bin/python benchmarks/bench_check.py [--frames 1000 4541]

Prints a table and writes ``benchmarks/results/bench_check.json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, time_it, write_results

from leap_core.config import config_from_dict
from leap_core.datasets.kitti import Calib, KittiSequence, write_calib, write_image, write_poses
from leap_core.pipeline.preflight import check_dataset, dataset_stamp


def make_sequence(root: Path, frames: int) -> Path:
    """A KITTI-layout folder with ``frames`` tiny scans, images, labels and 2D ground truth."""
    for sub in ("velodyne", "image_2", "labels", "gt2d/semantic", "gt2d/instance"):
        (root / sub).mkdir(parents=True)
    pixel = np.zeros((1, 1, 3), np.uint8)
    write_image(root / "image_2" / "000000.png", pixel)
    png = (root / "image_2" / "000000.png").read_bytes()
    for i in range(frames):
        fid = f"{i:06d}"
        (root / "velodyne" / f"{fid}.bin").write_bytes(b"\0" * 16)
        (root / "image_2" / f"{fid}.png").write_bytes(png)
        (root / "labels" / f"{fid}.label").write_bytes(b"\0" * 4)
        (root / "gt2d" / "semantic" / f"{fid}.png").write_bytes(png)
        (root / "gt2d" / "instance" / f"{fid}.png").write_bytes(png)
    p2 = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])
    write_calib(root / "calib.txt", Calib(P2=p2, Tr=np.eye(4)))
    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, 2, 3] = np.arange(frames) * 0.8
    write_poses(root / "poses.txt", poses)
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(frames)))
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[1000, 4541])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    config = config_from_dict({"labeler": "simulated"})
    rows, results = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.frames:
            root = make_sequence(Path(tmp) / f"f{n}" / "sequences" / "00", n)
            base = time_it(lambda root=root: KittiSequence(root), repeat=args.repeat)
            check = time_it(
                lambda root=root: check_dataset(root, config=config, check_models=False), repeat=args.repeat
            )
            stamp = time_it(lambda root=root: dataset_stamp(root), repeat=args.repeat)
            report = check_dataset(root, config=config, check_models=False)
            assert report.verdict == "full", report.findings
            rows.append(
                [
                    n,
                    f"{base.median * 1e3:.1f}",
                    f"{check.median * 1e3:.1f}",
                    f"{check.median / base.median:.2f}",
                    f"{stamp.median * 1e6:.0f}",
                ]
            )
            results.append(
                {
                    "frames": n,
                    "kitti_open": base.to_dict(),
                    "check": check.to_dict(),
                    "stamp": stamp.to_dict(),
                }
            )
    print_table(
        "dataset check (median of runs)",
        ["frames", "KittiSequence open ms", "check ms", "check / open", "cached (stamp) µs"],
        rows,
    )
    write_results("bench_check", {"results": results})


if __name__ == "__main__":
    main()
