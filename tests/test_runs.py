"""Runs of several sequences (leap_core.pipeline.run): two tiny ray-cast streets labeled in one run, their
exports and metrics, the 3D-CN over both, resume, a run folder given other sequences, and
`leap run A B ...`."""

from __future__ import annotations

import dataclasses
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.errors import Cancelled, ConfigError, LeapError
from leap_core.export import (
    LABEL_MAP_FILE,
    SUMMARY_FILE,
    ExportConflict,
    export_targets,
    label_map,
    label_map_yaml,
    load_label_map,
    run_export,
    summary_yaml,
    write_export_zip,
    write_run_export,
)
from leap_core.metrics import metrics_from_confusion
from leap_core.pipeline import (
    JOINT,
    PROTOCOLS,
    SequenceSpec,
    overall_metrics,
    read_run_metrics,
    result_tables,
    run_pipeline,
    run_result_tables,
)
from leap_core.pipeline.context import read_state
from leap_core.run_layout import RunLayout, SequenceLayout, save_corrections
from leap_core.schema import builtin_schema

TINY_3DCN = {
    "enabled": True,
    "iterations": 2,
    "points_per_scan": 1024,
    "num_threads": 1,
    "min_steps": 0,
    "device": "cpu",
    "backbone": {"channels": 8, "layers": 1, "knn": 4},
}
"""A 3D-CN small enough to train in seconds on the streets."""


@pytest.fixture(scope="module")
def streets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two sequences of different length and step, in two datasets: ``00`` and ``01``."""
    base = tmp_path_factory.mktemp("streets")
    return {
        "00": make_street(base / "x" / "sequences" / "00", n_frames=5),
        "01": make_street(base / "y" / "sequences" / "01", n_frames=4, step=2.0),
    }


@pytest.fixture(scope="module")
def schema():
    return builtin_schema("semantickitti")


def _specs(streets: dict[str, Path]) -> list[SequenceSpec]:
    return [SequenceSpec.of(path) for path in streets.values()]


def _files(folder: Path, pattern: str = "*") -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob(pattern)) if p.is_file()}


@pytest.fixture(scope="module")
def plain(streets, schema, tmp_path_factory: pytest.TempPathFactory):
    """A run of both sequences without the 3D-CN, and a run of each sequence alone."""
    runs = tmp_path_factory.mktemp("plain")
    calls: list[tuple[str, str, int, int]] = []
    multi = run_pipeline(
        _specs(streets), schema, PipelineConfig(), runs / "multi", progress=lambda *a: calls.append(a)
    )
    singles = {
        name: label(path, schema, PipelineConfig(), runs / f"single-{name}") for name, path in streets.items()
    }
    return multi, singles, calls


def _export(
    root: Path,
    target: Path,
    *,
    names: list[str] | None = None,
    overwrite: bool = False,
    with_conf: bool = False,
) -> dict[str, int]:
    """A run's export into ``target/sequences/<name>/predictions/`` (what ``leap run --export-to`` does)."""
    exported = run_export(root, names)
    folders = export_targets(target.resolve(), [s.name for s in exported], with_conf=with_conf)
    return write_run_export(folders, exported, with_conf=with_conf, overwrite=overwrite).files


# ------------------------------------------------------------------------------------- without 3D-CN
def test_without_3dcn_every_sequence_equals_its_run_alone(plain, streets) -> None:
    multi, singles, calls = plain
    layout = RunLayout(multi.root)
    assert layout.names() == ["00", "01"] == list(multi.sequences)
    assert [e["name"] for e in json.loads(layout.spec.read_text())["sequences"]] == ["00", "01"]
    for name, single in singles.items():
        member = layout.sequence(name)
        assert member.folder == multi.root / "sequences" / name == multi.sequences[name].folder
        assert single.folder == single.folder.parent.parent / "sequences" / name
        assert multi.sequences[name].ran == single.ran
        labels = _files(member.export_dir)
        assert labels and labels == _files(single.folder / "export")  # .label and .conf, byte for byte
        assert len(labels) == 2 * len(list((streets[name] / "velodyne").glob("*.bin")))
        # Same fingerprints too: the run alone finds every stage of the sequence's folder current.
        fps = {s: r["fingerprint"] for s, r in read_state(member).items()}
        assert fps == {s: r["fingerprint"] for s, r in read_state(SequenceLayout(single.folder)).items()}
        assert not member.joint_3dcn.exists()
    assert {c[0] for c in calls} == {"00", "01"}
    assert ("01", "export", 4, 4) in calls


