"""A finished run's export counts (leap_core.pipeline.coverage): the one-pass count against the definition,
and the counts kept in the run folder against a fresh count, as the export changes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.datasets.kitti import KittiSequence
from leap_core.fusion import voxel_keys, world_points
from leap_core.pipeline.context import load_observation
from leap_core.pipeline.coverage import (
    ExportCoverage,
    cached_export_coverage,
    coverage_key,
    export_coverage,
    read_coverage_file,
    summed_coverage,
)
from leap_core.run_layout import SequenceLayout
from leap_core.schema import builtin_schema
from leap_core.types import UNLABELED

VOXEL = PipelineConfig().fusion.voxel_size


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_street(tmp_path_factory.mktemp("street") / "sequences" / "00", n_frames=5)


def _run(street: Path, run_dir: Path, cfg: PipelineConfig | None = None) -> None:
    """Label ``street`` in the run whose folder of it is ``run_dir`` (``<run>/sequences/00``)."""
    assert run_dir == folder(run_dir.parent.parent)
    label(street, builtin_schema("semantickitti"), cfg or PipelineConfig(), run_dir.parent.parent)


def reference_counts(run_dir: Path, dataset: Path) -> ExportCoverage:
    """The module docstring's definition, point by point: seen voxels over every frame first, then each
    unlabeled point's reason."""
    lay = SequenceLayout(run_dir)
    seq = KittiSequence(dataset)
    keys = [voxel_keys(world_points(f.points, f.pose), VOXEL) for f in seq]
    seen: set[int] = set()
    for i, fid in enumerate(seq.frame_ids):
        _, _, in_view = load_observation(lay.observation(fid))
        seen.update(keys[i][in_view].tolist())
    points = labeled = outside = no_mask = 0
    raws: dict[int, int] = {}
    for i, fid in enumerate(seq.frame_ids):
        with np.load(lay.points(fid)) as z:
            lab = z["label"]
        for key, cls in zip(keys[i].tolist(), lab.tolist(), strict=True):
            points += 1
            if cls != UNLABELED:
                labeled += 1
            elif key in seen:
                no_mask += 1
            else:
                outside += 1
        for raw in (np.fromfile(lay.export_label(fid), dtype="<u4") & 0xFFFF).tolist():
            raws[raw] = raws.get(raw, 0) + 1
    return ExportCoverage(len(seq), points, labeled, outside, no_mask, dict(sorted(raws.items())))


@pytest.mark.parametrize("merge_at", [1, 3, 1 << 19])
def test_export_coverage_matches_the_definition(street: Path, tmp_path: Path, merge_at: int) -> None:
    run_dir = folder(tmp_path / "run")
    _run(street, run_dir)
    ref = reference_counts(run_dir, street)
    assert ref.outside_view > 0 and ref.no_mask > 0 and ref.labeled > 0  # every branch is exercised
    assert export_coverage(run_dir, street, None, VOXEL, merge_at=merge_at) == ref


def _cached_file(run_dir: Path) -> dict:
    return json.loads(SequenceLayout(run_dir).export_coverage.read_text())


def test_cached_counts_equal_a_fresh_count_as_the_export_changes(street: Path, tmp_path: Path) -> None:
    run_dir = folder(tmp_path / "run")
    lay = SequenceLayout(run_dir)
    _run(street, run_dir)
    fresh = export_coverage(run_dir, street, None, VOXEL)
    assert cached_export_coverage(run_dir, street, None, VOXEL) == fresh
    key = coverage_key(run_dir, street, None, VOXEL)
    assert key is not None and _cached_file(run_dir)["key"] == key
    assert read_coverage_file(lay.export_coverage, key) == fresh

    # Read back, not counted again: a file edited under the same key is what comes back.
    data = _cached_file(run_dir)
    data["labeled"] += 7
    lay.export_coverage.write_text(json.dumps(data))
    assert cached_export_coverage(run_dir, street, None, VOXEL).labeled == fresh.labeled + 7

    # Other settings: the export stage reruns, so its key changes and the counts are taken again.
    coarse = config_from_dict({"smoothing": {"k": 1}, "fusion": {"prob_floor": 0.2}}, PipelineConfig())
    _run(street, run_dir, coarse)
    assert coverage_key(run_dir, street, None, VOXEL) != key
    changed = cached_export_coverage(run_dir, street, None, VOXEL)
    assert changed == export_coverage(run_dir, street, None, VOXEL) == reference_counts(run_dir, street)
    assert _cached_file(run_dir)["key"] == coverage_key(run_dir, street, None, VOXEL)

    # Same settings, but one scan's export rewritten by a resumed run: a new key too.
    key = coverage_key(run_dir, street, None, VOXEL)
    data = _cached_file(run_dir)
    data["labeled"] += 7
    lay.export_coverage.write_text(json.dumps(data))
    lay.export_label("000002").unlink()
    _run(street, run_dir, coarse)
    assert coverage_key(run_dir, street, None, VOXEL) != key
    assert cached_export_coverage(run_dir, street, None, VOXEL) == changed

    # Other arguments than the run's (frames, voxel size): never the file's numbers.
    assert coverage_key(run_dir, street, range(0, 5), VOXEL) != coverage_key(run_dir, street, None, VOXEL)
    assert coverage_key(run_dir, street, None, 2 * VOXEL) != coverage_key(run_dir, street, None, VOXEL)


