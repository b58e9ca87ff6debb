"""What ``leap check`` and ``leap run`` say on folders as real data have them: the labeler both pick, the
verdict line against the stage list, advice that fits the folder, refusals that leave no run folder, the
run header, ``--seed``, the export's provenance and the classes the 2D labeler never found."""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import TinySequence, build_tiny_sequence
from runhelpers import folder
from typer.testing import CliRunner

from app.cli import cli
from leap_core.config import PipelineConfig
from leap_core.datasets.kitti import write_png16
from leap_core.errors import DatasetError
from leap_core.labelers.base import SoftMasks
from leap_core.labelers.tiny_models import TinyModelsConfig, make_tiny_models
from leap_core.pipeline import SequenceSpec, run_pipeline
from leap_core.pipeline.class_presence import class_pixels, silent_classes, warning_text
from leap_core.pipeline.preflight import LabelerCheck, check_dataset, pick_labeler, report_data, summary_text
from leap_core.pipeline.provenance import code_version
from leap_core.presets import load_preset
from leap_core.run_layout import RunLayout, read_run_pipeline
from leap_core.runtime import Runtime


def _invoke(*args: object) -> tuple[int, str]:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    return res.exit_code, res.output


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Tiny random-weight Grounding DINO + SAM folders (the grounded-sam code path, meaningless labels)."""
    return make_tiny_models(tmp_path_factory.mktemp("models"), TinyModelsConfig(num_queries=8)).models_dir


@pytest.fixture
def images_only(tmp_path: Path) -> TinySequence:
    """Scans, camera images, calibration, poses and 3D ground truth; no 2D ground truth (real data)."""
    return build_tiny_sequence(tmp_path / "img", n_frames=3, n_points=60)


@pytest.fixture
def with_gt2d(tmp_path: Path) -> TinySequence:
    """A sequence the simulated labeler reads: its 2D ground truth has road below, car and building above
    (raw ids 40, 10, 50), while its 3D ground truth also holds sidewalk (48) and vegetation (70)."""
    seq = build_tiny_sequence(tmp_path / "gt2d", n_frames=3, n_points=200)
    for fid in seq.frame_ids:
        sem = np.full((48, 64), 40, np.uint16)
        sem[:24, :32], sem[:24, 32:] = 10, 50
        inst = np.zeros((48, 64), np.uint16)
        inst[:24, :32] = 1
        write_png16(seq.root / "gt2d" / "semantic" / f"{fid}.png", sem)
        write_png16(seq.root / "gt2d" / "instance" / f"{fid}.png", inst)
    return seq


# ------------------------------------------------------------------------------- one labeler for both
def test_check_and_run_pick_the_same_labeler(images_only: TinySequence, models: Path, tmp_path: Path) -> None:
    """On camera images without 2D ground truth, ``leap check --models M`` judged grounded-sam while
    ``leap run --models M`` ran the simulated labeler and failed; both now pick the one that can run."""
    code, out = _invoke("check", images_only.root, "--models", models)
    assert code == 0 and "stages (labeler grounded-sam, picked by the check" in out, out
    run = tmp_path / "run"
    code, out = _invoke("run", images_only.root, "--models", models, "--out", run)
    assert code == 0, out
    assert "2D labels: grounded-sam (Grounding DINO + SAM), picked as the first labeler that can run" in out
    record = yaml.safe_load((folder(run) / "stages.json").read_text())["labels2d"]
    assert record["labeler"] == "grounded-sam" and record["status"] == "done"


def test_a_named_labeler_that_cannot_run_is_refused_naming_the_flag_that_works(
    images_only: TinySequence, models: Path, tmp_path: Path
) -> None:
    code, out = _invoke("run", images_only.root, "--labeler", "simulated", "--out", tmp_path / "r")
    assert code == 2
    assert f"error: {images_only.root}: the simulated labeler cannot run (no 2D ground truth); " in out
    assert "use --labeler grounded-sam" in out
    assert not (tmp_path / "r").exists()


def test_pick_labeler_wants_one_that_runs_on_every_sequence() -> None:
    def labs(sim: tuple[str, ...], gs: tuple[str, ...]) -> tuple[LabelerCheck, ...]:
        return (
            LabelerCheck("simulated", "s", not sim, sim),
            LabelerCheck("grounded-sam", "g", not gs, gs),
        )

    both = labs((), ())
    images = labs(("gt2d_missing",), ())
    no_models = labs(("gt2d_missing",), ("models_missing",))
    assert pick_labeler([both]) == "simulated"  # registry order
    assert pick_labeler([both, images]) == "grounded-sam"  # the one that runs on both
    assert pick_labeler([both, no_models]) == "grounded-sam"  # lacks only its models: the run says which
    assert pick_labeler([labs(("gt2d_missing",), ("images_missing",))]) is None
    assert pick_labeler([images], named="simulated") == "simulated"


# -------------------------------------------------------------------------------- the verdict line
def test_the_verdict_line_matches_the_stage_list(
    images_only: TinySequence, models: Path, tmp_path: Path
) -> None:
    """No 2D ground truth, no models, no poses and the simulated labeler named: every stage is blocked,
    and the verdict said "only some stages can run"."""
    (images_only.root / "poses.txt").unlink()
    code, out = _invoke("check", images_only.root, "--labeler", "simulated", "--models", tmp_path / "none")
    assert code == 1
    assert out.count("cannot run (") >= 10 + 2  # 10 stages and the 2 labelers
    assert "only some stages can run" not in out
    assert "verdict: no stage can run as set up (all 10 cannot run" in out
    # Some blocked, some not: the line counts them.
    code, out = _invoke("check", images_only.root, "--labeler", "grounded-sam", "--models", models)
    assert code == 1
    verdict = (
        "verdict: only some stages can run (8 of 10 cannot run: motion, fuse, smooth, 3dcn, label_points, "
    )
    assert verdict in out
    report = check_dataset(images_only.root, runtime=Runtime(models_dir=models))
    assert report_data(report)["summary"] == summary_text(report)  # what the app shows, too


# ------------------------------------------------------------------------ advice that fits the folder
def test_a_folder_without_images_is_not_told_to_use_its_images(tmp_path: Path) -> None:
    bare = build_tiny_sequence(tmp_path / "bare", n_frames=2, n_points=40, with_images=False)
    code, out = _invoke("run", bare.root, "--out", tmp_path / "r")
    assert code == 2 and not (tmp_path / "r").exists()
    assert "neither camera images (image_2/) nor 2D ground truth (gt2d/)" in out
    assert "fix: add camera images as image_2/NNNNNN.png" in out
    assert "for real camera images" not in out and "for its camera images" not in out
    # The run's own refusal (what the app shows) fits the folder too.
    preset = load_preset("semantickitti")
    with pytest.raises(DatasetError) as err:
        run_pipeline([SequenceSpec.of(bare.root)], preset.schema, PipelineConfig(), tmp_path / "direct")
    assert "the dataset has no camera images (image_2/) for the grounded-sam labeler either" in str(err.value)


def test_a_folder_of_images_is_pointed_at_the_labeler_that_reads_them(
    images_only: TinySequence, tmp_path: Path
) -> None:
    preset = load_preset("semantickitti")
    with pytest.raises(DatasetError) as err:
        run_pipeline([SequenceSpec.of(images_only.root)], preset.schema, PipelineConfig(), tmp_path / "r")
    assert "for its camera images (image_2/) choose the grounded-sam labeler" in str(err.value)


# ------------------------------------------------------------------------------ refused runs' folders
def test_a_run_refused_after_it_started_leaves_no_folder_but_never_removes_a_users_run(
    images_only: TinySequence, with_gt2d: TinySequence, tmp_path: Path
) -> None:
    # grounded-sam named, its models missing: the pre-flight lets it start, the model load refuses it.
    gone = tmp_path / "gone"
    code, out = _invoke(
        "run", images_only.root, "--labeler", "grounded-sam", "--models", tmp_path / "none", "--out", gone
    )
    assert code == 2 and "model folder for IDEA-Research/grounding-dino-tiny not found" in out, out
    assert not gone.exists()
    # A folder that held a run keeps it when a later run into it is refused.
    kept = tmp_path / "kept"
    code, out = _invoke("run", with_gt2d.root, "--labeler", "simulated", "--out", kept)
    assert code == 0, out
    before = sorted(p.relative_to(kept) for p in kept.rglob("*"))
    code, out = _invoke(
        "run", with_gt2d.root, "--labeler", "grounded-sam", "--models", tmp_path / "none", "--out", kept
    )
    assert code == 2
    assert RunLayout(kept).holds_results() and (folder(kept) / "export").is_dir()
    assert set(before) <= {p.relative_to(kept) for p in kept.rglob("*")}
    # An empty folder the user made is theirs too.
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _ = _invoke(
        "run", with_gt2d.root, "--labeler", "grounded-sam", "--models", tmp_path / "none", "--out", empty
    )
    assert code == 2 and empty.is_dir()


# ------------------------------------------------------------------------------ header and --seed
def test_the_run_header_names_the_labeler_once(with_gt2d: TinySequence, tmp_path: Path) -> None:
    code, out = _invoke("run", with_gt2d.root, "--out", tmp_path / "r")
    assert code == 0, out
    assert "2D labels: simulated (from 2D ground truth)\n" in out
    assert "simulated (simulated" not in out


def test_seed_reaches_the_labeler_and_the_stored_config(with_gt2d: TinySequence, tmp_path: Path) -> None:
    def soft(run: Path) -> list[SoftMasks]:
        return [SoftMasks.load(p) for p in sorted((folder(run) / "labels2d").glob("*.npz"))]

    runs = {}
    for name, seed in (("a", 1), ("b", 2), ("c", 1)):
        code, out = _invoke(
            "run", with_gt2d.root, "--labeler", "simulated", "--seed", seed, "--out", tmp_path / name
        )
        assert code == 0, out
        stored = read_run_pipeline(RunLayout(tmp_path / name))
        assert stored is not None and stored["simulated"]["seed"] == seed and stored["labeler"] == "simulated"
        runs[name] = soft(tmp_path / name)

    def same(x: list[SoftMasks], y: list[SoftMasks]) -> bool:
        return all(
            a.bits.shape == b.bits.shape
            and np.array_equal(a.bits, b.bits)
            and np.array_equal(a.probs, b.probs)
            and np.array_equal(a.confidence, b.confidence)
            for a, b in zip(x, y, strict=True)
        )

    assert same(runs["a"], runs["c"]) and not same(runs["a"], runs["b"])
    code, out = _invoke(
        "run", with_gt2d.root, "--labeler", "grounded-sam", "--seed", 3, "--out", tmp_path / "gs"
    )
    assert code == 2 and "--seed: the grounded-sam labeler draws nothing at random" in out
    assert not (tmp_path / "gs").exists()


# ------------------------------------------------------------------------------------ provenance
def test_the_zip_says_where_the_labels_came_from(
    images_only: TinySequence, models: Path, tmp_path: Path
) -> None:
    zip_path = tmp_path / "out.zip"
    code, out = _invoke(
        "run", images_only.root, "--models", models, "--out", tmp_path / "r", "--zip", zip_path
    )
    assert code == 0, out
    assert "labels: grounded-sam labeler, RANDOM-weight test models" in out
    assert f"poses: from the file {images_only.root / 'poses.txt'}" in out
    assert "corrections: none applied" in out and "code: leap-studio " in out
    with zipfile.ZipFile(zip_path) as zf:
        summary = yaml.safe_load(zf.read("summary.yaml"))
    prov = summary["provenance"]
    assert prov["labeler"]["name"] == "grounded-sam" and prov["labeler"]["weights"] == "random"
    assert prov["labeler"]["models"]["detector"] == "IDEA-Research/grounding-dino-tiny"
    assert prov["poses"] == [
        {"sequence": "00", "source": "file", "file": str(images_only.root / "poses.txt")}
    ]
    assert prov["corrections"] == [
        {"sequence": "00", "map_voxels": 0, "scan_points": 0, "scan_frames": 0, "digest": None}
    ]
    assert prov["code"]["package"] == summary["leap_studio_version"]
    # The fields an export had stay.
    assert {"sequences", "files", "counts", "settings", "leap_studio_version", "written_at"} <= set(summary)


def test_the_code_version_is_the_checkouts_commit_or_none() -> None:
    import subprocess

    import leap_core

    version = code_version()
    assert version["package"] == leap_core.__version__
    source = Path(leap_core.__file__).resolve().parent.parent
    head = subprocess.run(
        ["git", "-C", str(source), "rev-parse", "HEAD"], capture_output=True, text=True, check=False
    )
    if (source / ".git").exists() and head.returncode == 0:
        assert version["commit"] is not None and version["commit"].split("+")[0] == head.stdout.strip()
    else:  # an installed package, or a copy without git: no commit to name
        assert version["commit"] is None


# ------------------------------------------------------------------------------- silent classes
def test_classes_the_2d_labeler_never_found_are_warned_about(with_gt2d: TinySequence, tmp_path: Path) -> None:
    zip_path = tmp_path / "out.zip"
    code, out = _invoke("run", with_gt2d.root, "--out", tmp_path / "r", "--zip", zip_path)
    assert code == 0, out
    # The 2D ground truth has no sidewalk and no vegetation; the 3D ground truth has both.
    for name in ("sidewalk", "vegetation"):
        assert f"class '{name}' got no pixels from the 2D labeler in 3 frames, though the ground truth" in out
    assert "try other prompts" in out
    # A class absent from the ground truth too is not a prompt problem: not named.
    assert "class 'motorcycle'" not in out
    with zipfile.ZipFile(zip_path) as zf:
        silent = yaml.safe_load(zf.read("summary.yaml"))["provenance"]["silent_classes"]
    named = [s["class"] for s in silent]
    assert {"sidewalk", "vegetation"} <= set(named) and "motorcycle" not in named
    assert all(s["pixels"] == 0 and s["ground_truth_points"] > 0 and s["prompts"] for s in silent)
    assert f"classes the 2D labeler (almost) never found: {', '.join(named)}" in out


def test_class_pixels_and_the_silent_rule() -> None:
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :2] = True  # 8 pixels
    masks[1, 3, :2] = True  # 2 pixels
    soft = SoftMasks.from_dense(masks, [[0.75, 0.25, 0.0], [0.0, 0.4, 0.6]], [1.0, 1.0])
    np.testing.assert_allclose(class_pixels(soft), [8.0, 0.0, 2.0])  # each mask's area to its argmax
    names, prompts = ["a", "b", "c"], [["a"], ["bee", "b"], ["c"]]
    silent = silent_classes(names, prompts, [1e6, 10.0, 0.0], frames=5)
    assert [s.name for s in silent] == ["b", "c"]  # 10 px of a million is "almost no pixels"
    assert "almost no pixels" in warning_text(silent[0]) and "'bee', 'b'" in warning_text(silent[0])
    assert "it may be absent from these images" in warning_text(silent[1], "00")
    assert warning_text(silent[1], "00").startswith("sequence 00: class 'c' got no pixels")
    # With ground truth, only classes it holds.
    assert [s.name for s in silent_classes(names, prompts, [1e6, 10.0, 0.0], 5, [50, 0, 50])] == ["c"]


def test_a_run_with_several_sequences_needs_a_labeler_for_all(
    images_only: TinySequence, with_gt2d: TinySequence, models: Path, tmp_path: Path
) -> None:
    """One sequence with 2D ground truth, one without: the simulated labeler cannot label both, so the run
    picks grounded-sam (the check's rule, over every sequence)."""
    other = shutil.copytree(images_only.root, tmp_path / "two" / "b")
    code, out = _invoke("run", with_gt2d.root, other, "--models", models, "--out", tmp_path / "r")
    assert code == 0, out
    assert (
        "2D labels: grounded-sam (Grounding DINO + SAM), picked as the first labeler that can run on every"
        in out
    )