def test_overall_metrics_are_those_of_the_summed_confusion_matrices(plain) -> None:
    multi, singles, _ = plain
    data = json.loads(RunLayout(multi.root).metrics.read_text())
    assert data == multi.metrics.to_dict()
    single = {n: s.metrics.to_dict() for n, s in singles.items()}
    assert data["sequences"] == single
    overall = data["overall"]
    assert overall["sequences"] == ["00", "01"]
    names, cats = overall["class_names"], overall["categories"]
    for p in PROTOCOLS:
        for row in overall["rows"]:
            summed = sum(np.asarray(s[p][row]["confusion"]) for s in single.values())
            assert overall[p][row]["confusion"] == summed.tolist()
            expected = metrics_from_confusion(summed, names, cats, ignore_unlabeled_pred=p != "all")
            assert overall[p][row] == expected.to_dict()
    n = [s["n_points"] for s in single.values()]
    assert overall["n_points"] == sum(n)
    # Not the mean of the sequences' mIoUs: the sequences differ, so the two differ.
    mean = np.mean([s["all"]["voxel"]["miou"] for s in single.values()])
    assert overall["all"]["voxel"]["miou"] != pytest.approx(mean, abs=1e-9)


def test_a_runs_tables_are_its_sequences_then_the_overall_ones(plain) -> None:
    """A run's metrics and tables as text: a run of one sequence shows that sequence's tables only; a run
    of several each sequence's under its name, then the overall ones. ``only()`` is for a run of one."""
    multi, singles, _ = plain
    assert read_run_metrics(multi.root) == multi.metrics
    text = run_result_tables(multi.root)
    assert text is not None
    parts = text.split("\n\n== ")
    assert [p.splitlines()[0].lstrip("= ") for p in parts] == [
        "sequence 00",
        "sequence 01",
        "overall (confusion matrices of 00, 01 summed)",
    ]
    assert parts[1].split("\n", 1)[1] == result_tables(multi.sequences["01"].folder)
    single_root = singles["00"].folder.parent.parent
    assert run_result_tables(single_root) == result_tables(singles["00"].folder)
    assert read_run_metrics(single_root / "nothing") is None
    with pytest.raises(LeapError, match="a run of 2 sequences, not one"):
        multi.only()


def test_overall_metrics_refuse_disagreeing_sequences_and_skip_missing_ones(plain) -> None:
    _, singles, _ = plain
    a, b = singles["00"].metrics, singles["01"].metrics
    assert overall_metrics({"00": a, "01": None}).sequences == ["00"]
    assert overall_metrics({"00": None}) is None
    with pytest.raises(LeapError, match="sequence 01: metrics rows"):
        overall_metrics({"00": a, "01": dataclasses.replace(b, rows=["point"])})


def test_export_writes_the_semantickitti_layout_and_never_replaces_silently(plain, streets, tmp_path) -> None:
    multi, _, _ = plain
    target = tmp_path / "dataset"
    written = _export(multi.root, target)
    assert written == {"00": 5, "01": 4}
    for name in ("00", "01"):
        preds = target / "sequences" / name / "predictions"
        assert _files(preds) == _files(RunLayout(multi.root).sequence(name).export_dir, "*.label")
    (target / "sequences" / "01" / "predictions" / "000000.label").write_bytes(b"mine")
    with pytest.raises(ExportConflict, match="already holds"):
        _export(multi.root, target)
    assert (target / "sequences" / "01" / "predictions" / "000000.label").read_bytes() == b"mine"
    assert _export(multi.root, target, overwrite=True, with_conf=True) == {"00": 10, "01": 8}
    assert (target / "sequences" / "01" / "predictions" / "000000.label").read_bytes() != b"mine"
    assert len(list((target / "sequences" / "00" / "confidences").glob("*.conf"))) == 5
    # A dataset's own folders: sequences/00/labels would be the ground truth's folder.
    dataset_root = streets["00"].parent.parent
    gt = _files(streets["00"] / "labels")
    bad = tmp_path / "bad"
    (bad / "sequences" / "00" / "velodyne").mkdir(parents=True)
    with pytest.raises(LeapError, match="inside the dataset folder"):
        _export(multi.root, bad / "sequences" / "00" / "velodyne")
    # The run folder itself, a folder inside it, or one of its sequences' folders.
    for inside in (multi.root, multi.root / "exports", RunLayout(multi.root).sequence("00").folder):
        with pytest.raises(LeapError, match="inside the pipeline run folder"):
            _export(multi.root, inside)
    assert (
        not (multi.root / "exports").exists() and not (multi.root / "sequences" / "00" / "sequences").exists()
    )
    # Into the dataset root itself: predictions/ beside labels/, the ground truth untouched.
    _export(multi.root, dataset_root, names=["00"])
    assert _files(streets["00"] / "labels") == gt
    assert len(list((streets["00"] / "predictions").glob("*.label"))) == 5
    shutil.rmtree(streets["00"] / "predictions")


