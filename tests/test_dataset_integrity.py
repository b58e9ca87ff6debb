"""Per-frame files the reader must not trust: links leading out of the sequence folder (never opened, named
by the check and by ``leap run``), entries that are directories or pipes, truncated camera images and
images of another size. The app's side (a real server) is tests/app/test_dataset_integrity_api.py."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import TinySequence, build_tiny_sequence
from typer.testing import CliRunner

from app.advice import report_dict
from app.cli import cli
from leap_core.datasets.kitti import (
    A_LOOP,
    LINK_OUTSIDE,
    KittiSequence,
    image_size,
    read_image,
    write_image,
    write_png16,
)
from leap_core.errors import DatasetError
from leap_core.pipeline.evaluation import no_ground_truth
from leap_core.pipeline.preflight import check_dataset


@pytest.fixture
def seq(tmp_path: Path) -> TinySequence:
    s = build_tiny_sequence(tmp_path / "data", n_frames=4, n_points=40)
    for fid in s.frame_ids:
        for kind in ("semantic", "instance"):
            write_png16(s.root / "gt2d" / kind / f"{fid}.png", np.full((48, 64), 40, np.uint16))
    return s


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    """A file outside the sequence folder (37 bytes: as a label file it would be refused for its size, and
    the message would give the size away)."""
    path = tmp_path / "elsewhere" / "secret.txt"
    path.parent.mkdir()
    path.write_bytes(b"root:x:0:0:root:/root:/bin/bash\nabcd\n")
    return path


def _link(entry: Path, target: Path) -> None:
    entry.unlink(missing_ok=True)
    entry.symlink_to(target)


# --------------------------------------------------------------------------------- links out of the folder
@pytest.mark.parametrize(
    "entry",
    ["labels/000001.label", "velodyne/000002.bin", "image_2/000003.png", "gt2d/semantic/000000.png"],
)
def test_a_per_frame_file_linked_outside_the_sequence_is_never_read(
    seq: TinySequence, secret: Path, entry: str
) -> None:
    linked = seq.root / entry
    _link(linked, secret)
    with pytest.raises(DatasetError) as err:
        KittiSequence(seq.root)
    assert err.value.path == str(linked)
    assert err.value.problem.startswith(LINK_OUTSIDE) and "put the file itself in its place" in str(err.value)
    # Nothing of the file it points to reaches the message: neither its size nor its name.
    assert "bytes" not in str(err.value) and "secret" not in str(err.value)

    report = check_dataset(seq.root, check_models=False)
    assert report.verdict == "none"
    (finding,) = [f for f in report.findings if f.code == "linked_outside"]
    assert finding.severity == "blocker" and finding.path == str(linked.parent)
    assert finding.detail == f"{linked.name} is {LINK_OUTSIDE}" and finding.frames == (linked.stem,)
    assert not [f for f in report.findings if f.code == "unreadable"]  # the reader's refusal says the same
    fix = next(f for f in report_dict(report, "cli")["findings"] if f["code"] == "linked_outside")["fix"]
    assert "copy of the file it points to" in fix


def test_a_link_made_after_the_sequence_was_opened_is_refused_when_read(
    seq: TinySequence, secret: Path
) -> None:
    opened = KittiSequence(seq.root)
    _link(seq.root / "labels" / "000002.label", secret)
    frame = opened.frame(2)
    with pytest.raises(DatasetError) as err:
        _ = frame.labels
    assert err.value.path == str(seq.root / "labels" / "000002.label") and LINK_OUTSIDE in str(err.value)
    _link(seq.root / "velodyne" / "000003.bin", secret)
    with pytest.raises(DatasetError, match=LINK_OUTSIDE):
        _ = opened.frame(3).num_points


def test_links_that_stay_in_the_sequence_and_linked_folders_are_read(
    seq: TinySequence, tmp_path: Path
) -> None:
    # A whole folder linked to another disk is the sequence's layout; a file linked within it is fine.
    other_disk = tmp_path / "disk2" / "velodyne"
    shutil.move(seq.root / "velodyne", other_disk)
    (seq.root / "velodyne").symlink_to(other_disk, target_is_directory=True)
    shutil.copy(other_disk / "000001.bin", other_disk / "kept-001.raw")
    _link(other_disk / "000001.bin", other_disk / "kept-001.raw")
    (seq.root / "labels" / "v2").mkdir()
    os.replace(seq.root / "labels" / "000002.label", seq.root / "labels" / "v2" / "000002.label")
    _link(seq.root / "labels" / "000002.label", Path("v2") / "000002.label")
    opened = KittiSequence(seq.root)
    np.testing.assert_array_equal(opened.frame(1).points, seq.points[1])
    assert opened.frame(2).labels.shape == (40,)
    assert check_dataset(seq.root, check_models=False).verdict == "full"


def test_leap_check_and_leap_run_name_the_linked_file(
    seq: TinySequence, secret: Path, tmp_path: Path
) -> None:
    linked = seq.root / "labels" / "000001.label"
    _link(linked, secret)
    runner = CliRunner()
    check = runner.invoke(cli, ["check", str(seq.root), "--labeler", "simulated"])
    assert check.exit_code == 3, check.output
    assert f"{linked.parent}: 000001.label is {LINK_OUTSIDE}" in check.output
    assert "fix: replace each link with a copy of the file it points to" in check.output
    run = runner.invoke(cli, ["run", str(seq.root), "--out", str(tmp_path / "run"), "--labeler", "simulated"])
    assert run.exit_code != 0
    assert f"{linked}: {LINK_OUTSIDE}" in run.output and "bytes" not in run.output


def test_a_symlink_loop_in_place_of_a_per_frame_file_is_named(seq: TinySequence, tmp_path: Path) -> None:
    """A loop (``Path.resolve`` raises RuntimeError for one) is named like a dangling link: a scan that is
    one refuses the sequence, a label that is one only takes that frame's ground truth away."""
    scan = seq.root / "velodyne" / "000002.bin"
    _link(scan, scan)
    with pytest.raises(DatasetError) as err:
        KittiSequence(seq.root)
    assert err.value.path == str(scan) and err.value.problem.startswith(A_LOOP)
    (finding,) = [f for f in check_dataset(seq.root, check_models=False).findings if f.code == "not_a_file"]
    assert finding.severity == "blocker" and f"000002.bin is {A_LOOP}" in finding.detail

    _link(scan, Path("000003.bin"))
    label = seq.root / "labels" / "000001.label"
    _link(label, label)
    opened = KittiSequence(seq.root)
    assert opened.label_problem(1) == A_LOOP
    (finding,) = [f for f in check_dataset(seq.root, check_models=False).findings if f.code == "not_a_file"]
    assert finding.severity == "warning" and f"000001.label is {A_LOOP}" in finding.detail