def test_no_cache_while_the_export_is_not_done(street: Path, tmp_path: Path) -> None:
    run_dir = folder(tmp_path / "run")
    lay = SequenceLayout(run_dir)
    _run(street, run_dir)
    state = json.loads(lay.state.read_text())
    state["export"]["status"] = "running"
    lay.state.write_text(json.dumps(state))
    assert coverage_key(run_dir, street, None, VOXEL) is None
    assert cached_export_coverage(run_dir, street, None, VOXEL) == reference_counts(run_dir, street)
    assert not lay.export_coverage.exists()


def test_a_file_of_the_app_without_a_key_is_counted_again(street: Path, tmp_path: Path) -> None:
    run_dir = folder(tmp_path / "run")
    lay = SequenceLayout(run_dir)
    _run(street, run_dir)
    fresh = export_coverage(run_dir, street, None, VOXEL)
    data = fresh.to_dict() | {"labeled": 1, "raw_counts": {"0": 1}}
    lay.export_coverage.write_text(json.dumps(data))  # the app's older form: no key
    assert read_coverage_file(lay.export_coverage) is not None  # the app's reader still takes it
    assert cached_export_coverage(run_dir, street, None, VOXEL) == fresh


def test_cli_rerun_prints_the_counts_from_the_run_folder(street: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli as app

    out = tmp_path / "run"

    def run() -> str:
        res = CliRunner().invoke(app, ["run", str(street), "--out", str(out), "--labeler", "simulated"])
        assert res.exit_code == 0, res.output
        return next(line for line in res.output.splitlines() if "points labeled;" in line)

    first = run()
    seq_dir = folder(out)
    fresh = export_coverage(seq_dir, street, None, VOXEL)
    assert first.startswith(
        f"{fresh.labeled} of {fresh.points} points labeled; {fresh.unlabeled} unlabeled: "
        f"{fresh.outside_view} outside"
    )
    data = _cached_file(seq_dir)
    assert data["key"] == coverage_key(seq_dir, street, None, VOXEL)
    data["no_mask"] += 1000
    SequenceLayout(seq_dir).export_coverage.write_text(json.dumps(data))
    assert run().endswith(f"{fresh.no_mask + 1000} in view but no mask")


def test_a_runs_counts_are_its_sequences_counts_summed() -> None:
    """An export of several sequences counts each field over all of them, raw ids merged in order."""
    a = ExportCoverage(3, 100, 60, 30, 10, {0: 40, 40: 50, 10: 10})
    b = ExportCoverage(2, 50, 45, 1, 4, {0: 5, 48: 45})
    both = summed_coverage([a, b])
    assert both == ExportCoverage(5, 150, 105, 31, 14, {0: 45, 10: 10, 40: 50, 48: 45})
    assert list(both.raw_counts) == [0, 10, 40, 48] and both.unlabeled == 45
    assert summed_coverage([a]) == a
    assert summed_coverage([]) == ExportCoverage(0, 0, 0, 0, 0, {})


@pytest.mark.parametrize("merge_at", [1, 5, 1000])
def test_key_counts_are_the_multiset_of_everything_added(merge_at: int) -> None:
    from leap_core.pipeline.coverage import _KeyCounts

    rng = np.random.default_rng(3)
    parts = [rng.integers(-50, 50, rng.integers(0, 30)).astype(np.int64) for _ in range(20)]
    kc = _KeyCounts(merge_at)
    for p in parts:
        kc.add(p)
    keys, counts = kc.merged()
    want_keys, want_counts = np.unique(np.concatenate(parts), return_counts=True)
    assert keys.dtype == np.int64 and counts.dtype == np.int64
    np.testing.assert_array_equal(keys, want_keys)  # sorted, each key once
    np.testing.assert_array_equal(counts, want_counts)