def test_run_export_lists_the_runs_sequences_with_their_datasets_and_frames(
    plain, streets, schema, tmp_path
) -> None:
    multi, _, _ = plain
    exported = run_export(multi.root)
    assert [(s.name, s.dataset, s.frames) for s in exported] == [
        ("00", streets["00"].resolve(), None),
        ("01", streets["01"].resolve(), None),
    ]
    assert [s.export_dir for s in exported] == [multi.sequences[n].export_dir for n in ("00", "01")]
    assert [s.name for s in run_export(multi.root, ["01"])] == ["01"]
    with pytest.raises(LeapError, match="not a run folder"):
        run_export(multi.sequences["00"].folder)
    out = tmp_path / "unfinished"
    run_pipeline(_specs(streets), schema, PipelineConfig(), out, until="labels2d")
    with pytest.raises(LeapError, match=r"sequence 00 has no exported \.label files"):
        run_export(out)


def test_export_zip_holds_every_sequence(plain, schema, tmp_path) -> None:
    multi, _, _ = plain
    path = tmp_path / "all.zip"
    exported = run_export(multi.root)
    lmap = label_map(schema, {0: 3, 40: 5}, sequences=[s.name for s in exported])
    counts = {"scans": 9, "points": 8, "labeled": 5, "unlabeled": 3, "unlabeled_by_reason": {}}
    summary = summary_yaml(
        sequences=exported,
        schema=schema,
        pipeline={},
        counts={**counts, "raw_counts": {0: 3, 40: 5}},
        with_confidence=False,
        version="test",
        written_at="now",
    )
    extra = {LABEL_MAP_FILE: label_map_yaml(lmap), SUMMARY_FILE: summary}
    assert write_export_zip(path, exported, extra, include_confidence=False) == 9
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        lm = load_label_map(zf.read("label-map.yaml").decode())
        assert sum(n.endswith(".label") and "/predictions/" in n for n in names) == 9
        assert "sequences/01/predictions/000003.label" in names and "summary.yaml" in names
        raw = yaml_safe(zf.read("label-map.yaml").decode())
        listed = yaml_safe(zf.read("summary.yaml").decode())["sequences"]
    assert raw["split"]["valid"] == [0, 1] and lm.counts[40] == 5
    assert [s["name"] for s in listed] == ["00", "01"] and listed[1]["dataset"] == str(exported[1].dataset)
    with pytest.raises(ExportConflict):
        write_export_zip(path, exported, extra, include_confidence=False)


def yaml_safe(text: str):
    import yaml

    return yaml.safe_load(text)


def test_specs_are_checked(streets, schema, tmp_path) -> None:
    link = tmp_path / "sequences" / "07"
    link.parent.mkdir()
    link.symlink_to(streets["00"])
    assert SequenceSpec.of(link).name == "07" and SequenceSpec.of(link / ".." / "07").name == "07"
    assert SequenceSpec.of(link, name="seven", frames=range(2)) == SequenceSpec("seven", link, range(2))
    with pytest.raises(ConfigError, match="name: must be 1-64") as err:
        SequenceSpec("../x", streets["00"])
    assert err.value.field == ("name",)
    with pytest.raises(ConfigError, match="frames: must be a range"):
        SequenceSpec("a", streets["00"], (0, 3))  # type: ignore[arg-type]  # the mistake under test
    dup = [SequenceSpec("a", streets["00"]), SequenceSpec("a", streets["01"])]
    with pytest.raises(ConfigError, match="duplicate sequence name 'a'") as err:
        run_pipeline(dup, schema, PipelineConfig(), tmp_path / "m")
    assert err.value.field == ("sequences", "1", "name")
    with pytest.raises(ConfigError, match="a run needs at least one sequence"):
        run_pipeline([], schema, PipelineConfig(), tmp_path / "m")
    with pytest.raises(LeapError, match="velodyne"):
        run_pipeline([SequenceSpec("a", tmp_path)], schema, PipelineConfig(), tmp_path / "m")
    assert not (tmp_path / "m").exists()  # refused before any work


