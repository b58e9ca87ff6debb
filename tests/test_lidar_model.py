"""The LiDAR-only model: trained on a run's final labels, resumed after an interruption, labeling a
sequence without images, exported to TorchScript (leap_core.lidar_model, `leap train` / `leap predict`)."""

from __future__ import annotations

import json
import shutil
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from runhelpers import label
from typer.testing import CliRunner

from app.cli import cli
from leap_core.consistency.config import BackboneConfig
from leap_core.consistency.data import prepare_cloud
from leap_core.consistency.train import predict_log_probs
from leap_core.corrections import ScanCorrections
from leap_core.datasets.kitti import KittiSequence, read_label
from leap_core.errors import Cancelled, LeapError
from leap_core.export import read_confidence, run_export
from leap_core.io_utils import read_npz
from leap_core.lidar_model.config import LidarModelConfig
from leap_core.lidar_model.data import block_split, labeled_sequences, split_scans
from leap_core.lidar_model.export import export_torchscript, run_scripted
from leap_core.lidar_model.model import load_model, read_card, state_path
from leap_core.lidar_model.predict import predict_run
from leap_core.lidar_model.train import train_lidar_model
from leap_core.pipeline.apply import RunCorrections, apply_to_run, load_run_cache
from leap_core.presets import builtin_preset
from leap_core.run_layout import RunLayout
from leap_core.synth import CameraConfig, LidarConfig, SynthConfig, generate_sequence

SMALL = SynthConfig(
    frames=4, seed=0, lidar=LidarConfig(beams=16, azimuth_step_deg=1.0), camera=CameraConfig().scaled(0.5)
)
"""Four frames of the demo street with a coarse LiDAR (about 5k points a scan) and a half-size camera."""
TINY = LidarModelConfig(
    steps=6,
    points_per_scan=1024,
    checkpoint_every=2,
    val_block=2,
    val_every=2,
    device="cpu",
    num_threads=1,
    backbone=BackboneConfig(channels=8, layers=3, embed_channels=4, knn=8),
)
"""A few steps of a tiny network; frames 2-3 of each sequence are held apart for validation."""
SCHEMA = builtin_preset("semantickitti")


@pytest.fixture(scope="module")
def labeled_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished `leap run` of the four frames (simulated labeler, default settings)."""
    root = tmp_path_factory.mktemp("lidar_model")
    seq = generate_sequence(root / "data", SMALL).path
    out = root / "run"
    label(seq, SCHEMA.schema, SCHEMA.pipeline, out)
    return out


@pytest.fixture(scope="module")
def camera_less(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another street (seed 1, two frames) with its images removed: a LiDAR-only sequence."""
    seq = generate_sequence(tmp_path_factory.mktemp("other"), replace(SMALL, frames=2, seed=1)).path
    shutil.rmtree(seq / "image_2")
    return seq


def _train(run: Path, out: Path, cfg: LidarModelConfig = TINY, **kw: object) -> None:
    train, val = split_scans(labeled_sequences([run]), [], cfg.val_block, cfg.val_every)
    train_lidar_model(out, train, val, SCHEMA.schema, cfg, **kw)  # type: ignore[arg-type]


def test_block_split_holds_every_nth_block_apart() -> None:
    assert np.flatnonzero(block_split(10, 2, 2)).tolist() == [2, 3, 6, 7]
    assert np.flatnonzero(block_split(10, 3, 3)).tolist() == [6, 7, 8]
    assert not block_split(10, 0, 5).any()


def test_a_sequence_cannot_both_train_and_validate(labeled_run: Path) -> None:
    runs = labeled_sequences([labeled_run])
    with pytest.raises(LeapError, match="both to train on and apart for validation"):
        split_scans(runs, labeled_sequences([labeled_run]), 0, 2)
    train, val = split_scans(runs, [], 2, 2)
    assert [i for _, i in train.scans] == [0, 1] and [i for _, i in val.scans] == [2, 3]


