"""Training the 3D-CN's network on ground truth (``leap train-3dcn``): the scans and counts it trains on,
the network it learns, and the command's checkpoint that ``leap run --3dcn-init`` starts from."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cli import cli
from leap_core.consistency.config import BackboneConfig, ConsistencyConfig
from leap_core.consistency.pretrain import ground_truth_scans, train_on_ground_truth
from leap_core.consistency.train import class_counts, load_checkpoint, load_source, predict_log_probs
from leap_core.datasets.kitti import KittiSequence, write_calib, write_label, write_poses, write_scan
from leap_core.errors import DatasetError, LeapError
from leap_core.schema import builtin_schema
from tests.conftest import make_tiny_calib
from tests.test_consistency import synthetic_scan

SCHEMA = builtin_schema("semantickitti")
ROAD, BUILDING, POLE = 40, 50, 80
"""Raw SemanticKITTI ids of the three shapes of :func:`_scene_scan`."""

TINY_BACKBONE = BackboneConfig(channels=16, layers=2, grid_cells=(1.0, 1.0, 1.0), knn=4)
TINY = ConsistencyConfig(
    enabled=True,
    backbone=TINY_BACKBONE,
    points_per_scan=0,
    min_steps=0,
    lr=1e-2,
    augment=False,
    device="cpu",
    num_threads=1,
)


def _scene_scan(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`tests.test_consistency.synthetic_scan` (road plane, building wall, pole) with raw ids."""
    pts, lab = synthetic_scan(seed)
    return pts, np.array([ROAD, BUILDING, POLE], np.uint32)[lab]


def _labeled_sequence(root: Path, seeds: list[int], *, unmapped_share: float = 0.0) -> KittiSequence:
    """``root/sequences/00`` with one :func:`_scene_scan` per seed; ``unmapped_share`` of each scan's
    points get raw id 0 (unlabeled: no class)."""
    seq = root / "sequences" / "00"
    for i, s in enumerate(seeds):
        pts, raw = _scene_scan(s)
        raw = raw.copy()
        raw[np.random.default_rng(s).random(len(raw)) < unmapped_share] = 0
        write_scan(seq / "velodyne" / f"{i:06d}.bin", pts)
        write_label(seq / "labels" / f"{i:06d}.label", raw, np.zeros(len(raw), np.uint32))
    write_calib(seq / "calib.txt", make_tiny_calib())
    write_poses(seq / "poses.txt", np.tile(np.eye(4), (len(seeds), 1, 1)))
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(len(seeds))))
    return KittiSequence(seq)


def test_class_counts_hand_computed() -> None:
    assert class_counts([2, -1, 0, 2, 2, -1], 4).tolist() == [1, 0, 3, 0]
    assert class_counts(np.array([], np.int16), 2).tolist() == [0, 0]


def test_ground_truth_scans_cover_every_scan_and_count_the_mapped_points(tmp_path: Path) -> None:
    a = _labeled_sequence(tmp_path / "a", [1, 2], unmapped_share=0.25)
    b = _labeled_sequence(tmp_path / "b", [3])
    data = ground_truth_scans([a, b], SCHEMA)
    assert [(s.root, i) for s, i in data.scans] == [(a.root, 0), (a.root, 1), (b.root, 0)]
    want = np.zeros(SCHEMA.num_classes, np.int64)
    for seq, i in data.scans:
        raw = seq.frame(i).labels & 0xFFFF
        for rid, name in ((ROAD, "road"), (BUILDING, "building"), (POLE, "pole")):
            want[SCHEMA.index(name)] += int((raw == rid).sum())
    assert data.class_counts.tolist() == want.tolist()
    # Unlabeled points (raw id 0) count for no class.
    assert data.class_counts.sum() < 3 * 600


def test_ground_truth_scans_refuse_a_missing_label_file_naming_it(tmp_path: Path) -> None:
    seq = _labeled_sequence(tmp_path, [1, 2])
    (seq.root / "labels" / "000001.label").unlink()
    with pytest.raises(DatasetError, match=r"000001\.label.*missing ground-truth label file"):
        ground_truth_scans([KittiSequence(seq.root)], SCHEMA)