def test_a_run_of_other_sequences_leaves_the_folders_of_the_others_untouched(
    plain, streets, schema, tmp_path
) -> None:
    """A run folder holds the sequences of its last run (run.json) beside the folders of sequences an
    earlier run in it labeled: those are neither read nor changed, and a later run of them resumes."""
    multi, _, _ = plain
    out = tmp_path / "run"
    shutil.copytree(multi.root, out)
    kept = {p: p.read_bytes() for p in sorted((out / "sequences" / "01").rglob("*")) if p.is_file()}
    only = run_pipeline([SequenceSpec.of(streets["00"])], schema, PipelineConfig(), out)
    assert list(only.sequences) == ["00"] and only.only().ran == []
    layout = RunLayout(out)
    assert layout.names() == ["00"]  # run.json names the run's sequences
    assert only.metrics.to_dict() == json.loads(layout.metrics.read_text())
    assert only.metrics.sequences == {"00": multi.metrics.sequences["00"]}
    assert only.metrics.overall.sequences == ["00"]
    assert {p: p.read_bytes() for p in sorted((out / "sequences" / "01").rglob("*")) if p.is_file()} == kept
    both = run_pipeline(_specs(streets), schema, PipelineConfig(), out)
    assert all(r.ran == [] for r in both.sequences.values())
    assert both.metrics == multi.metrics and layout.names() == ["00", "01"]


def test_a_sequence_takes_its_folder_by_name(plain, streets, schema, tmp_path) -> None:
    """A run folder's sequence folder belongs to the sequence of that name: another sequence gets its own
    folder, computed from scratch; a sequence of the same name but another dataset recomputes in it."""
    _, singles, _ = plain
    out = tmp_path / "run"
    shutil.copytree(singles["00"].folder.parent.parent, out)
    kept = {p: p.read_bytes() for p in sorted(folder(out, "00").rglob("*")) if p.is_file()}
    other = label(streets["01"], schema, PipelineConfig(), out)
    assert other.folder == folder(out, "01") and other.ran == singles["01"].ran  # nothing reused
    assert _files(other.folder / "export") == _files(singles["01"].folder / "export")
    assert {p: p.read_bytes() for p in sorted(folder(out, "00").rglob("*")) if p.is_file()} == kept
    assert RunLayout(out).names() == ["01"]
    # Another dataset under the name 00: it takes the folder named 00, where every stage sees other inputs.
    renamed = label(streets["01"], schema, PipelineConfig(), out, name="00")
    assert renamed.folder == folder(out, "00") and renamed.ran == singles["01"].ran
    assert _files(renamed.folder / "export") == _files(singles["01"].folder / "export")
    assert RunLayout(out).names() == ["00"]


def test_resume_after_cancel_is_byte_identical(plain, streets, schema, tmp_path) -> None:
    multi, _, _ = plain
    out = tmp_path / "resumed"
    for seq, stage, at in (("00", "label_points", 3), ("01", "labels2d", 2)):

        def cancel(
            name: str, s: str, done: int, _total: int, seq: str = seq, stage: str = stage, at: int = at
        ) -> None:
            if (name, s, done) == (seq, stage, at):
                raise Cancelled()

        with pytest.raises(Cancelled):
            run_pipeline(_specs(streets), schema, PipelineConfig(), out, progress=cancel)
    assert read_state(RunLayout(out).sequence("00"))["export"]["status"] == "done"
    result = run_pipeline(_specs(streets), schema, PipelineConfig(), out)
    assert result.sequences["00"].ran == []
    assert result.sequences["01"].stages["labels2d"].frames_computed == 2  # 2 of 4 were kept
    for name in ("00", "01"):
        assert _files(RunLayout(out).sequence(name).export_dir) == _files(
            RunLayout(multi.root).sequence(name).export_dir
        )
    assert result.metrics == multi.metrics