def test_training_labels_are_the_run_s_final_labels_with_corrections(
    labeled_run: Path, tmp_path: Path
) -> None:
    """A scan-scope correction applied to the run reaches the training labels (corrections win)."""
    run = tmp_path / "run"
    shutil.copytree(labeled_run, run)
    seq = RunLayout(run).sequence("00")
    car = SCHEMA.schema.index("car")
    dataset = KittiSequence(json.loads(RunLayout(run).spec.read_text())["sequences"][0]["dataset"])
    frames, vs = range(len(dataset)), SCHEMA.pipeline.fusion.voxel_size
    new = RunCorrections(
        np.zeros(0, np.int64), np.zeros(0, np.int16), ScanCorrections.merge([("000001", [0, 1, 2], car)])
    )
    cache = load_run_cache(seq, dataset, frames, vs)
    apply_to_run(seq, dataset, frames, vs, SCHEMA.schema.export_ids(), new=new, cache=cache)
    (part,) = labeled_sequences([run])
    labels = part.labels(1, SCHEMA.schema)
    assert labels[:3].tolist() == [car] * 3
    assert np.array_equal(labels, read_npz(seq.points("000001"), ("label",))["label"])


def test_train_predict_without_images_and_export(
    labeled_run: Path, camera_less: Path, tmp_path: Path
) -> None:
    """The issue's acceptance: a few steps on the 4-frame run, a second sequence labeled without images,
    its exports checked; the card names classes, export ids, data, settings, validation and code."""
    model_file = tmp_path / "m.pt"
    _train(labeled_run, model_file)
    assert not state_path(model_file).exists()
    card = read_card(model_file)
    ids = SCHEMA.schema.export_ids()
    assert [(e["name"], e["export_id"]) for e in card["classes"]] == list(
        zip(SCHEMA.schema.names, ids.tolist(), strict=True)
    )
    assert card["data"]["train"][0]["scans"] == 2 and card["data"]["validation"][0]["scans"] == 2
    assert card["data"]["runs"] == [str(labeled_run)]
    assert card["settings"]["steps"] == 6 and card["validation"]["scans"] == 2
    assert set(card["validation"]["iou"]) == set(SCHEMA.schema.names)
    assert "commit" in card["code"]

    model = load_model(model_file)
    out = tmp_path / "pred"
    (res,) = predict_run(model, model_file, [("lidar", camera_less, None)], out, device="cpu")
    seq = KittiSequence(camera_less)
    assert not seq.has_images and res.scans == 2
    lay = RunLayout(out).sequence("lidar")
    for i, fid in enumerate(seq.frame_ids):
        points = seq.frame(i).points
        expect = predict_log_probs(model.network, points)
        raw = read_label(lay.export_label(fid), points.shape[0]) & 0xFFFF
        assert np.array_equal(raw, ids[expect.argmax(1)])  # every point labeled, by the model's argmax
        conf = read_confidence(lay.export_conf(fid), points.shape[0])
        assert np.allclose(conf, np.exp(expect.max(1)), atol=1e-6)
    assert res.metrics is not None  # the synthetic sequence has ground truth
    scores = json.loads(lay.model_metrics.read_text())["all"]
    assert scores["n_points"] == res.metrics.n_points > 0
    assert json.loads(RunLayout(out).model_note.read_text())["card"] == card

    (exported,) = run_export(out)  # the run's export reads as any run's
    assert exported.name == "lidar" and len(exported.files(with_confidence=True)) == 4
    before = sorted(p.name for p in labeled_run.rglob("*"))
    with pytest.raises(LeapError, match="holds another run's results"):
        predict_run(model, model_file, [("lidar", camera_less, None)], labeled_run, device="cpu")
    assert sorted(p.name for p in labeled_run.rglob("*")) == before


def test_interrupted_training_resumes_to_the_same_checkpoint(labeled_run: Path, tmp_path: Path) -> None:
    whole, parts = tmp_path / "whole.pt", tmp_path / "parts.pt"
    _train(labeled_run, whole)

    def stop_at_5(done: int, total: int) -> None:
        if done == 5:
            raise Cancelled

    with pytest.raises(Cancelled):
        _train(labeled_run, parts, progress=stop_at_5)
    assert state_path(parts).is_file() and not parts.exists()
    _train(labeled_run, parts)
    a, b = load_model(whole), load_model(parts)
    assert read_card(parts)["training"]["resumed_from"] == 4
    sa, sb = a.network.state_dict(), b.network.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # another seed trains other weights: the comparison can tell checkpoints apart
    other = tmp_path / "other.pt"
    _train(labeled_run, other, replace(TINY, seed=1))
    so = load_model(other).network.state_dict()
    assert not all(torch.equal(sa[k], so[k]) for k in sa)