def test_a_symlink_loop_on_the_way_to_the_export_folder_is_named(seq: TinySequence, tmp_path: Path) -> None:
    """``leap run --export-to DIR`` checks DIR/sequences/<name>/predictions before the run: a loop on the way
    is one line naming the option and the loop, not a traceback."""
    target = tmp_path / "exports"
    target.mkdir()
    (target / "sequences").symlink_to(target / "sequences")
    out = tmp_path / "run"
    run = CliRunner().invoke(
        cli, ["run", str(seq.root), "--out", str(out), "--labeler", "simulated", "--export-to", str(target)]
    )
    assert (run.exit_code != 0 and run.exception is None) or isinstance(run.exception, SystemExit), run.output
    assert f"--export-to: export folder '{target / 'sequences'}" in run.output, run.output
    assert "a symlink loop" in run.output and "Traceback" not in run.output
    assert not out.exists()


def test_a_pipe_in_place_of_a_label_is_refused_without_reading_it(seq: TinySequence) -> None:
    pipe = seq.root / "labels" / "000003.label"
    pipe.unlink()
    os.mkfifo(pipe)  # opening it to read would block until someone writes: the reader never does
    with pytest.raises(DatasetError, match="not a regular file") as err:
        KittiSequence(seq.root)
    assert err.value.path == str(pipe)
    report = check_dataset(seq.root, check_models=False)
    (finding,) = [f for f in report.findings if f.code == "not_a_file"]
    assert finding.severity == "blocker" and "000003.label is not a regular file" in finding.detail