# ---------------------------------------------------------------------------------------------- 3D-CN
@pytest.fixture(scope="module")
def joint(streets, schema, tmp_path_factory: pytest.TempPathFactory):
    # new_voxel_margin 0: every voxel the network predicts is created (this tiny network is sure of few).
    cfg = config_from_dict({"consistency": {**TINY_3DCN, "iterations": 1, "new_voxel_margin": 0.0}})
    calls: list[tuple[str, str, int, int]] = []
    result = run_pipeline(
        _specs(streets),
        schema,
        cfg,
        tmp_path_factory.mktemp("joint") / "multi",
        progress=lambda *a: calls.append(a),
    )
    return result, cfg, calls


@pytest.mark.slow
def test_the_3dcn_trains_one_network_on_every_sequence(joint) -> None:
    import torch

    result, _, calls = joint
    layout = RunLayout(result.root)
    meta = torch.load(layout.cn_dir / "3dcn_iter1.pt", weights_only=True)["meta"]
    assert meta["frames"] == [["00", 0, 5, 1], ["01", 0, 4, 1]]
    assert meta["steps"] == 5 + 4  # one step per scan of either sequence (min_steps 0)
    assert (JOINT, "3dcn", 1000, 1000) in calls
    for name in ("00", "01"):
        member = layout.sequence(name)
        assert not (member.folder / "3dcn").exists()  # no network of its own
        assert member.grid_smooth_3dcn(1).samefile(layout.joint_rounds(name).grid_smooth_3dcn(1))
        assert result.sequences[name].metrics.rows == ["point", "voxel", "+3D-CN x1", "objects"]
        with np.load(member.points("000000")) as z:
            assert (z["label"] >= 0).all()  # the network labels every point
    assert result.metrics.overall.rows == ["point", "voxel", "+3D-CN x1", "objects"]


@pytest.mark.slow
def test_a_change_in_one_sequence_reruns_the_3dcn_of_all(joint, streets, schema, tmp_path) -> None:
    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    staged = RunLayout(out).joint_rounds("00").grid_3dcn(1)
    before = staged.stat().st_mtime_ns
    again = run_pipeline(_specs(streets), schema, cfg, out)
    assert all(r.ran == [] for r in again.sequences.values())
    assert staged.stat().st_mtime_ns == before  # the finished round was kept, not recomputed
    # A correction in sequence 01 changes its fused grid, hence what the network trains on.
    member = RunLayout(out).sequence("01")
    with np.load(member.grid) as z:
        keys = np.asarray(z["keys"][:50])
    save_corrections(member.corrections, keys, np.zeros(len(keys), np.int64))
    changed = run_pipeline(_specs(streets), schema, cfg, out)
    assert changed.sequences["01"].ran == [
        "fuse",
        "smooth",
        "3dcn",
        "label_points",
        "tracks",
        "evaluate",
        "export",
    ]
    assert changed.sequences["00"].ran == ["3dcn", "label_points", "tracks", "evaluate", "export"]
    old = RunLayout(result.root).sequence("00").grid_3dcn(1).read_bytes()
    assert RunLayout(out).sequence("00").grid_3dcn(1).read_bytes() != old


def test_a_source_network_starts_the_3dcn_and_is_part_of_its_fingerprint(
    joint, streets, schema, tmp_path
) -> None:
    from leap_core.consistency.train import load_checkpoint
    from leap_core.io_utils import file_digest
    from leap_core.runtime import Runtime

    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    source = tmp_path / "source.pt"
    shutil.copy(RunLayout(out).cn_dir / "3dcn_iter1.pt", source)
    runtime = Runtime(init_3dcn=source)
    tuned = run_pipeline(_specs(streets), schema, cfg, out, runtime=runtime)
    assert all(
        r.ran == ["3dcn", "label_points", "tracks", "evaluate", "export"] for r in tuned.sequences.values()
    )
    meta = load_checkpoint(RunLayout(out).cn_dir / "3dcn_iter1.pt").meta
    assert meta["source"] == file_digest(source)
    again = run_pipeline(_specs(streets), schema, cfg, out, runtime=runtime)
    assert all(r.ran == [] for r in again.sequences.values())
    back = run_pipeline(_specs(streets), schema, cfg, out)  # no source: the random-weight network again
    assert all(
        r.ran == ["3dcn", "label_points", "tracks", "evaluate", "export"] for r in back.sequences.values()
    )