def test_a_saved_state_of_other_settings_is_refused(labeled_run: Path, tmp_path: Path) -> None:
    model_file = tmp_path / "m.pt"

    def stop_at_3(done: int, total: int) -> None:
        if done == 3:
            raise Cancelled

    with pytest.raises(Cancelled):
        _train(labeled_run, model_file, progress=stop_at_3)
    with pytest.raises(LeapError, match="other data or settings"):
        _train(labeled_run, model_file, replace(TINY, lr=1e-3))


def test_torchscript_export_predicts_what_pytorch_predicts(labeled_run: Path, tmp_path: Path) -> None:
    model_file = tmp_path / "m.pt"
    _train(labeled_run, model_file)
    model = load_model(model_file)
    script = tmp_path / "m.torchscript.pt"
    export_torchscript(model.network, script)
    loaded = torch.jit.load(str(script))
    seq = KittiSequence(json.loads(RunLayout(labeled_run).spec.read_text())["sequences"][0]["dataset"])
    points = seq.frame(0).points
    ours = predict_log_probs(model.network, points)
    theirs = run_scripted(loaded, prepare_cloud(points, model.network.cfg))
    assert np.array_equal(ours, theirs)


def _tiny_project(path: Path) -> Path:
    """The SemanticKITTI classes with the tiny backbone as the project's 3D-CN backbone."""
    bb = TINY.backbone
    doc = {
        **SCHEMA.schema.to_dict(),
        "pipeline": {
            "consistency": {
                "backbone": {
                    "channels": bb.channels,
                    "layers": bb.layers,
                    "embed_channels": bb.embed_channels,
                    "knn": bb.knn,
                }
            }
        },
    }
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.slow
def test_cli_train_predict_export(labeled_run: Path, camera_less: Path, tmp_path: Path) -> None:
    """`leap train`, `leap predict --zip` on the camera-less sequence, `leap export-model`; one-line
    errors for an existing model file and a file that is not a model."""
    runner = CliRunner()
    project = _tiny_project(tmp_path / "p.yaml")
    model_file = tmp_path / "m.pt"
    args = ["train", str(labeled_run), "--out", str(model_file), "--project-file", str(project)]
    opts = [
        "--steps",
        "3",
        "--points-per-scan",
        "512",
        "--val-block",
        "2",
        "--val-every",
        "2",
        "--device",
        "cpu",
    ]
    done = runner.invoke(cli, [*args, *opts])
    assert done.exit_code == 0, done.output
    assert "2 training scans, 2 held apart" in done.output and "points/s" in done.output
    again = runner.invoke(cli, [*args, *opts])
    assert again.exit_code == 2 and "already exists; add --force" in again.output

    zipped = tmp_path / "labels.zip"
    pred = runner.invoke(
        cli,
        ["predict", str(model_file), str(camera_less), "--out", str(tmp_path / "run"), "--zip", str(zipped)],
    )
    assert pred.exit_code == 0, pred.output
    assert "2 scans" in pred.output and "mIoU" in pred.output
    with zipfile.ZipFile(zipped) as zf:
        names = set(zf.namelist())
    assert {"sequences/00/predictions/000000.label", "label-map.yaml", "model-card.json"} <= names

    script = tmp_path / "m.ts"
    exp = runner.invoke(cli, ["export-model", str(model_file), "--out", str(script)])
    assert exp.exit_code == 0, exp.output
    assert torch.jit.load(str(script)) is not None

    bad = runner.invoke(cli, ["predict", str(script), str(camera_less), "--out", str(tmp_path / "r2")])
    assert bad.exit_code == 2 and f"error: {script}: unreadable model" in bad.output
    card = tmp_path / "m.card.json"
    bad = runner.invoke(cli, ["predict", str(card), str(camera_less), "--out", str(tmp_path / "r3")])
    assert bad.exit_code == 2 and "unreadable model" in bad.output