def test_ground_truth_scans_refuse_labels_the_schema_does_not_know(tmp_path: Path) -> None:
    seq = _labeled_sequence(tmp_path, [1], unmapped_share=1.0)
    with pytest.raises(LeapError, match=r"no ground-truth point maps to a class of the schema \(car, "):
        ground_truth_scans([seq], SCHEMA)


def test_the_network_learns_the_ground_truth(tmp_path: Path) -> None:
    data = ground_truth_scans([_labeled_sequence(tmp_path, [1, 2, 3, 4])], SCHEMA)
    model, stats = train_on_ground_truth(data, SCHEMA, replace(TINY, epochs=8))
    assert stats.steps == 32
    # Only the classes with ground truth are trained; the others get probability 0.
    trained = {SCHEMA.names[c] for c in np.flatnonzero(model.trained_classes.numpy())}
    assert trained == {"road", "building", "pole"}
    pts, raw = _scene_scan(99)
    pred = predict_log_probs(model, pts).argmax(1)
    assert (pred == SCHEMA.map_gt(raw)).mean() > 0.9


def _project(tmp_path: Path) -> Path:
    """A project file with the built-in classes and a tiny backbone (the runs' settings to match)."""
    text = Path("projects/semantickitti.yaml").read_text()
    bb = TINY_BACKBONE
    path = tmp_path / "tiny.yaml"
    assert "\npipeline:" not in text
    path.write_text(
        text + "\npipeline:\n  consistency:\n    points_per_scan: 0\n    augment: false\n    lr: 0.01\n"
        f"    backbone: {{channels: {bb.channels}, layers: {bb.layers}, grid_cells: {list(bb.grid_cells)}, "
        f"knn: {bb.knn}}}\n"
    )
    return path


@pytest.mark.slow
def test_cli_writes_a_source_network_for_3dcn_init_and_never_replaces_one_unasked(tmp_path: Path) -> None:
    seq = _labeled_sequence(tmp_path / "d", [1, 2, 3])
    project = _project(tmp_path)
    out = tmp_path / "src.pt"
    run = CliRunner().invoke
    res = run(
        cli,
        [
            "train-3dcn",
            str(seq.root),
            "--out",
            str(out),
            "--project-file",
            str(project),
            "--steps",
            "5",
            "--seed",
            "3",
        ],
    )
    assert res.exit_code == 0, res.output
    assert f"wrote {out}: 3 scans of 1 sequence(s), 5 steps" in res.output
    ck = load_checkpoint(out)
    assert ck.meta["kind"] == "ground-truth" and ck.meta["scans"] == 3 and ck.meta["steps"] == 5
    assert ck.meta["class_names"] == SCHEMA.names and ck.config.seed == 3
    assert ck.meta["class_counts"] == ground_truth_scans([seq], SCHEMA).class_counts.tolist()
    # What a run with the same project accepts as its 3D-CN source.
    load_source(out, TINY_BACKBONE, SCHEMA.num_classes)
    # An existing file is kept unless --force.
    before = out.read_bytes()
    res = run(cli, ["train-3dcn", str(seq.root), "--out", str(out), "--project-file", str(project)])
    assert res.exit_code == 2 and "already exists; add --force" in res.output
    assert out.read_bytes() == before
    res = run(
        cli,
        [
            "train-3dcn",
            str(seq.root),
            "--out",
            str(out),
            "--project-file",
            str(project),
            "--steps",
            "5",
            "--seed",
            "4",
            "--force",
        ],
    )
    assert res.exit_code == 0, res.output
    assert out.read_bytes() != before


def test_cli_names_the_scan_without_labels(tmp_path: Path) -> None:
    seq = _labeled_sequence(tmp_path / "d", [1, 2])
    (seq.root / "labels" / "000000.label").unlink()
    out = tmp_path / "src.pt"
    res = CliRunner().invoke(cli, ["train-3dcn", str(seq.root), "--out", str(out)])
    assert res.exit_code == 2
    assert "000000.label" in res.output and "missing ground-truth label file" in res.output
    assert not out.exists()