@pytest.mark.slow
def test_sequences_seeded_from_an_earlier_run_keep_their_3dcn(joint, streets, schema, tmp_path) -> None:
    """The app starts a run by linking the last run's sequence folders into a fresh root: with nothing
    changed, no network is trained again, though the fresh root has no checkpoints or staged rounds."""
    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root / "sequences", out / "sequences")
    again = run_pipeline(_specs(streets), schema, cfg, out)
    assert all(r.ran == [] for r in again.sequences.values())
    assert not (RunLayout(out).cn_dir / "3dcn_iter1.pt").exists()
    assert again.metrics == result.metrics


@pytest.mark.slow
def test_3dcn_resumes_after_cancel(joint, streets, schema, tmp_path) -> None:
    result, cfg, _ = joint
    out = tmp_path / "multi"

    ckpt = RunLayout(out).cn_dir / "3dcn_iter1.pt"

    def cancel(name: str, _stage: str, done: int, _total: int) -> None:
        if name == JOINT and ckpt.is_file() and done < 1000:  # trained, not yet fused back
            raise Cancelled()

    with pytest.raises(Cancelled):
        run_pipeline(_specs(streets), schema, cfg, out, progress=cancel)
    trained = ckpt.stat().st_mtime_ns
    again = run_pipeline(_specs(streets), schema, cfg, out)
    assert ckpt.stat().st_mtime_ns == trained  # the checkpoint was reused, not retrained
    assert again.sequences["00"].ran == ["3dcn", "label_points", "tracks", "evaluate", "export"]
    for name in ("00", "01"):
        assert _files(RunLayout(out).sequence(name).export_dir) == _files(
            RunLayout(result.root).sequence(name).export_dir
        )


@pytest.mark.slow
def test_switching_the_3dcn_off_gives_the_runs_without_it_again(
    joint, plain, streets, schema, tmp_path
) -> None:
    result, _, _ = joint
    multi, _, _ = plain
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    off = run_pipeline(_specs(streets), schema, PipelineConfig(), out)
    for name in ("00", "01"):
        member = RunLayout(out).sequence(name)
        assert not member.joint_3dcn.exists()
        assert off.sequences[name].ran == ["label_points", "tracks", "evaluate", "export"]
        assert _files(member.export_dir) == _files(RunLayout(multi.root).sequence(name).export_dir)
    assert off.metrics == multi.metrics


def test_the_3dcn_fingerprint_takes_the_round_record_only_when_present(plain, streets, schema) -> None:
    """The round record is an optional input of the 3dcn stage: before the rounds ran (no record) the
    stage's fingerprint is its config section (less the fields added at their former value) and upstream
    only, the spelling earlier versions recorded; the record, when present, changes it."""
    from leap_core.config import config_to_dict
    from leap_core.consistency.config import fingerprint_form
    from leap_core.pipeline import PIPELINE_VERSION, stage_fingerprints
    from leap_core.pipeline.context import hash_json

    _, singles, _ = plain
    cfg = config_from_dict({"consistency": TINY_3DCN})
    seq_dir = singles["00"].folder
    fp = stage_fingerprints(streets["00"], schema, cfg, seq_dir)
    before = hash_json(
        {
            "v": PIPELINE_VERSION,
            "C": schema.num_classes,
            "stage": "3dcn",
            "up": [fp["project"], fp["fuse"], fp["smooth"]],
            "config": {"consistency": fingerprint_form(config_to_dict(cfg)["consistency"])},
        }
    )
    assert fp["3dcn"] == before
    note = SequenceLayout(seq_dir).joint_3dcn
    note.write_text("{}")
    try:
        assert stage_fingerprints(streets["00"], schema, cfg, seq_dir)["3dcn"] != before
    finally:
        note.unlink()