# ------------------------------------------------------------------------------- a directory, not a file
def test_a_label_that_is_a_directory_is_named_not_taken_for_missing_ground_truth(seq: TinySequence) -> None:
    label = seq.root / "labels" / "000003.label"
    label.unlink()
    label.mkdir()
    opened = KittiSequence(seq.root)  # the other scans' ground truth and everything else still read
    assert not opened.has_labels
    assert opened.label_problem(3) == "a directory, not a file" and opened.label_problem(1) is None
    assert no_ground_truth(opened, range(4)) == f"no ground truth: {label} is a directory, not a file"
    assert no_ground_truth(opened, range(3)) is None

    report = check_dataset(seq.root, check_models=False)
    assert report.verdict == "full" and report.ground_truth.present == 3  # evaluation is skipped
    (finding,) = [f for f in report.findings if f.code == "not_a_file"]
    assert finding.severity == "warning" and finding.path == str(label.parent)
    assert finding.detail == "000003.label is a directory, not a file" and finding.frames == ("000003",)
    assert {s.name: s.state for s in report.stages}["evaluate"] == "skipped"

    label.rmdir()
    assert no_ground_truth(opened, range(4)) == "no ground truth"


def test_a_scan_that_is_a_directory_blocks_the_run(seq: TinySequence) -> None:
    scan = seq.root / "velodyne" / "000002.bin"
    scan.unlink()
    scan.mkdir()
    with pytest.raises(DatasetError, match="a directory, not a file") as err:
        KittiSequence(seq.root)
    assert err.value.path == str(scan)
    report = check_dataset(seq.root, check_models=False)
    assert report.verdict == "none"
    assert [f.detail for f in report.findings if f.code == "not_a_file"] == [
        "000002.bin is a directory, not a file"
    ]


# -------------------------------------------------------------------------------------- camera images
def _truncate(path: Path, keep: float = 0.6) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_image_size_reads_the_header_of_complete_images(tmp_path: Path, suffix: str) -> None:
    rgb = np.random.default_rng(0).integers(0, 255, (37, 53, 3), dtype=np.uint8)
    path = tmp_path / f"a{suffix}"
    write_image(path, rgb)
    assert image_size(path) == (53, 37) == read_image(path).shape[1::-1]
    # Zero bytes after a JPEG's end marker are padding some writers add; the image is complete.
    if suffix == ".jpg":
        path.write_bytes(path.read_bytes() + b"\x00" * 10)
        assert image_size(path) == (53, 37)


@pytest.mark.parametrize(("suffix", "what"), [(".png", "a truncated PNG"), (".jpg", "a truncated JPEG")])
def test_a_truncated_image_is_named_by_the_check_and_refused_by_the_reader(
    seq: TinySequence, suffix: str, what: str
) -> None:
    rgb = np.random.default_rng(1).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    (seq.root / "image_2" / "000002.png").unlink()
    path = seq.root / "image_2" / f"000002{suffix}"
    write_image(path, rgb)
    _truncate(path)
    with pytest.raises(DatasetError) as err:
        read_image(path)
    assert err.value.path == str(path) and what in err.value.problem
    with pytest.raises(DatasetError, match=what):
        _ = KittiSequence(seq.root).frame(2).image

    report = check_dataset(seq.root, config=None, check_models=False)
    (finding,) = [f for f in report.findings if f.code == "images_damaged"]
    assert finding.severity == "warning" and finding.path == str(seq.root / "image_2")
    assert finding.detail.startswith(f"{path.name} is {what}") and finding.frames == ("000002",)
    gsam = next(lab for lab in report.labelers if lab.name == "grounded-sam")
    assert not gsam.can_run and "images_damaged" in gsam.reasons


def test_an_image_of_another_size_is_named(seq: TinySequence) -> None:
    write_image(seq.root / "image_2" / "000001.png", np.zeros((24, 32, 3), np.uint8))
    report = check_dataset(seq.root, check_models=False)
    (finding,) = [f for f in report.findings if f.code == "images_size"]
    assert finding.detail == "000001.png is 32×24 pixels, the sequence's other images 64×48"
    assert finding.frames == ("000001",) and finding.severity == "warning"
    gsam = next(lab for lab in report.labelers if lab.name == "grounded-sam")
    assert "images_size" in gsam.reasons
    assert not [f for f in check_dataset(seq.root, check_models=False).findings if f.code == "images_damaged"]
