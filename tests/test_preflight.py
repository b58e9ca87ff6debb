"""The pre-flight dataset check (leap_core/pipeline/preflight.py) and ``leap check`` on bad folders: what
is missing, what still runs, the fix worded for the command line or the app (app/advice.py), and the exit
codes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from conftest import TinySequence, build_tiny_sequence
from typer.testing import CliRunner

from app.advice import ADVICE, advice, render_cli, report_dict, setting_fix
from app.cli import CHECK_EXIT_CODES, cli
from leap_core.config import config_from_dict
from leap_core.datasets.kitti import POSES_NOTE, write_png16
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.pipeline.preflight import REASONS, check_dataset, dataset_stamp, report_data
from leap_core.runtime import Runtime

SIMULATED = config_from_dict({"labeler": "simulated"})


def _gt2d(seq: TinySequence) -> None:
    import numpy as np

    for fid in seq.frame_ids:
        for kind in ("semantic", "instance"):
            write_png16(seq.root / "gt2d" / kind / f"{fid}.png", np.full((48, 64), 40, np.uint16))


@pytest.fixture
def seq(tmp_path: Path) -> TinySequence:
    s = build_tiny_sequence(tmp_path / "data", n_frames=4, n_points=40)
    _gt2d(s)
    return s


def _stages(report) -> dict[str, str]:  # type: ignore[no-untyped-def]
    return {s.name: s.state for s in report.stages}


def test_a_complete_sequence_can_run_every_stage(seq: TinySequence) -> None:
    r = check_dataset(seq.root, config=SIMULATED, check_models=False)
    assert r.verdict == "full" and r.frames == 4 and (r.first_frame, r.last_frame) == ("000000", "000003")
    assert (r.images.kind, r.ground_truth.kind, r.gt2d.kind) == ("all", "all", "all")
    assert r.calib.valid and r.poses.source == "file" and r.poses.lines == 4
    assert _stages(r) == {
        "labels2d": "runs",
        "project": "runs",
        "motion": "skipped",
        "fuse": "runs",
        "smooth": "runs",
        "3dcn": "skipped",
        "label_points": "runs",
        "tracks": "runs",
        "evaluate": "runs",
        "export": "runs",
    }
    assert not [f for f in r.findings if f.severity != "info"]


def test_without_poses_only_the_3d_stages_are_blocked(seq: TinySequence) -> None:
    (seq.root / "poses.txt").unlink()
    r = check_dataset(seq.root, config=SIMULATED, check_models=False)
    assert r.verdict == "partial" and r.poses.source == "missing"
    states = _stages(r)
    assert states["labels2d"] == states["project"] == "runs"
    three_d = ("fuse", "smooth", "3dcn", "label_points", "tracks", "evaluate", "export")
    assert all(states[s] == "blocked" for s in three_d)
    f = r.finding("poses_missing")
    assert f is not None and f.path == str(seq.root / "poses.txt")
    assert f"leap poses {seq.root}" in advice(f, "cli", r) and "--estimate-poses" in advice(f, "cli", r)
    assert "Estimate poses (KISS-ICP)" in advice(f, "app", r) and "--" not in advice(f, "app", r)
    # With the poses to be estimated first, every stage can run.
    later = check_dataset(seq.root, config=SIMULATED, check_models=False, estimate_poses=True)
    assert later.verdict == "full"


def test_estimated_poses_are_reported_with_their_method(seq: TinySequence) -> None:
    (seq.root / POSES_NOTE).write_text(json.dumps({"method": "kiss-icp", "version": "1.3.0"}))
    r = check_dataset(seq.root, config=SIMULATED, check_models=False)
    assert r.poses.source == "estimated" and r.poses.method == "kiss-icp" and r.verdict == "full"


def test_folders_nothing_can_run_on_are_reported_not_raised(seq: TinySequence, tmp_path: Path) -> None:
    def verdict_and_codes(path: Path) -> tuple[str, list[str]]:
        r = check_dataset(path, config=SIMULATED, check_models=False)
        return r.verdict, [f.code for f in r.findings if f.severity == "blocker"]

    assert verdict_and_codes(tmp_path / "nope") == ("none", ["not_a_folder"])
    assert verdict_and_codes(tmp_path / "data") == ("none", ["not_a_sequence"])  # the dataset root
    r = check_dataset(tmp_path / "data", check_models=False)
    assert "holds sequence folders: 00" in r.findings[0].detail

    empty = tmp_path / "empty"
    (empty / "velodyne").mkdir(parents=True)
    assert verdict_and_codes(empty) == ("none", ["no_scans"])

    no_calib = shutil.copytree(seq.root, tmp_path / "nocalib")
    (no_calib / "calib.txt").unlink()
    assert verdict_and_codes(no_calib) == ("none", ["calib_missing"])

    corrupt = shutil.copytree(seq.root, tmp_path / "corrupt")
    (corrupt / "calib.txt").write_bytes(b"P2: 1 2 x\n\xff\xfe")
    v, codes = verdict_and_codes(corrupt)
    assert v == "none" and codes == ["calib_invalid"]

    bare = shutil.copytree(seq.root, tmp_path / "bare", ignore=shutil.ignore_patterns("image_2", "gt2d"))
    assert verdict_and_codes(bare) == ("none", ["no_2d_input"])

    times = shutil.copytree(seq.root, tmp_path / "times")
    (times / "times.txt").write_text("0.0\nnot a number\n")
    v, codes = verdict_and_codes(times)
    assert v == "none" and codes == ["unreadable"]
    r = check_dataset(times, check_models=False)
    assert r.findings[-1].path == str(times / "times.txt") or any(
        f.path == str(times / "times.txt") for f in r.findings
    )

    damaged = shutil.copytree(seq.root, tmp_path / "damaged")
    (damaged / "velodyne" / "000001.bin").write_bytes(b"\0" * 17)
    r = check_dataset(damaged, check_models=False)
    f = r.finding("scans_damaged")
    assert r.verdict == "none" and f is not None and f.frames == ("000001",)


def test_labelers_and_their_inputs(seq: TinySequence, tmp_path: Path) -> None:
    real = shutil.copytree(seq.root, tmp_path / "real", ignore=shutil.ignore_patterns("gt2d"))
    r = check_dataset(real, config=SIMULATED, runtime=Runtime(models_dir=tmp_path / "models"))
    labelers = {lab.name: lab for lab in r.labelers}
    assert not labelers["simulated"].can_run and labelers["simulated"].reasons == ("gt2d_missing",)
    assert labelers["grounded-sam"].reasons == ("models_missing",)
    assert r.verdict == "partial" and _stages(r)["labels2d"] == "blocked"
    f = r.finding("models_missing")
    assert f is not None and f.severity == "warning"  # the simulated labeler cannot run: they matter
    assert f.path == str(tmp_path / "models") and "grounding-dino-tiny/" in f.detail
    f = r.finding("labeler_cannot_run")
    assert f is not None and "could, given its models" in f.detail
    assert advice(f, "cli", r) == "use --labeler grounded-sam"
    # Where the chosen labeler runs, missing models are only a fact.
    f = check_dataset(seq.root, config=SIMULATED, runtime=Runtime(models_dir=tmp_path / "models")).finding(
        "models_missing"
    )
    assert f is not None and f.severity == "info"

    models = make_tiny_models(tmp_path / "models", TinyModelsConfig(num_queries=8)).models_dir
    r = check_dataset(real, runtime=Runtime(models_dir=models))  # no config: the first labeler that can run
    assert r.labeler == "grounded-sam" and not r.labeler_chosen and r.verdict == "full"
    assert [f.code for f in r.findings if f.severity == "warning"] == ["models_random", "models_random"]

    r = check_dataset(real, config=SIMULATED, runtime=Runtime(models_dir=models))
    f = r.finding("labeler_cannot_run")
    assert f is not None and advice(f, "cli", r) == "use --labeler grounded-sam"
    assert advice(f, "app", r) == 'choose "Grounding DINO + SAM" as the 2D labeler under Parameters'

    gap = shutil.copytree(seq.root, tmp_path / "gap")
    (gap / "image_2" / "000002.png").unlink()
    (gap / "labels" / "000003.label").unlink()
    r = check_dataset(gap, config=SIMULATED, check_models=False)
    assert r.images.present == 3 and r.finding("images_partial").frames == ("000002",)  # type: ignore[union-attr]
    assert r.ground_truth.kind == "some" and _stages(r)["evaluate"] == "skipped"
    assert r.verdict == "full"  # the simulated labeler reads 2D ground truth; evaluation is merely skipped


def test_poses_are_indexed_by_frame_number(seq: TinySequence, tmp_path: Path) -> None:
    """Frames 000001 and 000003 alone with the full 4-line poses.txt: every scan has its line."""
    sub = shutil.copytree(seq.root, tmp_path / "sub")
    for fid in ("000000", "000002"):
        for part in (
            "velodyne/{}.bin",
            "image_2/{}.png",
            "labels/{}.label",
            "gt2d/semantic/{}.png",
            "gt2d/instance/{}.png",
        ):
            (sub / part.format(fid)).unlink()
    r = check_dataset(sub, config=SIMULATED, check_models=False)
    assert r.frames == 2 and r.poses.lines == 4 and r.finding("poses_short") is None
    assert r.verdict == "full" and r.finding("poses_extra") is not None

    short = shutil.copytree(seq.root, tmp_path / "short")
    (short / "poses.txt").write_text("".join((short / "poses.txt").read_text().splitlines(True)[:2]))
    r = check_dataset(short, config=SIMULATED, check_models=False)
    f = r.finding("poses_short")
    assert f is not None and f.frames == ("000002", "000003") and f.count == 2


def test_app_wording_never_names_a_flag(seq: TinySequence, tmp_path: Path) -> None:
    variants = []
    for drop in ("poses.txt", "gt2d", "image_2", "calib.txt", "labels"):
        folder = shutil.copytree(
            seq.root, tmp_path / drop.replace(".", "_"), ignore=shutil.ignore_patterns(drop)
        )
        variants.append(check_dataset(folder, config=SIMULATED, runtime=Runtime(models_dir=tmp_path / "m")))
    variants.append(check_dataset(tmp_path / "nope"))
    for r in variants:
        data = report_dict(r, "app")
        for f in data["findings"]:
            assert "--" not in f["fix"] and "leap " not in f["fix"], f
        cli_text = render_cli(r)
        assert "verdict:" in cli_text


def test_leap_core_reports_codes_and_the_app_words_their_fixes(seq: TinySequence, tmp_path: Path) -> None:
    # Every finding code has its fix in both wordings, and no other code has one.
    assert set(ADVICE) == set(REASONS)
    folder = shutil.copytree(seq.root, tmp_path / "np", ignore=shutil.ignore_patterns("poses.txt"))
    r = check_dataset(folder, config=SIMULATED)
    neutral = report_data(r)
    assert [f["code"] for f in neutral["findings"]] == [f.code for f in r.findings] and neutral["findings"]
    assert all("fix" not in f for f in neutral["findings"])  # leap_core gives no advice
    for audience in ("cli", "app"):
        worded = report_dict(r, audience)
        assert [{k: v for k, v in f.items() if k != "fix"} for f in worded["findings"]] == neutral["findings"]
        assert [f["fix"] for f in worded["findings"]] == [advice(f, audience, r) for f in r.findings]
        assert {k: v for k, v in worded.items() if k != "findings"} == {
            k: v for k, v in neutral.items() if k != "findings"
        }


def test_the_stamp_follows_the_folder(seq: TinySequence) -> None:
    before = dataset_stamp(seq.root)
    assert dataset_stamp(seq.root) == before
    (seq.root / "image_2" / "000001.png").unlink()
    assert dataset_stamp(seq.root) != before


def test_leap_check_prints_the_report_and_exits_by_verdict(seq: TinySequence, tmp_path: Path) -> None:
    runner = CliRunner()
    ok = runner.invoke(cli, ["check", str(seq.root), "--labeler", "simulated"])
    assert ok.exit_code == CHECK_EXIT_CODES["full"] == 0, ok.output
    assert "verdict: every stage can run (exit code 0)" in ok.output
    assert "evaluate       runs" in ok.output

    (seq.root / "poses.txt").unlink()
    partial = runner.invoke(cli, ["check", str(seq.root), "--labeler", "simulated"])
    assert partial.exit_code == 1, partial.output
    assert "fuse           cannot run (no poses)" in partial.output
    assert f"fix: estimate them with `leap poses {seq.root}`" in partial.output

    none = runner.invoke(cli, ["check", str(tmp_path / "data")])
    assert none.exit_code == 3, none.output
    assert "no velodyne/ folder" in none.output

    as_json = runner.invoke(cli, ["check", str(seq.root), "--labeler", "simulated", "--json"])
    data = json.loads(as_json.output)
    assert data["verdict"] == "partial" and "leap poses" in data["findings"][0]["fix"]

    assert runner.invoke(cli, ["check", str(seq.root), "--labeler", "nope"]).exit_code == 2
    help_text = runner.invoke(cli, ["check", "--help"]).output
    assert "Exit codes" in help_text and "3 the pipeline cannot run" in " ".join(help_text.split())


def test_a_run_error_whose_advice_names_a_setting_is_recognised() -> None:
    """The app offers a new run with the project's settings beside Resume (which keeps the run's) exactly
    when the run's error carries advice that changes a setting, whichever advice that is."""
    named = {code: a for code, a in ADVICE.items() if a.setting}
    assert {"poses_missing", "labeler_cannot_run"} <= set(named)
    for code, entry in ADVICE.items():
        text = entry.app.format(alt_label="Simulated", seq="/data/00")
        assert setting_fix(f"/data/00/poses.txt: broken; {text}") == (entry.setting or None), code
    assert setting_fix("RuntimeError: out of memory") is None and setting_fix(None) is None