def test_a_sequence_without_its_round_is_refused(plain, streets, schema, tmp_path) -> None:
    """A sequence's 3dcn stage only links the run's rounds: without a record of them, or with one of
    another round, it stops with a one-line error naming the run to rerun."""
    from leap_core.pipeline.runner import run_sequence

    multi, _, _ = plain
    out = tmp_path / "multi"
    shutil.copytree(multi.root, out)
    member = RunLayout(out).sequence("00")
    cfg = config_from_dict({"consistency": TINY_3DCN})
    with pytest.raises(LeapError, match=r"3dcn_joint\.json is missing.*leap run SEQ \.\.\. --out RUN") as err:
        run_sequence(streets["00"], schema, cfg, member.folder)
    assert "\n" not in str(err.value)
    member.joint_3dcn.write_text(json.dumps({"fingerprint": "x", "name": "00"}))
    with pytest.raises(LeapError, match=rf"3D-CN has not run for these settings; .*--out {out}\)$") as err:
        run_sequence(streets["00"], schema, cfg, member.folder)
    assert "\n" not in str(err.value)
    assert read_state(member)["3dcn"]["status"] == "failed"


@pytest.mark.slow
def test_a_sequence_whose_round_grids_are_gone_is_refused_and_the_run_computes_them(
    joint, streets, schema, tmp_path
) -> None:
    """The run's record names the round, but its staged grids are gone (deleted by hand), and so is the
    sequence's smoothed round grid: the run computes the round again, from its kept checkpoint, to the same
    grids; the sequence's 3dcn stage alone refuses to link, one line naming that fix."""
    from leap_core.pipeline.runner import run_sequence

    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    layout = RunLayout(out)
    member = layout.sequence("00")

    def lose_the_round() -> None:
        shutil.rmtree(layout.cn_dir / "rounds")
        member.grid_smooth_3dcn(1).unlink()  # so the sequence's own 3dcn stage is no longer current

    lose_the_round()
    trained = (layout.cn_dir / "3dcn_iter1.pt").stat().st_mtime_ns
    again = run_pipeline(_specs(streets), schema, cfg, out)
    # The same round again: the same grids, so only the link is new and nothing downstream reruns.
    assert again.sequences["00"].ran == ["3dcn"] and again.sequences["01"].ran == []
    assert (layout.cn_dir / "3dcn_iter1.pt").stat().st_mtime_ns == trained
    assert member.grid_smooth_3dcn(1).samefile(layout.joint_rounds("00").grid_smooth_3dcn(1))
    for name in ("00", "01"):
        lay, was = layout.sequence(name), RunLayout(result.root).sequence(name)
        assert lay.grid_smooth_3dcn(1).read_bytes() == was.grid_smooth_3dcn(1).read_bytes()
        assert layout.joint_rounds(name).grid_3dcn(1).read_bytes() == was.grid_3dcn(1).read_bytes()
        assert _files(lay.export_dir) == _files(was.export_dir)
    lose_the_round()
    with pytest.raises(
        LeapError, match=rf"3D-CN has not run for these settings; run it again .*--out {out}\)$"
    ) as err:
        run_sequence(streets["00"], schema, cfg, member.folder)
    assert "\n" not in str(err.value)


# ----------------------------------------------------------------------------------------------- CLI
def _cli(*args: str):
    from typer.testing import CliRunner

    from app.cli import cli

    return CliRunner().invoke(cli, list(args))


def _tree(root: Path) -> dict[Path, tuple[bytes, int]]:
    """Every file under ``root``: its bytes and modification time."""
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(root.rglob("*")) if p.is_file()}


