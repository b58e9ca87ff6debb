"""Multi-sequence runs (leap_core.pipeline.multi): two tiny ray-cast streets labeled in one run, their
exports and metrics, the joint 3D-CN, resume, and `leap run A B ...`."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.errors import Cancelled, ConfigError, LeapError
from leap_core.export import ExportConflict, load_label_map
from leap_core.metrics import metrics_from_confusion
from leap_core.pipeline import (
    JOINT,
    PROTOCOLS,
    SequenceSpec,
    export_sequences,
    export_zip,
    overall_metrics,
    run_pipeline,
    run_sequences,
)
from leap_core.pipeline.context import read_state
from leap_core.run_layout import MultiRunLayout, RunLayout, is_multi_run, save_corrections
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
    """A multi run without the 3D-CN, and an ordinary run of each sequence."""
    runs = tmp_path_factory.mktemp("plain")
    calls: list[tuple[str, str, int, int]] = []
    multi = run_sequences(
        _specs(streets), schema, PipelineConfig(), runs / "multi", progress=lambda *a: calls.append(a)
    )
    singles = {
        name: run_pipeline(path, schema, PipelineConfig(), runs / f"single-{name}")
        for name, path in streets.items()
    }
    return multi, singles, calls


# ------------------------------------------------------------------------------------- without 3D-CN
def test_without_3dcn_every_sequence_equals_its_ordinary_run(plain, streets) -> None:
    multi, singles, calls = plain
    layout = MultiRunLayout(multi.root)
    assert is_multi_run(multi.root) and not is_multi_run(singles["00"].run_dir)
    assert layout.names() == ["00", "01"] == list(multi.per_sequence)
    for name, single in singles.items():
        member = layout.sequence(name)
        assert member.run_dir == multi.root / "sequences" / name
        assert multi.per_sequence[name].ran == single.ran
        labels = _files(member.export_dir)
        assert labels and labels == _files(single.run_dir / "export")  # .label and .conf, byte for byte
        assert len(labels) == 2 * len(list((streets[name] / "velodyne").glob("*.bin")))
        # Same fingerprints too: an ordinary run in the member folder would find every stage current.
        fps = {s: r["fingerprint"] for s, r in read_state(member).items()}
        assert fps == {s: r["fingerprint"] for s, r in read_state(RunLayout(single.run_dir)).items()}
        assert not member.joint_3dcn.exists()
    assert {c[0] for c in calls} == {"00", "01"}
    assert ("01", "export", 4, 4) in calls


def test_overall_metrics_are_those_of_the_summed_confusion_matrices(plain) -> None:
    multi, singles, _ = plain
    data = json.loads(MultiRunLayout(multi.root).metrics.read_text())
    assert data == multi.metrics
    assert data["sequences"] == {n: s.metrics for n, s in singles.items()}
    overall = data["overall"]
    assert overall["sequences"] == ["00", "01"]
    names, cats = overall["class_names"], overall["categories"]
    for p in PROTOCOLS:
        for row in overall["rows"]:
            summed = sum(np.asarray(s.metrics[p][row]["confusion"]) for s in singles.values())
            assert overall[p][row]["confusion"] == summed.tolist()
            expected = metrics_from_confusion(summed, names, cats, ignore_unlabeled_pred=p != "all")
            assert overall[p][row] == expected.to_dict()
    n = [s.metrics["n_points"] for s in singles.values()]
    assert overall["n_points"] == sum(n)
    # Not the mean of the sequences' mIoUs: the sequences differ, so the two differ.
    mean = np.mean([s.metrics["all"]["voxel"]["miou"] for s in singles.values()])
    assert overall["all"]["voxel"]["miou"] != pytest.approx(mean, abs=1e-9)


def test_overall_metrics_refuse_disagreeing_sequences_and_skip_missing_ones(plain) -> None:
    _, singles, _ = plain
    a, b = singles["00"].metrics, singles["01"].metrics
    assert overall_metrics({"00": a, "01": None})["sequences"] == ["00"]
    assert overall_metrics({"00": None}) is None
    with pytest.raises(LeapError, match="sequence 01: metrics rows"):
        overall_metrics({"00": a, "01": {**b, "rows": ["point"]}})


def test_export_writes_the_semantickitti_layout_and_never_replaces_silently(plain, streets, tmp_path) -> None:
    multi, _, _ = plain
    target = tmp_path / "dataset"
    written = export_sequences(multi.root, target)
    assert written == {"00": 5, "01": 4}
    for name in ("00", "01"):
        preds = target / "sequences" / name / "predictions"
        assert _files(preds) == _files(MultiRunLayout(multi.root).sequence(name).export_dir, "*.label")
    (target / "sequences" / "01" / "predictions" / "000000.label").write_bytes(b"mine")
    with pytest.raises(ExportConflict, match="already holds"):
        export_sequences(multi.root, target)
    assert (target / "sequences" / "01" / "predictions" / "000000.label").read_bytes() == b"mine"
    assert export_sequences(multi.root, target, overwrite=True, with_conf=True) == {"00": 10, "01": 8}
    assert (target / "sequences" / "01" / "predictions" / "000000.label").read_bytes() != b"mine"
    assert len(list((target / "sequences" / "00" / "confidences").glob("*.conf"))) == 5
    # A dataset's own folders: sequences/00/labels would be the ground truth's folder.
    dataset_root = streets["00"].parent.parent
    gt = _files(streets["00"] / "labels")
    bad = tmp_path / "bad"
    (bad / "sequences" / "00" / "velodyne").mkdir(parents=True)
    with pytest.raises(LeapError, match="inside the dataset folder"):
        export_sequences(multi.root, bad / "sequences" / "00" / "velodyne")
    with pytest.raises(LeapError, match="inside the pipeline run folder"):
        export_sequences(multi.root, MultiRunLayout(multi.root).sequence("00").run_dir)
    # Into the dataset root itself: predictions/ beside labels/, the ground truth untouched.
    export_sequences(multi.root, dataset_root, names=["00"])
    assert _files(streets["00"] / "labels") == gt
    assert len(list((streets["00"] / "predictions").glob("*.label"))) == 5
    shutil.rmtree(streets["00"] / "predictions")


def test_export_zip_holds_every_sequence(plain, schema, tmp_path) -> None:
    multi, _, _ = plain
    path = tmp_path / "all.zip"
    assert export_zip(multi.root, path, schema, raw_counts={0: 3, 40: 5}) == 9
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        lm = load_label_map(zf.read("label-map.yaml").decode())
        assert sum(n.endswith(".label") and "/predictions/" in n for n in names) == 9
        assert "sequences/01/predictions/000003.label" in names and "summary.yaml" in names
        raw = yaml_safe(zf.read("label-map.yaml").decode())
    assert raw["split"]["valid"] == [0, 1] and lm.counts[40] == 5
    with pytest.raises(ExportConflict):
        export_zip(multi.root, path, schema)


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
        run_sequences(dup, schema, PipelineConfig(), tmp_path / "m")
    assert err.value.field == ("sequences", "1", "name")
    with pytest.raises(LeapError, match="velodyne"):
        run_sequences([SequenceSpec("a", tmp_path)], schema, PipelineConfig(), tmp_path / "m")
    assert not (tmp_path / "m").exists()  # refused before any work
    single = tmp_path / "single"
    run_pipeline(streets["01"], schema, PipelineConfig(), single, until="labels2d")
    with pytest.raises(LeapError, match="a single-sequence run folder"):
        run_sequences(_specs(streets), schema, PipelineConfig(), single)


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
            run_sequences(_specs(streets), schema, PipelineConfig(), out, progress=cancel)
    assert read_state(MultiRunLayout(out).sequence("00"))["export"]["status"] == "done"
    result = run_sequences(_specs(streets), schema, PipelineConfig(), out)
    assert result.per_sequence["00"].ran == []
    assert result.per_sequence["01"].stages["labels2d"].frames_computed == 2  # 2 of 4 were kept
    for name in ("00", "01"):
        assert _files(MultiRunLayout(out).sequence(name).export_dir) == _files(
            MultiRunLayout(multi.root).sequence(name).export_dir
        )
    assert result.metrics == multi.metrics


# ---------------------------------------------------------------------------------------- joint 3D-CN
@pytest.mark.slow
def test_a_one_sequence_joint_3dcn_is_the_single_3dcn(plain, streets, schema, tmp_path) -> None:
    import torch

    _, singles, _ = plain
    cfg = config_from_dict({"consistency": TINY_3DCN})
    single_dir = tmp_path / "single"
    shutil.copytree(singles["01"].run_dir, single_dir)
    run_pipeline(streets["01"], schema, cfg, single_dir)
    multi = run_sequences([SequenceSpec.of(streets["01"])], schema, cfg, tmp_path / "multi")
    member = MultiRunLayout(multi.root).sequence("01")
    assert member.joint_3dcn.is_file()
    for it in (1, 2):
        for grid in (member.grid_3dcn(it), member.grid_smooth_3dcn(it)):
            assert grid.read_bytes() == (single_dir / grid.name).read_bytes()
        ckpt = MultiRunLayout(multi.root).cn_dir / f"3dcn_iter{it}.pt"
        a, b = (torch.load(p, weights_only=True) for p in (ckpt, single_dir / "3dcn" / ckpt.name))
        assert a["meta"].pop("seconds") > 0 and b["meta"].pop("seconds") > 0  # wall time: the only difference
        assert a["meta"] == b["meta"] and a["config"] == b["config"]
        assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in b["state_dict"])
    assert _files(member.export_dir) == _files(single_dir / "export")
    assert multi.per_sequence["01"].metrics == json.loads((single_dir / "metrics.json").read_text())


@pytest.fixture(scope="module")
def joint(streets, schema, tmp_path_factory: pytest.TempPathFactory):
    # new_voxel_margin 0: every voxel the network predicts is created (this tiny network is sure of few).
    cfg = config_from_dict({"consistency": {**TINY_3DCN, "iterations": 1, "new_voxel_margin": 0.0}})
    calls: list[tuple[str, str, int, int]] = []
    result = run_sequences(
        _specs(streets),
        schema,
        cfg,
        tmp_path_factory.mktemp("joint") / "multi",
        progress=lambda *a: calls.append(a),
    )
    return result, cfg, calls


@pytest.mark.slow
def test_the_joint_3dcn_trains_one_network_on_every_sequence(joint) -> None:
    import torch

    result, _, calls = joint
    layout = MultiRunLayout(result.root)
    meta = torch.load(layout.cn_dir / "3dcn_iter1.pt", weights_only=True)["meta"]
    assert meta["frames"] == [["00", 0, 5, 1], ["01", 0, 4, 1]]
    assert meta["steps"] == 5 + 4  # one step per scan of either sequence (min_steps 0)
    assert (JOINT, "3dcn", 1000, 1000) in calls
    for name in ("00", "01"):
        member = layout.sequence(name)
        assert not member.cn_dir.exists() or not any(member.cn_dir.iterdir())  # no network of its own
        assert member.grid_smooth_3dcn(1).samefile(layout.joint_rounds(name).grid_smooth_3dcn(1))
        assert result.per_sequence[name].metrics["rows"] == ["point", "voxel", "+3D-CN x1"]
        with np.load(member.points("000000")) as z:
            assert (z["label"] >= 0).all()  # the network labels every point
    assert result.metrics["overall"]["rows"] == ["point", "voxel", "+3D-CN x1"]


@pytest.mark.slow
def test_a_change_in_one_sequence_reruns_the_3dcn_of_all(joint, streets, schema, tmp_path) -> None:
    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    staged = MultiRunLayout(out).joint_rounds("00").grid_3dcn(1)
    before = staged.stat().st_mtime_ns
    again = run_sequences(_specs(streets), schema, cfg, out)
    assert all(r.ran == [] for r in again.per_sequence.values())
    assert staged.stat().st_mtime_ns == before  # the finished round was kept, not recomputed
    # A correction in sequence 01 changes its fused grid, hence what the joint network trains on.
    member = MultiRunLayout(out).sequence("01")
    with np.load(member.grid) as z:
        keys = np.asarray(z["keys"][:50])
    save_corrections(member.corrections, keys, np.zeros(len(keys), np.int64))
    changed = run_sequences(_specs(streets), schema, cfg, out)
    assert changed.per_sequence["01"].ran == ["fuse", "smooth", "3dcn", "label_points", "evaluate", "export"]
    assert changed.per_sequence["00"].ran == ["3dcn", "label_points", "evaluate", "export"]
    old = MultiRunLayout(result.root).sequence("00").grid_3dcn(1).read_bytes()
    assert MultiRunLayout(out).sequence("00").grid_3dcn(1).read_bytes() != old


def test_a_source_network_starts_the_joint_3dcn_and_is_part_of_its_fingerprint(
    joint, streets, schema, tmp_path
) -> None:
    from leap_core.consistency.train import load_checkpoint
    from leap_core.io_utils import file_digest
    from leap_core.runtime import Runtime

    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    source = tmp_path / "source.pt"
    shutil.copy(MultiRunLayout(out).cn_dir / "3dcn_iter1.pt", source)
    runtime = Runtime(init_3dcn=source)
    tuned = run_sequences(_specs(streets), schema, cfg, out, runtime=runtime)
    assert all(r.ran == ["3dcn", "label_points", "evaluate", "export"] for r in tuned.per_sequence.values())
    meta = load_checkpoint(MultiRunLayout(out).cn_dir / "3dcn_iter1.pt").meta
    assert meta["source"] == file_digest(source)
    again = run_sequences(_specs(streets), schema, cfg, out, runtime=runtime)
    assert all(r.ran == [] for r in again.per_sequence.values())
    back = run_sequences(_specs(streets), schema, cfg, out)  # no source: the random-weight network again
    assert all(r.ran == ["3dcn", "label_points", "evaluate", "export"] for r in back.per_sequence.values())


@pytest.mark.slow
def test_sequences_seeded_from_an_earlier_run_keep_their_joint_3dcn(joint, streets, schema, tmp_path) -> None:
    """The app starts a run by linking the last run's sequence folders into a fresh root: with nothing
    changed, no network is trained again, though the fresh root has no checkpoints or staged rounds."""
    result, cfg, _ = joint
    out = tmp_path / "multi"
    shutil.copytree(result.root / "sequences", out / "sequences")
    again = run_sequences(_specs(streets), schema, cfg, out)
    assert all(r.ran == [] for r in again.per_sequence.values())
    assert not (MultiRunLayout(out).cn_dir / "3dcn_iter1.pt").exists()
    assert again.metrics == result.metrics


@pytest.mark.slow
def test_joint_3dcn_resumes_after_cancel(joint, streets, schema, tmp_path) -> None:
    result, cfg, _ = joint
    out = tmp_path / "multi"

    ckpt = MultiRunLayout(out).cn_dir / "3dcn_iter1.pt"

    def cancel(name: str, _stage: str, done: int, _total: int) -> None:
        if name == JOINT and ckpt.is_file() and done < 1000:  # trained, not yet fused back
            raise Cancelled()

    with pytest.raises(Cancelled):
        run_sequences(_specs(streets), schema, cfg, out, progress=cancel)
    trained = ckpt.stat().st_mtime_ns
    again = run_sequences(_specs(streets), schema, cfg, out)
    assert ckpt.stat().st_mtime_ns == trained  # the checkpoint was reused, not retrained
    assert again.per_sequence["00"].ran == ["3dcn", "label_points", "evaluate", "export"]
    for name in ("00", "01"):
        assert _files(MultiRunLayout(out).sequence(name).export_dir) == _files(
            MultiRunLayout(result.root).sequence(name).export_dir
        )


@pytest.mark.slow
def test_switching_the_3dcn_off_gives_the_ordinary_runs_again(
    joint, plain, streets, schema, tmp_path
) -> None:
    result, _, _ = joint
    multi, _, _ = plain
    out = tmp_path / "multi"
    shutil.copytree(result.root, out)
    off = run_sequences(_specs(streets), schema, PipelineConfig(), out)
    for name in ("00", "01"):
        member = MultiRunLayout(out).sequence(name)
        assert not member.joint_3dcn.exists()
        assert off.per_sequence[name].ran == ["label_points", "evaluate", "export"]
        assert _files(member.export_dir) == _files(MultiRunLayout(multi.root).sequence(name).export_dir)
    assert off.metrics == multi.metrics


def test_an_ordinary_runs_3dcn_fingerprint_is_unchanged_by_the_joint_input(plain, streets, schema) -> None:
    """The joint record is an optional input of the 3dcn stage: an ordinary 3D-CN run's fingerprint is the
    one it had before multi-sequence runs existed (config section, less the fields added at their former
    value, and upstream only), so existing run folders keep their 3D-CN, and the record, when present,
    changes it."""
    from leap_core.config import config_to_dict
    from leap_core.consistency.config import fingerprint_form
    from leap_core.pipeline import PIPELINE_VERSION, stage_fingerprints
    from leap_core.pipeline.context import hash_json

    _, singles, _ = plain
    cfg = config_from_dict({"consistency": TINY_3DCN})
    run_dir = singles["00"].run_dir
    fp = stage_fingerprints(streets["00"], schema, cfg, run_dir)
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
    note = RunLayout(run_dir).joint_3dcn
    note.write_text("{}")
    try:
        assert stage_fingerprints(streets["00"], schema, cfg, run_dir)["3dcn"] != before
    finally:
        note.unlink()


def test_a_member_without_its_joint_round_is_refused(plain, streets, schema, tmp_path) -> None:
    multi, _, _ = plain
    out = tmp_path / "multi"
    shutil.copytree(multi.root, out)
    member = MultiRunLayout(out).sequence("00")
    member.joint_3dcn.write_text(json.dumps({"fingerprint": "x", "name": "00"}))
    cfg = config_from_dict({"consistency": TINY_3DCN})
    with pytest.raises(LeapError, match="joint 3D-CN has not run for these settings"):
        run_pipeline(streets["00"], schema, cfg, member.run_dir)


# ----------------------------------------------------------------------------------------------- CLI
def _cli(*args: str):
    from typer.testing import CliRunner

    from app.cli import cli

    return CliRunner().invoke(cli, list(args))


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
    # A single-sequence run never goes into a multi-sequence folder, nor the reverse.
    res = _cli("run", str(streets["00"]), "--out", str(out))
    assert res.exit_code == 2 and "a multi-sequence run folder" in res.output
    res = _cli("run", str(streets["00"]), str(streets["01"]), "--out", str(out / "sequences" / "00"))
    assert res.exit_code == 2 and "a single-sequence run folder" in res.output
    # Another process in the folder (the app's worker, another `leap run`): refused, nothing touched.
    from app.jobs.worker import run_dir_lock

    state = (out / "sequences" / "00" / "stages.json").read_bytes()
    with run_dir_lock(out):
        res = _cli("run", str(streets["00"]), str(streets["01"]), "--out", str(out), "--no-3dcn")
    assert res.exit_code == 2 and "another process is working in this run folder" in res.output, res.output
    assert (out / "sequences" / "00" / "stages.json").read_bytes() == state


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