def test_cli_runs_several_sequences_and_exports_their_layout(streets, tmp_path) -> None:
    out, target, zpath = tmp_path / "run", tmp_path / "export", tmp_path / "all.zip"
    res = _cli(
        "run",
        str(streets["00"]),
        str(streets["01"]),
        "--out",
        str(out),
        "--labeler",
        "simulated",
        "--export-to",
        str(target),
        "--zip",
        str(zpath),
    )
    assert res.exit_code == 0, res.output
    assert "== sequence 00" in res.output and "== sequence 01" in res.output
    assert "== overall (confusion matrices of 00, 01 summed)" in res.output
    assert "sequence 01: " in res.output and "points labeled" in res.output
    for name, n in (("00", 5), ("01", 4)):
        assert len(list((target / "sequences" / name / "predictions").glob("*.label"))) == n
    with zipfile.ZipFile(zpath) as zf:
        assert "sequences/00/predictions/000004.label" in zf.namelist()
    # Exports are never replaced silently: refused before the run, untouched.
    (target / "sequences" / "00" / "predictions" / "000000.label").write_bytes(b"mine")
    res = _cli("run", str(streets["00"]), str(streets["01"]), "--out", str(out), "--export-to", str(target))
    last = res.output.strip().splitlines()[-1]
    assert res.exit_code == 2 and last.startswith("error: --export-to:") and "--overwrite" in last
    assert (target / "sequences" / "00" / "predictions" / "000000.label").read_bytes() == b"mine"
    # One of the run's sequences alone: a run of it in the same folder, the other's folder untouched.
    other = _tree(out / "sequences" / "01")
    res = _cli("run", str(streets["00"]), "--out", str(out))
    assert res.exit_code == 0, res.output
    assert "stages: labels2d cached" in res.output and "== sequence" not in res.output
    assert "sequence 01" not in res.output and "5 .label files" in res.output
    assert _tree(out / "sequences" / "01") == other
    assert RunLayout(out).names() == ["00"]
    # Another process in the folder (the app's worker, another `leap run`): refused, nothing touched.
    from app.jobs.worker import run_dir_lock

    state = (out / "sequences" / "00" / "stages.json").read_bytes()
    with run_dir_lock(out):
        res = _cli("run", str(streets["00"]), str(streets["01"]), "--out", str(out), "--no-3dcn")
    assert res.exit_code == 2 and "another process is working in this run folder" in res.output, res.output
    assert (out / "sequences" / "00" / "stages.json").read_bytes() == state


def test_cli_run_of_another_sequence_in_a_run_folder_gets_its_own_folder(streets, tmp_path) -> None:
    """`leap run B --out OUT` where OUT holds a run of A: B is labeled in OUT/sequences/B/ from scratch, A's
    folder stays as it was, and `leap run A --out OUT` again finds A's stages current."""
    out = tmp_path / "run"
    first = _cli("run", str(streets["00"]), "--out", str(out), "--frames", "0:2")
    assert first.exit_code == 0, first.output
    kept = _tree(out / "sequences" / "00")
    res = _cli("run", str(streets["01"]), "--out", str(out), "--frames", "0:2")
    assert res.exit_code == 0, res.output
    assert "cached" not in res.output.split("stages: ")[1].splitlines()[0]
    assert f"2 .label files (+ .conf confidences) in {out / 'sequences' / '01' / 'export'}" in res.output
    assert _tree(out / "sequences" / "00") == kept
    assert RunLayout(out).names() == ["01"]
    assert list(json.loads(RunLayout(out).metrics.read_text())["sequences"]) == ["01"]
    again = _cli("run", str(streets["00"]), "--out", str(out), "--frames", "0:2")
    assert again.exit_code == 0, again.output
    timing = again.output.split("stages: ")[1].splitlines()[0]
    assert timing.count("cached") == 8 and "3dcn skipped" in timing, timing
    assert RunLayout(out).names() == ["00"]


def test_cli_refuses_duplicate_names_and_non_sequences(streets, tmp_path) -> None:
    twin = tmp_path / "z" / "sequences" / "00"
    shutil.copytree(streets["00"], twin)
    res = _cli("run", str(streets["00"]), str(twin), "--out", str(tmp_path / "r"))
    last = res.output.strip().splitlines()[-1]
    assert res.exit_code == 2 and "duplicate sequence name '00'" in last, res.output
    res = _cli("run", str(streets["00"]), str(tmp_path / "z"), "--out", str(tmp_path / "r"))
    last = res.output.strip().splitlines()[-1]
    assert res.exit_code == 2 and f"{tmp_path / 'z'}: not a sequence folder" in last and "velodyne" in last
    assert not (tmp_path / "r").exists()


def test_a_sequence_folder_of_a_run_is_refused_as_a_run_folder(plain, streets, schema, tmp_path) -> None:
    """A run folder given as the sequence folder of another run (``--out RUN/sequences/00``): refused,
    naming the run, with the run's files untouched (not moved as a run folder of an earlier version)."""
    multi, _, _ = plain
    out = tmp_path / "multi"
    shutil.copytree(multi.root, out)
    before = _tree(out)
    with pytest.raises(LeapError, match=rf"sequence 00 of the run {out}"):
        run_pipeline([SequenceSpec.of(streets["00"])], schema, PipelineConfig(), out / "sequences" / "00")
    assert _tree(out) == before
