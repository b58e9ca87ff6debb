"""The pipeline end to end on a tiny ray-cast street, plus PipelineConfig's dict form."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label

from leap_core.config import PipelineConfig, config_from_dict, config_to_dict
from leap_core.datasets.kitti import (
    Calib,
    KittiSequence,
    read_label,
    read_png16,
    write_calib,
    write_label,
    write_png16,
    write_poses,
    write_scan,
)
from leap_core.errors import Cancelled, DatasetError, LeapError, ModelLoadError, PosesMissingError
from leap_core.labelers.simulated import SimulatedLabelerConfig
from leap_core.metrics import evaluate, metrics_from_confusion
from leap_core.pipeline import (
    STAGE_TABLE,
    STAGES,
    load_metrics,
    plan_stages,
    result_tables,
    stage_status,
)
from leap_core.pipeline.context import file_digest, hash_json
from leap_core.pipeline.runner import (
    PIPELINE_VERSION,
    UNCHANGED,
    StageReport,
    require_poses,
    skip_reason,
    stage_fingerprints,
    warn_missing_images,
)
from leap_core.pipeline.stages import load_soft
from leap_core.run_layout import SequenceLayout
from leap_core.runtime import Runtime
from leap_core.schema import builtin_schema
from leap_core.synth.camera import world_cells

# ------------------------------------------------------------------------------------ a tiny street
# World: z up, ground z = 0. Road |y| < 4, sidewalk 4..6, terrain beyond; building walls at y = ±9;
# two cars and a pole. The sensor drives along +x at 1.7 m height, 1.5 m per frame.
ROAD, SIDEWALK, TERRAIN, BUILDING, CAR, POLE = 40, 48, 72, 50, 10, 80
BOXES = [  # (xmin, xmax, ymin, ymax, zmin, zmax, semantic id, instance id)
    (8.0, 12.0, -3.0, -1.2, 0.0, 1.5, CAR, 1),
    (17.0, 21.0, 1.2, 3.0, 0.0, 1.6, CAR, 2),
    (14.0, 14.3, 5.0, 5.3, 0.0, 4.0, POLE, 3),
    (-60.0, 80.0, 9.0, 9.5, 0.0, 7.0, BUILDING, 0),
    (-60.0, 80.0, -9.5, -9.0, 0.0, 7.0, BUILDING, 0),
]
H, W, F = 60, 200, 90.0
# LiDAR (x fwd, y left, z up) → camera (x right, y down, z forward), camera at the LiDAR origin.
TR = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
P2 = np.array([[F, 0, W / 2, 0], [0, F, H / 2, 0], [0, 0, 1, 0]], dtype=np.float64)


def _raycast(
    origin: np.ndarray, dirs: np.ndarray, max_range: float = 45.0, boxes: list | None = None
) -> tuple:
    """Nearest hit of each ray among the ground and ``boxes`` (default :data:`BOXES`): (t, semantic id,
    instance id); t = inf for no hit."""
    n = dirs.shape[0]
    t_best = np.full(n, np.inf)
    sem = np.zeros(n, np.uint16)
    inst = np.zeros(n, np.uint16)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origin[2] / dirs[:, 2]
        ok = (t > 0) & (t < t_best)
        hit_y = np.abs(origin[1] + t * dirs[:, 1])
        ground = np.where(hit_y < 4, ROAD, np.where(hit_y < 6, SIDEWALK, TERRAIN))
        t_best = np.where(ok, t, t_best)
        sem = np.where(ok, ground, sem).astype(np.uint16)
        for x0, x1, y0, y1, z0, z1, s, k in BOXES if boxes is None else boxes:
            lo = (np.array([x0, y0, z0]) - origin) / dirs
            hi = (np.array([x1, y1, z1]) - origin) / dirs
            tn = np.nanmax(np.minimum(lo, hi), axis=1)
            tf = np.nanmin(np.maximum(lo, hi), axis=1)
            ok = (tn <= tf) & (tn > 0) & (tn < t_best)
            t_best = np.where(ok, tn, t_best)
            sem = np.where(ok, s, sem).astype(np.uint16)
            inst = np.where(ok, k, inst).astype(np.uint16)
    far = t_best > max_range
    t_best[far] = np.inf
    sem[far] = 0
    inst[far] = 0
    return t_best, sem, inst


def make_street(root: Path, n_frames: int = 6, step: float = 1.5, movers: tuple = ()) -> Path:
    """Write a KITTI-layout sequence with scans, labels, images and 2D ground truth (no times.txt: scans
    0.1 s apart). ``movers``: boxes as in :data:`BOXES` plus a velocity ``(vx, vy)`` in m/s, placed at
    ``frame × 0.1 s``."""
    root.mkdir(parents=True, exist_ok=True)
    write_calib(root / "calib.txt", Calib(P2=P2, Tr=TR))
    lidar_poses = []
    el = np.deg2rad(np.linspace(-24.0, 4.0, 24))
    az = np.deg2rad(np.arange(0.0, 360.0, 1.0))
    ee, aa = np.meshgrid(el, az, indexing="ij")
    ldirs = np.stack([np.cos(ee) * np.cos(aa), np.cos(ee) * np.sin(aa), np.sin(ee)], axis=-1).reshape(-1, 3)
    vv, uu = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    cam_dirs = np.stack([(uu - W / 2) / F, (vv - H / 2) / F, np.ones_like(uu, dtype=float)], axis=-1)
    # camera (x right, y down, z fwd) → world (x fwd, y left, z up)
    pdirs = cam_dirs.reshape(-1, 3) @ np.linalg.inv(TR[:3, :3]).T
    for i in range(n_frames):
        origin = np.array([i * step, 0.0, 1.7])
        pose = np.eye(4)
        pose[:3, 3] = origin
        lidar_poses.append(pose)
        boxes = BOXES + [
            (x0 + vx * i * 0.1, x1 + vx * i * 0.1, y0 + vy * i * 0.1, y1 + vy * i * 0.1, z0, z1, sem_id, k)
            for (x0, x1, y0, y1, z0, z1, sem_id, k), (vx, vy) in movers
        ]
        t, sem, inst = _raycast(origin, ldirs, boxes=boxes)
        hit = np.isfinite(t)
        xyz = (ldirs[hit] * t[hit, None]).astype(np.float32)  # LiDAR frame: no rotation
        pts = np.concatenate([xyz, np.full((xyz.shape[0], 1), 0.5, np.float32)], axis=1)
        fid = f"{i:06d}"
        write_scan(root / "velodyne" / f"{fid}.bin", pts)
        write_label(root / "labels" / f"{fid}.label", sem[hit], inst[hit])
        pt, psem, pinst = _raycast(origin, pdirs, boxes=boxes)
        write_png16(root / "gt2d" / "semantic" / f"{fid}.png", psem.reshape(H, W))
        write_png16(root / "gt2d" / "instance" / f"{fid}.png", pinst.reshape(H, W))
        seen = np.isfinite(pt)
        cells = np.zeros(H * W, np.uint16)  # the world cell each pixel sees, as leap synth writes them
        cells[seen] = world_cells(origin + pdirs[seen] * pt[seen, None])
        write_png16(root / "gt2d" / "cell" / f"{fid}.png", cells.reshape(H, W))
        img = np.zeros((H, W, 3), np.uint8)
        img[..., 0] = (psem.reshape(H, W) * 3 % 256).astype(np.uint8)
        from leap_core.datasets.kitti import write_image

        write_image(root / "image_2" / f"{fid}.png", img)
    cam_poses = [TR @ p @ np.linalg.inv(TR) for p in lidar_poses]
    write_poses(root / "poses.txt", np.stack(cam_poses))
    return root


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_street(tmp_path_factory.mktemp("street") / "sequences" / "00")


@pytest.fixture(scope="module")
def schema():
    return builtin_schema("semantickitti")


def _labels(run_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((run_dir / "export").iterdir())}


@pytest.fixture(scope="module")
def baseline(street: Path, schema, tmp_path_factory: pytest.TempPathFactory):
    """A run of the street (3D-CN off): (its sequence's folder, its result, its progress calls)."""
    out = tmp_path_factory.mktemp("runs") / "base"
    calls: list[tuple[str, int, int]] = []
    result = label(street, schema, PipelineConfig(), out, progress=lambda *a: calls.append(a))
    return result.folder, result, calls


def _copy_run(baseline, out: Path) -> Path:
    """A copy of the baseline's run folder at ``out``; returns the copy's sequence folder."""
    shutil.copytree(baseline[0].parent.parent, out)
    return folder(out)


# ------------------------------------------------------------------------------------------- tests
def test_end_to_end_outputs(baseline, street: Path, schema) -> None:
    run_dir, result, calls = baseline
    assert list(result.stages) == list(STAGES)
    assert result.ran == [s for s in STAGES if s not in ("motion", "3dcn")]
    assert result.stages["3dcn"].status == "skipped"
    assert not (run_dir / ".fuse_spill").exists()  # the fuse stage's chunk folder goes when it ends
    # Each report names its stage; per-frame stages computed every frame, whole-run stages count none.
    assert [r.name for r in result.stages.values()] == list(STAGES)
    assert {s: r.frames_computed for s, r in result.stages.items()} == {
        s.name: 6 if s.per_frame else 0 for s in STAGE_TABLE
    }
    # The record keeps the report's seconds to the millisecond, the finish time and a disabled stage's note.
    records = stage_status(run_dir)
    assert all(records[s]["seconds"] == round(r.seconds, 3) for s, r in result.stages.items())
    assert skip_reason(run_dir, "fuse", time.time()) == UNCHANGED
    assert skip_reason(run_dir, "3dcn", time.time()) == "3D-CN disabled"
    seq = KittiSequence(street)
    for fid in seq.frame_ids:
        n = seq.frame(seq.frame_ids.index(fid)).points.shape[0]
        assert read_label(run_dir / "export" / f"{fid}.label", n).shape == (n,)
        assert (run_dir / "labels2d" / f"{fid}.npz").is_file()
        with np.load(run_dir / "points" / f"{fid}.npz") as z:
            assert z["label"].dtype == np.int16 and z["label"].shape == (n,)
    # Every stage reported progress ending at done == total.
    for s in STAGES:
        last = [c for c in calls if c[0] == s][-1]
        assert last[1] == last[2]
    status = stage_status(run_dir)
    assert all(status[s]["status"] in ("done", "skipped") for s in STAGES)

    m = result.metrics
    assert m is not None and set(m.rows) == {"point", "voxel", "objects"}
    cam, allp = m.table("camera"), m.table("all")
    # Voxels fuse several noisy views and label points the camera does not see in that scan.
    assert cam["voxel"].miou > 0.5
    # Only 6 frames 1.5 m apart: points behind the car were seen by earlier frames only near the start.
    assert allp["voxel"].labeled_share > 1.5 * allp["point"].labeled_share
    assert m.coverage_ratio["voxel"] > 1.5
    tables = result_tables(run_dir)
    assert "simulated" in tables and "voxel" in tables and "point" in tables


def test_exported_ids_match_metrics(baseline, street: Path, schema) -> None:
    """The all-points IoU recomputed from the exported .label files equals metrics.json."""
    run_dir, result, _ = baseline
    seq = KittiSequence(street)
    gt_all, pred_all = [], []
    raw_to_idx = {int(e): i for i, e in enumerate(schema.export_ids())}
    raw_to_idx |= {int(e): i for i, e in enumerate(schema.moving_export_ids())}
    for i, fid in enumerate(seq.frame_ids):
        frame = seq.frame(i)
        gt_all.append(schema.map_gt(frame.labels))
        raw = read_label(run_dir / "export" / f"{fid}.label") & 0xFFFF
        pred_all.append(np.array([raw_to_idx.get(int(r), -1) for r in raw], np.int16))
    m = evaluate(
        np.concatenate(gt_all),
        np.concatenate(pred_all),
        schema.names,
        schema.categories(),
        ignore_unlabeled_pred=False,
    )
    assert m.miou == pytest.approx(result.metrics.miou("all", "objects"), abs=1e-9)


def test_second_run_skips_everything(baseline, street: Path, schema) -> None:
    run_dir, _, _ = baseline
    before = _labels(run_dir)
    again = label(street, schema, PipelineConfig(), run_dir.parent.parent)
    assert again.ran == []
    # A cached stage reports its name, its recorded status and no time spent in this call.
    recorded = stage_status(run_dir)
    assert again.stages == {s: StageReport(s, False, recorded[s]["status"], 0.0) for s in STAGES}
    assert _labels(run_dir) == before
    assert not any(plan_stages(street, schema, PipelineConfig(), run_dir).values())


def test_changing_k_reruns_only_smooth_and_later(baseline, street: Path, schema, tmp_path: Path) -> None:
    run_dir = _copy_run(baseline, tmp_path / "copy")
    cfg = config_from_dict({"smoothing": {"k": 4}})
    plan = plan_stages(street, schema, cfg, run_dir)
    assert [s for s, todo in plan.items() if todo] == [
        "smooth",
        "3dcn",
        "label_points",
        "tracks",
        "evaluate",
        "export",
    ]
    result = label(street, schema, cfg, tmp_path / "copy")
    assert result.ran == [
        "smooth",
        "label_points",
        "tracks",
        "evaluate",
        "export",
    ]  # 3dcn is off: nothing to run
    # A colour edit changes nothing downstream.
    recolored = schema.with_classes(
        [dataclasses.replace(schema.classes[0], color=(1, 2, 3)), *schema.classes[1:]]
    )
    assert label(street, recolored, cfg, tmp_path / "copy").ran == []


# ------------------------------------------------------------------------------------- stage table
def test_stage_table_is_ordered_and_complete() -> None:
    names = [s.name for s in STAGE_TABLE]
    assert tuple(names) == STAGES and len(set(names)) == len(names)
    for k, stage in enumerate(STAGE_TABLE):
        assert set(stage.upstream) <= set(names[:k]), f"{stage.name}: upstream must come earlier"
        assert stage.per_frame == (stage.frame_files is not None)
        assert stage.label and stage.description and callable(stage.run)
    sections = set(config_to_dict(PipelineConfig()))
    assert {r for s in STAGE_TABLE for r in s.reads} <= sections


def _downstream(names: set[str]) -> set[str]:
    """``names`` and every stage that reads (transitively) from one of them, by the table's upstream."""
    out = set(names)
    for stage in STAGE_TABLE:
        if out & set(stage.upstream):
            out.add(stage.name)
    return out


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (
            {"projection": {"min_depth": 0.8}},
            ["project", "motion", "fuse", "smooth", "3dcn", "label_points", "tracks", "evaluate", "export"],
        ),
        (
            {"fusion": {"prob_floor": 0.002}},
            ["fuse", "smooth", "3dcn", "label_points", "tracks", "evaluate", "export"],
        ),
        ({"smoothing": {"k": 4}}, ["smooth", "3dcn", "label_points", "tracks", "evaluate", "export"]),
        ({"consistency": {"enabled": True}}, ["3dcn", "label_points", "tracks", "evaluate", "export"]),
        # A disabled 3D-CN's settings and the strength of corrections the run does not have are not inputs.
        ({"consistency": {"share": 0.3}}, []),
        ({"correction_strength": 20.0}, []),
        # The labeler's own fingerprint covers its section: everything reruns.
        ({"simulated": {"recall": 0.5}}, list(STAGES)),
    ],
)
def test_a_config_change_reruns_its_readers_and_their_downstream(
    baseline, street: Path, schema, overrides: dict, expected: list[str]
) -> None:
    run_dir, _, _ = baseline
    plan = plan_stages(street, schema, config_from_dict(overrides), run_dir)
    assert [s for s, todo in plan.items() if todo] == expected
    # The same set follows from the table: the stages that read the section, then their downstream.
    section = next(iter(overrides))
    readers = {s.name for s in STAGE_TABLE if section in s.reads}
    if section == "consistency" and "enabled" not in overrides[section]:
        readers = set()
    if section == "simulated":
        readers = {"labels2d"}
    if section == "correction_strength":
        readers = set()
    assert set(expected) == _downstream(readers)


def test_a_prompt_edit_reruns_the_2d_stage_and_a_colour_edit_nothing(baseline, street: Path, schema) -> None:
    """The simulated labeler reads the prompts (docs/METHOD.md A.7): a prompt edit must not reuse masks."""
    run_dir, _, _ = baseline
    car = schema.names.index("car")

    def edited(**changes: object):
        return schema.with_classes(
            [dataclasses.replace(c, **changes) if i == car else c for i, c in enumerate(schema.classes)]
        )

    plan = plan_stages(street, edited(prompts=("car",)), PipelineConfig(), run_dir)
    assert [s for s, todo in plan.items() if todo] == list(STAGES)
    plan = plan_stages(street, edited(color=(1, 2, 3)), PipelineConfig(), run_dir)
    assert not any(plan.values())


def test_corrections_rerun_fuse_and_its_downstream(baseline, street: Path, schema, tmp_path: Path) -> None:
    run_dir = _copy_run(baseline, tmp_path / "plan_corr")
    np.savez(run_dir / "corrections.npz", keys=np.array([1], np.int64), class_idx=np.array([0]))
    plan = plan_stages(street, schema, PipelineConfig(), run_dir)
    assert [s for s, todo in plan.items() if todo] == sorted(_downstream({"fuse"}), key=STAGES.index)
    # Now the strength of the corrections is an input too.
    label(street, schema, PipelineConfig(), tmp_path / "plan_corr", until="fuse")
    plan = plan_stages(street, schema, config_from_dict({"correction_strength": 20.0}), run_dir)
    assert plan["fuse"] and not plan["project"]


def test_erased_voxels_are_never_3dcn_training_labels(baseline, street: Path, schema, tmp_path: Path) -> None:
    # Erase every voxel of the map: fuse keeps their evidence, so only the 3D-CN's exclusion of erased
    # voxels leaves it nothing to train on (before any training starts).
    run_dir = _copy_run(baseline, tmp_path / "erase_all")
    with np.load(run_dir / "grid.npz") as z:
        keys = np.asarray(z["keys"], np.int64)
    np.savez(run_dir / "corrections.npz", keys=keys, class_idx=np.full(keys.shape, -1))
    cfg = config_from_dict({"consistency": {"enabled": True, "device": "cpu", "num_threads": 1}})
    with pytest.raises(LeapError, match="no point of any scan has a voxel label"):
        label(street, schema, cfg, tmp_path / "erase_all", until="3dcn")


def test_a_source_network_starts_every_round_and_is_an_input_of_the_3dcn(
    baseline, street: Path, schema, tmp_path: Path
) -> None:
    from leap_core.consistency.train import load_checkpoint

    cn = {
        "enabled": True,
        "device": "cpu",
        "num_threads": 1,
        "min_steps": 9,
        "points_per_scan": 2000,
        "backbone": {"channels": 16, "layers": 2},
    }
    cfg = config_from_dict({"consistency": cn})
    out = tmp_path / "run"
    run_dir = _copy_run(baseline, out)
    label(street, schema, cfg, out, until="3dcn")
    ckpt = out / "3dcn" / "3dcn_iter1.pt"
    assert load_checkpoint(ckpt).meta["steps"] == 9 and "source" not in load_checkpoint(ckpt).meta
    source = tmp_path / "source.pt"
    shutil.copy(ckpt, source)
    with_source = Runtime(init_3dcn=source)
    assert plan_stages(street, schema, cfg, run_dir, runtime=with_source)["3dcn"]
    result = label(street, schema, cfg, out, until="3dcn", runtime=with_source)
    assert "3dcn" in result.ran
    meta = load_checkpoint(ckpt).meta
    # Fine-tuned for one epoch over the 6 frames (finetune_min_steps 0 replaces min_steps 9).
    assert meta["source"] == file_digest(source) and meta["steps"] == 6
    assert not plan_stages(street, schema, cfg, run_dir, runtime=with_source)["3dcn"]
    assert plan_stages(street, schema, cfg, run_dir)["3dcn"]  # without it: from random weights again
    tuned = ckpt.read_bytes()
    # A source of another backbone is refused, naming the file, before anything is written.
    other = config_from_dict({"consistency": {**cn, "backbone": {"channels": 8, "layers": 2}}})
    with pytest.raises(ModelLoadError, match=r"source\.pt: the 3D-CN source network's backbone differs"):
        label(street, schema, other, out, until="3dcn", runtime=with_source)
    assert ckpt.read_bytes() == tuned
    with pytest.raises(ModelLoadError, match=r"gone\.pt: 3D-CN source network \(--3dcn-init\) cannot"):
        plan_stages(street, schema, cfg, run_dir, runtime=Runtime(init_3dcn=tmp_path / "gone.pt"))


def test_resume_after_cancel_is_byte_identical(baseline, street: Path, schema, tmp_path: Path) -> None:
    base_dir, _, _ = baseline
    run_dir = folder(tmp_path / "interrupted")
    running: list[dict] = []
    for stage, at in (("labels2d", 3), ("project", 2), ("fuse", 2), ("label_points", 4)):

        def cancel(s: str, done: int, total: int, stage: str = stage, at: int = at) -> None:
            if s == stage and done == at:
                running.append(stage_status(run_dir)[stage])
                raise Cancelled()

        # One frame at a time: with frames in flight the cancelled stage may finish every frame
        # (tests/test_scan_speed.py covers the threaded case).
        with pytest.raises(Cancelled):
            label(
                street,
                schema,
                PipelineConfig(),
                tmp_path / "interrupted",
                progress=cancel,
                runtime=Runtime(frame_threads=1),
            )
        assert stage_status(run_dir)[stage]["status"] == "cancelled"
    # While a stage runs, its record says so (and since when) under the fingerprint it computes for.
    assert [sorted(r) for r in running] == [["fingerprint", "started", "status"]] * 4
    assert all(r["status"] == "running" and r["started"] <= time.time() for r in running)
    # A temporary file a killed run left in a per-frame folder is removed when the stage resumes.
    leftover = run_dir / "points" / ".000005.npz.0123456789ab.tmp"
    leftover.write_bytes(b"partial")
    result = label(street, schema, PipelineConfig(), tmp_path / "interrupted")
    assert not leftover.exists()
    # The frames finished before the last interruption were not recomputed.
    assert 0 < result.stages["label_points"].frames_computed < 6
    assert result.stages["labels2d"].ran is False
    assert _labels(run_dir) == _labels(base_dir)
    assert (run_dir / "grid.npz").read_bytes() == (base_dir / "grid.npz").read_bytes()


def test_frames_subset_and_shared_2d_cache(street: Path, schema, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    a = label(
        street,
        schema,
        PipelineConfig(),
        tmp_path / "a",
        frames=range(0, 3),
        runtime=Runtime(cache_dir=cache),
        until="fuse",
    )
    assert a.frames == (0, 1, 2)
    assert a.metrics is None and a.export_dir is None  # neither stage was reached
    names = sorted(p.name for p in (folder(tmp_path / "a") / "labels2d").iterdir())
    assert names == [f"{i:06d}.npz" for i in range(3)]
    b = label(
        street,
        schema,
        PipelineConfig(),
        tmp_path / "b",
        frames=range(0, 4),
        runtime=Runtime(cache_dir=cache),
        until="labels2d",
    )
    assert stage_status(folder(tmp_path / "b"))["labels2d"]["cache_hits"] == 3
    assert b.stages["labels2d"].frames_computed == 4
    same = [(folder(tmp_path / d) / "labels2d" / "000001.npz").read_bytes() for d in ("a", "b")]
    assert same[0] == same[1]
    with pytest.raises(LeapError, match="out of range"):
        label(street, schema, PipelineConfig(), tmp_path / "c", frames=range(4, 9))


def test_plans_and_fingerprints_are_for_the_frames_asked_for(street: Path, schema, tmp_path: Path) -> None:
    """A run folder made for three frames: its first stages are current for those frames (recorded
    fingerprints included), not for all six."""
    out = tmp_path / "runs" / "a"  # its parent folder does not exist yet either
    run_dir = label(street, schema, PipelineConfig(), out, frames=range(0, 3), until="fuse").folder
    assert run_dir == folder(out)
    plan = plan_stages(street, schema, PipelineConfig(), run_dir, frames=range(0, 3))
    assert [s for s, todo in plan.items() if not todo] == ["labels2d", "project", "motion", "fuse"]
    # The switched-off motion stage has nothing to do for any frames; every other stage has, for all six.
    whole = plan_stages(street, schema, PipelineConfig(), run_dir)
    assert [s for s, todo in whole.items() if not todo] == ["motion"]
    recorded = stage_status(run_dir)
    fps = stage_fingerprints(street, schema, PipelineConfig(), run_dir, frames=range(0, 3))
    assert [s for s in STAGES if fps[s] == recorded[s].get("fingerprint")] == [
        "labels2d",
        "project",
        "motion",
        "fuse",
    ]


def test_zero_noise_point_labels_match_ground_truth(street: Path, schema, tmp_path: Path) -> None:
    """Exact 2D labels, no depth-clustering loss: projected labels equal the 3D ground truth."""
    cfg = PipelineConfig().with_labeler_config(SimulatedLabelerConfig.exact())
    result = label(street, schema, cfg, tmp_path / "exact", until="evaluate")
    cam = result.metrics.table("camera")["point"]
    # Points straddling an object edge may land on a pixel whose ray hits the neighbour, so allow a little.
    assert cam.miou > 0.9
    assert result.metrics.miou("camera", "voxel") > 0.85


def test_corrections_override_voxels(baseline, street: Path, schema, tmp_path: Path) -> None:
    from leap_core.fusion import VoxelGrid

    run_dir = _copy_run(baseline, tmp_path / "corr")
    grid = VoxelGrid.load(run_dir / "grid.npz")
    keys = grid.keys[:50]
    np.savez(run_dir / "corrections.npz", keys=keys, class_idx=np.full(50, schema.index("trunk")))
    result = label(street, schema, PipelineConfig(), tmp_path / "corr", until="fuse")
    assert result.ran == ["fuse"]
    fixed = VoxelGrid.load(run_dir / "grid.npz")
    lab, _ = fixed.labels_and_confidence()
    assert (lab[fixed.lookup(keys)] == schema.index("trunk")).all()
    np.savez(run_dir / "corrections.npz", keys=keys, class_idx=np.full(50, 99))
    with pytest.raises(LeapError, match=r"corrections\.npz"):
        label(street, schema, PipelineConfig(), tmp_path / "corr", until="fuse")


def test_scan_corrections_reach_their_scan_and_an_index_past_it_is_refused(
    baseline, street: Path, schema, tmp_path: Path
) -> None:
    """A scan-scope correction relabels the points it names in its own scan only (label, confidence 1); one
    that names a point past its scan's end stops the stage with the corrections file and the frame named."""
    from leap_core.corrections import ScanCorrections
    from leap_core.datasets.kitti import KittiSequence

    lay = SequenceLayout(_copy_run(baseline, tmp_path / "scan_corr"))
    pole = schema.index("pole")
    before = {f: np.load(lay.points(f)) for f in ("000000", "000001")}
    assert (before["000001"]["label"][[0, 5]] != pole).all()
    ScanCorrections.merge([("000001", [0, 5], pole)]).save(lay.corrections_scan)
    label(street, schema, PipelineConfig(), tmp_path / "scan_corr")
    after = {f: np.load(lay.points(f)) for f in ("000000", "000001")}
    assert after["000001"]["label"][[0, 5]].tolist() == [pole, pole]
    assert after["000001"]["conf"].dtype == np.float16 and after["000001"]["conf"][[0, 5]].tolist() == [1, 1]
    keep = np.ones(len(after["000001"]["label"]), bool)
    keep[[0, 5]] = False
    np.testing.assert_array_equal(after["000001"]["label"][keep], before["000001"]["label"][keep])
    np.testing.assert_array_equal(after["000000"]["label"], before["000000"]["label"])
    n = KittiSequence(street).frame(1).points.shape[0]
    ScanCorrections.merge([("000001", [n], pole)]).save(lay.corrections_scan)
    with pytest.raises(
        DatasetError,
        match=rf"corrections_scan\.npz: frame 000001: point index {n}, the scan "
        rf"has {n}",
    ):
        label(street, schema, PipelineConfig(), tmp_path / "scan_corr")


def test_corrections_survive_smoothing_and_latest_wins(
    baseline, street: Path, schema, tmp_path: Path
) -> None:
    """Every point in a corrected voxel is exported with the corrected class, even at a selection's edge
    where kNN smoothing would otherwise pull it back; a later correction of the same voxel wins."""
    from leap_core.datasets.kitti import KittiSequence, read_label
    from leap_core.fusion import VoxelGrid, voxel_keys
    from leap_core.pipeline import world_points

    run_dir = _copy_run(baseline, tmp_path / "corr_smooth")
    grid = VoxelGrid.load(run_dir / "grid.npz")
    trunk, pole = schema.index("trunk"), schema.index("pole")
    keys = grid.keys[::7][:200]  # scattered voxels: each one is surrounded by uncorrected neighbours
    np.savez(
        run_dir / "corrections.npz",
        keys=np.concatenate([keys, keys[:20]]),
        class_idx=np.concatenate([np.full(len(keys), trunk), np.full(20, pole)]),
    )
    result = label(street, schema, PipelineConfig(), tmp_path / "corr_smooth")
    assert "smooth" in result.ran and "export" in result.ran
    expected = {int(k): trunk for k in keys} | {int(k): pole for k in keys[:20]}
    seq = KittiSequence(street)
    export_ids = schema.export_ids()
    checked = 0
    for i in range(len(seq)):
        frame = seq.frame(i)
        pk = voxel_keys(world_points(frame.points, frame.pose), grid.voxel_size)
        exported = read_label(result.export_dir / f"{frame.frame_id}.label", len(pk))
        for j in np.flatnonzero(np.isin(pk, keys)):
            assert exported[j] == export_ids[expected[int(pk[j])]]
            checked += 1
    assert checked > 0


def test_metrics_from_confusion_equals_evaluate() -> None:
    rng = np.random.default_rng(0)
    gt = rng.integers(-1, 4, 500).astype(np.int16)
    pred = rng.integers(-1, 4, 500).astype(np.int16)
    names, cats = ["a", "b", "c", "d"], ["x", "x", "y", "z"]
    from leap_core.metrics import confusion_matrix

    for ignore in (True, False):
        a = evaluate(gt, pred, names, cats, ignore_unlabeled_pred=ignore)
        b = metrics_from_confusion(
            confusion_matrix(gt[:200], pred[:200], 4) + confusion_matrix(gt[200:], pred[200:], 4),
            names,
            cats,
            ignore_unlabeled_pred=ignore,
        )
        assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())


def test_load_metrics_roundtrip(baseline) -> None:
    run_dir, result, _ = baseline
    tables = load_metrics(run_dir)
    assert tables["camera"]["voxel"].miou == pytest.approx(result.metrics.miou("camera", "voxel"))


def test_bad_inputs_are_one_line_errors(street: Path, schema, tmp_path: Path) -> None:
    with pytest.raises(LeapError, match="velodyne"):
        label(tmp_path, schema, PipelineConfig(), tmp_path / "r")
    with pytest.raises(LeapError, match="until"):
        label(street, schema, PipelineConfig(), tmp_path / "r", until="nope")


@pytest.mark.parametrize("damaged", ["points", "observations"])
def test_evaluate_names_a_damaged_run_file(
    baseline, street: Path, schema, tmp_path: Path, damaged: str
) -> None:
    """evaluate reads two members of a frame's points/ and observations/ files: a damaged one is a
    one-line error naming it, and the stages before keep their outputs."""
    run_dir = _copy_run(baseline, tmp_path / "run")
    bad = sorted((run_dir / damaged).glob("*.npz"))[2]
    bad.write_bytes(bad.read_bytes()[:100])
    (run_dir / "metrics.json").unlink()
    with pytest.raises(DatasetError, match="unreadable") as exc:
        label(street, schema, PipelineConfig(), tmp_path / "run")
    assert str(bad) in str(exc.value)
    assert json.loads((run_dir / "stages.json").read_text())["label_points"]["status"] == "done"


# ------------------------------------------------------------------------------------- stage records
def test_stages_never_started_are_pending(street: Path, schema, tmp_path: Path) -> None:
    label(street, schema, PipelineConfig(), tmp_path / "r", frames=range(0, 1), until="labels2d")
    status = stage_status(folder(tmp_path / "r"))
    assert status["labels2d"]["status"] == "done"
    assert all(status[s] == {"status": "pending"} for s in STAGES[1:])


def test_failed_cancelled_and_done_records(street: Path, schema, tmp_path: Path) -> None:
    """A stage's record after it failed (the error's first line, or its type when it has no message), was
    cancelled, or finished; each with the seconds spent in that call."""
    run_dir = folder(tmp_path / "r")

    def labels2d(stop: BaseException | None) -> tuple[dict, float]:
        """Run the 2D stage on two frames, ``stop`` raised by the progress callback after the first."""

        def progress(stage: str, done: int, total: int) -> None:
            if stop is not None and stage == "labels2d" and done == 1:
                raise stop

        t0 = time.perf_counter()
        try:
            label(
                street,
                schema,
                PipelineConfig(),
                tmp_path / "r",
                progress=progress,
                frames=range(0, 2),
                until="labels2d",
                runtime=Runtime(frame_threads=1),
            )
        except BaseException as exc:
            assert exc is stop  # the stage's own exception, not one raised while recording it
        else:
            assert stop is None
        return stage_status(run_dir)["labels2d"], time.perf_counter() - t0

    cases = [
        (RuntimeError("first line\nsecond line"), "failed", "first line"),
        (RuntimeError(), "failed", "RuntimeError"),
        (Cancelled(), "cancelled", None),
        (None, "done", None),
    ]
    for stop, status, error in cases:
        rec, elapsed = labels2d(stop)
        assert (rec["status"], rec.get("error")) == (status, error)
        assert 0.0 <= rec["seconds"] <= elapsed


def test_frames_without_a_camera_image_are_named_in_a_warning(
    street: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    copy = tmp_path / "00"
    shutil.copytree(street, copy)
    (copy / "image_2" / "000002.png").unlink()
    with caplog.at_level("WARNING", logger="leap_core.pipeline.runner"):
        assert warn_missing_images(KittiSequence(copy), range(0, 6), "simulated") == ["000002"]
        assert warn_missing_images(KittiSequence(copy), range(3, 6), "simulated") == []
    assert [r.getMessage() for r in caplog.records] == [
        f"1 of 6 frames have no camera image in {copy / 'image_2'} (frames 000002): the simulated labeler "
        "labels them from the 2D ground truth only"
    ]
    caplog.clear()
    for p in (copy / "image_2").iterdir():
        p.unlink()
    with caplog.at_level("WARNING", logger="leap_core.pipeline.runner"):
        assert len(warn_missing_images(KittiSequence(copy), range(0, 6), "grounded-sam")) == 6
        assert warn_missing_images(KittiSequence(copy), range(1, 6), "grounded-sam") == [
            f"{i:06d}" for i in range(1, 6)
        ]
    assert [r.getMessage() for r in caplog.records] == [
        f"6 of 6 frames have no camera image in {copy / 'image_2'} (frames 000000, 000001, 000002, 000003, "
        "000004, …): the 2D labeler cannot label them",
        f"5 of 5 frames have no camera image in {copy / 'image_2'} (frames 000001, 000002, 000003, 000004, "
        "000005): the 2D labeler cannot label them",
    ]


def test_a_run_without_poses_is_refused_only_when_an_enabled_stage_needs_them(
    street: Path, tmp_path: Path
) -> None:
    copy = tmp_path / "00"
    shutil.copytree(street, copy)
    (copy / "poses.txt").unlink()
    seq, on = KittiSequence(copy), config_from_dict({"consistency": {"enabled": True}})
    require_poses(seq, PipelineConfig(), STAGE_TABLE[:2])  # the 2D labels and the projection need none
    require_poses(KittiSequence(street), on, STAGE_TABLE)
    for cfg, needing in (
        (PipelineConfig(), "fuse, label_points, tracks, evaluate"),
        (on, "fuse, 3dcn, label_points, tracks, evaluate"),
    ):
        with pytest.raises(PosesMissingError, match=rf"poses\.txt: no poses: the 3D stages \({needing}\)"):
            require_poses(seq, cfg, STAGE_TABLE)


def test_a_run_without_poses_stops_before_any_stage_but_a_2d_run_warns_and_runs(
    street: Path, schema, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    copy = tmp_path / "00"
    shutil.copytree(street, copy)
    (copy / "poses.txt").unlink()
    (copy / "image_2" / "000001.png").unlink()
    run_dir = folder(tmp_path / "r")
    with caplog.at_level("WARNING", logger="leap_core.pipeline.runner"):
        result = label(copy, schema, PipelineConfig(), tmp_path / "r", frames=range(0, 2), until="project")
    assert result.ran == ["labels2d", "project"]
    assert [r.getMessage().split(":")[0] for r in caplog.records] == [
        f"1 of 2 frames have no camera image in {copy / 'image_2'} (frames 000001)"
    ]
    with pytest.raises(PosesMissingError, match=r"poses\.txt"):
        label(copy, schema, PipelineConfig(), tmp_path / "r", frames=range(0, 2))
    assert stage_status(run_dir)["fuse"] == {"status": "pending"}  # refused before the stage started
    # A run that stops at the first stage needing poses is refused before its 2D labels too.
    with pytest.raises(PosesMissingError, match=r"poses\.txt"):
        label(copy, schema, PipelineConfig(), tmp_path / "r2", frames=range(0, 2), until="fuse")
    assert stage_status(folder(tmp_path / "r2"))["labels2d"] == {"status": "pending"}


def test_fingerprints_hash_the_documented_parts(baseline, street: Path, schema) -> None:
    """A stage's fingerprint is the hash of: pipeline version, class count, stage name, upstream
    fingerprints, the config sections it reads and its other inputs (a disabled stage: ``enabled`` false
    instead). Their spelling is part of the contract: run folders of earlier versions stay cached only
    while it holds (as tests/test_runs.py checks for the 3D-CN)."""
    run_dir, _, _ = baseline
    cfg = PipelineConfig()
    fp = stage_fingerprints(street, schema, cfg, run_dir)
    sections = config_to_dict(cfg)

    def parts(stage: str, up: list[str], **rest: object) -> str:
        return hash_json(
            {
                "v": PIPELINE_VERSION,
                "C": schema.num_classes,
                "stage": stage,
                "up": [fp[u] for u in up],
                **rest,
            }
        )

    frames = hash_json([f"{i:06d}" for i in range(6)])
    assert fp["project"] == parts("project", ["labels2d"], config={"projection": sections["projection"]})
    assert fp["motion"] == parts("motion", ["project"], enabled=False)
    assert fp["fuse"] == parts(
        "fuse",
        ["project", "motion"],
        config={"fusion": sections["fusion"]},
        inputs={"frames": frames, "corrections": None, "strength": None},
    )
    assert fp["smooth"] == parts("smooth", ["fuse"], config={"smoothing": sections["smoothing"]})
    assert fp["3dcn"] == parts("3dcn", ["project", "fuse", "smooth"], enabled=False)
    assert {s: r["fingerprint"] for s, r in stage_status(run_dir).items()} == fp


def test_world_cells_are_an_input_of_the_2d_labels_only_where_present(street: Path, tmp_path: Path) -> None:
    """The simulated labeler's world tiles read ``gt2d/cell``: a changed cell image changes that frame's
    labels2d input digest and the dataset identity; a sequence without the folder (real data, or one
    generated before it existed) hashes as it did before the folder existed."""
    from leap_core.pipeline.context import dataset_identity, frame_input_digest

    copy = tmp_path / "00"
    shutil.copytree(street, copy)
    seq = KittiSequence(copy)
    before = [frame_input_digest(seq, i) for i in range(2)]
    ident = dataset_identity(seq)
    cell = copy / "gt2d" / "cell" / "000000.png"
    write_png16(cell, read_png16(cell) + 1)
    after = [frame_input_digest(KittiSequence(copy), i) for i in range(2)]
    assert after[0] != before[0] and after[1] == before[1]
    assert dataset_identity(KittiSequence(copy)) != ident
    # Without the folder: the identity of the folder list before gt2d/cell existed.
    shutil.rmtree(copy / "gt2d" / "cell")
    bare = KittiSequence(copy)
    root = copy.resolve()
    legacy = [str(root), file_digest(root / "calib.txt"), file_digest(bare.poses_path)]
    for name in ["velodyne", "labels", "image_2", "gt2d/semantic", "gt2d/instance", "gt2d/name"]:
        folder = root / name
        entries = (
            None
            if not folder.is_dir()
            else sorted(
                (e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in os.scandir(folder) if e.is_file()
            )
        )
        legacy.append([name, entries])
    assert dataset_identity(bare) == hash_json(legacy)


def test_stage_records_and_progress(baseline) -> None:
    """What each stage adds to its record, and the progress calls of a stage that works per frame, the
    fusion (one per frame read, then done) and the smoothing (start, done)."""
    from leap_core.fusion import VoxelGrid

    run_dir, _, calls = baseline
    records = stage_status(run_dir)
    voxels = VoxelGrid.load(run_dir / "grid.npz").num_voxels
    assert (records["fuse"]["voxels"], records["fuse"]["corrections"]) == (voxels, 0)
    assert records["smooth"]["voxels"] == voxels
    assert (records["labels2d"]["labeler"], records["labels2d"]["cache_hits"]) == ("simulated", 0)
    assert (records["project"]["frames_done"], records["project"]["frames_computed"]) == (6, 6)
    assert records["3dcn"]["note"] == "3D-CN disabled"
    for stage in ("labels2d", "project", "fuse", "label_points", "export"):
        assert [c for c in calls if c[0] == stage] == [(stage, k, 6) for k in range(7)], stage
    assert [c for c in calls if c[0] == "smooth"] == [("smooth", 0, 1), ("smooth", 1, 1)]
    assert [c for c in calls if c[0] == "3dcn"] == [("3dcn", 6, 6)]


def test_a_damaged_2d_cache_entry_is_recomputed(street: Path, schema, tmp_path: Path) -> None:
    cache = Runtime(cache_dir=tmp_path / "cache")
    label(
        street, schema, PipelineConfig(), tmp_path / "a", frames=range(0, 2), until="labels2d", runtime=cache
    )
    entries = sorted((tmp_path / "cache" / "labels2d").glob("*/*.npz"))
    # The layout docs/METHOD.md gives (entries of other versions would be orphaned by any other):
    # labels2d/<16 hex digits of the labeler's fingerprint and C>/<frame id>-<20 hex digits of its inputs>.npz
    assert [e.name[:7] for e in entries] == ["000000-", "000001-"]
    assert all(re.fullmatch(r"[0-9a-f]{16}", e.parent.name) for e in entries)
    assert all(re.fullmatch(r"\d{6}-[0-9a-f]{20}\.npz", e.name) for e in entries)
    good = entries[0].read_bytes()
    entries[0].write_bytes(b"damaged")
    label(
        street, schema, PipelineConfig(), tmp_path / "b", frames=range(0, 2), until="labels2d", runtime=cache
    )
    assert stage_status(folder(tmp_path / "b"))["labels2d"]["cache_hits"] == 1
    assert entries[0].read_bytes() == good
    assert (folder(tmp_path / "b") / "labels2d" / "000000.npz").read_bytes() == good


def test_a_2d_cache_entry_without_instances_is_recomputed(street: Path, schema, tmp_path: Path) -> None:
    """An entry written before labelers gave instances has the same key: it is not served but recomputed
    (the stage's record counts it) and replaced by one with the same masks and the instances."""
    cache = Runtime(cache_dir=tmp_path / "cache")
    label(
        street, schema, PipelineConfig(), tmp_path / "a", frames=range(0, 2), until="labels2d", runtime=cache
    )
    entries = sorted((tmp_path / "cache" / "labels2d").glob("*/*.npz"))
    new = load_soft(entries[0])
    assert new.instances is not None and new.instances.num_instances > 0
    old = {k: v for k, v in new.arrays().items() if not k.startswith("instance_")}
    entries[0].unlink()  # the run folder's hard link keeps its file
    with entries[0].open("wb") as fh:
        np.savez_compressed(fh, **old)
    label(
        street, schema, PipelineConfig(), tmp_path / "b", frames=range(0, 2), until="labels2d", runtime=cache
    )
    record = stage_status(folder(tmp_path / "b"))["labels2d"]
    assert (record["cache_hits"], record["cache_refreshed"]) == (1, 1)
    again = load_soft(entries[0])
    assert again.instances is not None
    np.testing.assert_array_equal(again.instances.ids, new.instances.ids)
    np.testing.assert_array_equal(again.bits, new.bits)
    assert "cache_refreshed" not in stage_status(folder(tmp_path / "a"))["labels2d"]


def test_the_2d_cache_is_keyed_by_the_labeler_config(street: Path, schema, tmp_path: Path) -> None:
    """Two labeler settings share a cache folder but never its entries: a run with another simulated seed
    finds nothing to reuse and gets its own masks; the first setting then still hits its own."""
    cache = Runtime(cache_dir=tmp_path / "cache")
    other = config_from_dict({"simulated": {"seed": 5}})
    for name, cfg in (("a", PipelineConfig()), ("b", other), ("c", PipelineConfig())):
        label(street, schema, cfg, tmp_path / name, frames=range(0, 2), until="labels2d", runtime=cache)
    hits = {n: stage_status(folder(tmp_path / n))["labels2d"]["cache_hits"] for n in "abc"}
    assert hits == {"a": 0, "b": 0, "c": 2}
    assert len(list((tmp_path / "cache" / "labels2d").iterdir())) == 2
    masks = {n: (folder(tmp_path / n) / "labels2d" / "000000.npz").read_bytes() for n in "abc"}
    assert masks["a"] == masks["c"] != masks["b"]


def test_stage_errors_name_their_file(baseline, street: Path, schema, tmp_path: Path) -> None:
    no_gt2d = tmp_path / "00"
    shutil.copytree(street, no_gt2d)
    shutil.rmtree(no_gt2d / "gt2d")
    # Refused before any frame is read, with what the labeler needs and the other choice.
    with pytest.raises(
        LeapError,
        match=r"gt2d/semantic: the simulated labeler needs 2D ground truth .* "
        r"choose the grounded-sam labeler",
    ):
        label(no_gt2d, schema, PipelineConfig(), tmp_path / "r0", frames=range(0, 1), until="labels2d")
    run_dir = _copy_run(baseline, tmp_path / "r")
    (run_dir / "labels2d" / "000002.npz").write_bytes(b"damaged")
    shutil.rmtree(run_dir / "observations")
    with pytest.raises(LeapError, match=r"labels2d/000002\.npz: unreadable 2D label file"):
        label(street, schema, PipelineConfig(), tmp_path / "r", until="project")
    run_dir = _copy_run(baseline, tmp_path / "s")
    (run_dir / "points" / "000003.npz").write_bytes(b"damaged")
    shutil.rmtree(run_dir / "export")
    with pytest.raises(LeapError, match=r"points/000003\.npz: unreadable point labels"):
        label(street, schema, PipelineConfig(), tmp_path / "s")


def test_skip_reason_of_a_finished_run(baseline) -> None:
    """What the progress displays say of each stage of the baseline run (3D-CN off) when a later run
    reports it complete: cached stages "unchanged", the disabled 3D-CN its note; a stage that finished
    after the run started (or at the same instant) computed in it."""
    run_dir, _, _ = baseline
    status = stage_status(run_dir)
    later = max(float(r.get("finished", 0.0)) for r in status.values()) + 1.0
    assert skip_reason(run_dir, "fuse", later) == UNCHANGED
    assert skip_reason(run_dir, "3dcn", later) == "3D-CN disabled"
    assert skip_reason(run_dir, "fuse", status["fuse"]["finished"]) is None
    assert skip_reason(run_dir, "fuse", 0.0) is None
    assert skip_reason(run_dir, "no_such_stage", later) is None


def test_skip_reason_reads_the_stage_record(tmp_path: Path) -> None:
    """skip_reason is a function of ``stages.json``: records another program version (or a hand edit) may
    have left, including a skipped record without a note and a failed one that carries a finish time."""
    lay = SequenceLayout(tmp_path / "r")
    lay.folder.mkdir()
    lay.state.write_text(
        json.dumps(
            {
                "labels2d": {"status": "done", "finished": 100.0},
                "project": {"status": "skipped"},
                "fuse": {"status": "failed", "finished": 100.0},
                "smooth": {"status": "skipped", "note": "no ground truth"},
                "3dcn": {"status": "done"},
            }
        )
    )
    assert skip_reason(lay.folder, "labels2d", 100.5) == UNCHANGED
    assert skip_reason(lay.folder, "labels2d", 100.0) is None
    assert skip_reason(lay.folder, "project", 100.5) == "nothing to do"
    assert skip_reason(lay.folder, "fuse", 100.5) is None
    assert skip_reason(lay.folder, "smooth", 100.5) == "no ground truth"
    assert skip_reason(lay.folder, "3dcn", 100.5) is None  # done, finish time unknown: not "unchanged"
    assert skip_reason(lay.folder, "evaluate", 100.5) is None  # pending
    lay.state.write_text("{not json")
    assert skip_reason(lay.folder, "labels2d", 100.5) is None  # an unreadable record says nothing


def test_a_model_labeler_fingerprint_follows_the_runtime_models(street: Path, schema, tmp_path: Path) -> None:
    """The models folder is part of the run's runtime, not its config: planning and fingerprints must use
    the runtime they are given (another model folder content = other 2D labels, everything reruns)."""
    from leap_core.labelers.grounded_sam import GroundedSamConfig, model_folder_name

    cfg = config_from_dict({"labeler": "grounded-sam"})
    gs = cfg.labeler_config(GroundedSamConfig)
    fps = []
    for version in ("a", "b"):
        models = tmp_path / f"models_{version}"
        for model_id in (gs.detector_id, gs.segmenter_id):
            folder = models / model_folder_name(model_id)
            folder.mkdir(parents=True)
            (folder / "config.json").write_text(json.dumps({"version": version}))
        runtime = Runtime(models_dir=models)
        fps.append(stage_fingerprints(street, schema, cfg, tmp_path / "r", runtime=runtime))
        assert all(plan_stages(street, schema, cfg, tmp_path / "r", runtime=runtime).values())
    assert all(fps[0][s] != fps[1][s] for s in STAGES)


# -------------------------------------------------------------------------------------------- config
def test_config_roundtrip_through_json() -> None:
    cfg = config_from_dict(
        {
            "fusion": {"voxel_size": 0.3},
            "simulated": {"peak_prob": [0.6, 0.7]},
            "consistency": {"enabled": True, "backbone": {"channels": 32}},
        }
    )
    d = json.loads(json.dumps(config_to_dict(cfg)))
    assert config_from_dict(d) == cfg
    assert cfg.fusion.voxel_size == 0.3 and cfg.labeler_config(SimulatedLabelerConfig).peak_prob == (0.6, 0.7)
    assert cfg.consistency.backbone.channels == 32 and cfg.consistency.backbone.layers == 6
    # Overrides apply on a base, keeping the base's other values.
    again = config_from_dict({"smoothing": {"k": 3}}, cfg)
    assert again.smoothing.k == 3 and again.fusion.voxel_size == 0.3


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"fusion": {"voxel_size": 0}}, "pipeline.fusion.voxel_size: must be"),
        (
            {"fusion": {"voxel_sise": 0.1}},
            "pipeline.fusion.voxel_sise: unknown setting (did you mean 'voxel_size'?)",
        ),
        ({"smoothing": {"k": "9"}}, "pipeline.smoothing.k: must be an integer"),
        ({"smoothing": {"k": True}}, "pipeline.smoothing.k: must be an integer"),
        ({"consistency": {"share": 1.5}}, "pipeline.consistency.share: must be in (0, 1]"),
        (
            {"consistency": {"backbone": {"channels": 2}}},
            "pipeline.consistency.backbone.channels: must be in [4, 1024], got 2",
        ),
        ({"grounded_sam": {"box_threshold": 1.5}}, "pipeline.grounded_sam.box_threshold: must be in (0, 1)"),
        ({"labeler": "sam"}, "pipeline.labeler: must be one of 'simulated', 'grounded-sam', 'sam3'"),
        ({"simulated": {"peak_prob": [0.5]}}, "pipeline.simulated.peak_prob: must be a list of 2 values"),
        (
            {"simulated": {"class_recall": {"car": 2}}},
            "pipeline.simulated.class_recall.car: must be in [0, 1]",
        ),
        ({"projection": 3}, "pipeline.projection: must be a mapping"),
        ({"bogus": 1}, "pipeline.bogus: unknown setting"),
    ],
)
def test_config_errors_name_the_field(overrides: dict, message: str) -> None:
    with pytest.raises(LeapError) as info:
        config_from_dict(overrides)
    assert str(info.value).startswith(message)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------------------------- CLI
def test_cli_run_prints_table_and_export(street: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import cli as app
    from leap_core.schema import projects_dir

    project = tmp_path / "proj.yaml"
    text = (projects_dir() / "semantickitti.yaml").read_text()
    project.write_text(text + "\npipeline:\n  smoothing: {k: 5}\n  simulated: {recall: 0.95}\n")
    out = tmp_path / "run"
    res = CliRunner().invoke(
        app,
        [
            "run",
            str(street),
            "--out",
            str(out),
            "--project-file",
            str(project),
            "--frames",
            "0:4",
            "--labeler",
            "simulated",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "2D labels: simulated" in res.output
    assert "point" in res.output and "voxel" in res.output and "mIoU" in res.output
    assert "the paper's Table 1" in res.output and "manmade" in res.output  # the paper's protocol too
    seq_dir = folder(out)
    assert f"4 .label files (+ .conf confidences) in {seq_dir / 'export'}" in res.output
    assert json.loads((seq_dir / "stages.json").read_text())["smooth"]["status"] == "done"
    assert len(list((seq_dir / "export").glob("*.label"))) == 4
    again = CliRunner().invoke(
        app, ["run", str(street), "--out", str(out), "--project-file", str(project), "--frames", "0:4"]
    )
    assert again.exit_code == 0 and "labels2d cached" in again.output
    # While another process works in the folder (the app's worker, another `leap run`), a run is refused
    # before it touches anything: two runs in one folder delete each other's temporaries.
    from app.jobs.worker import run_dir_lock

    state = (seq_dir / "stages.json").read_bytes()
    with run_dir_lock(out):
        busy = CliRunner().invoke(
            app,
            [
                "run",
                str(street),
                "--out",
                str(out),
                "--project-file",
                str(project),
                "--frames",
                "0:4",
                "--no-3dcn",
            ],
        )
    assert busy.exit_code == 2 and "another process is working in this run folder" in busy.output, busy.output
    assert (seq_dir / "stages.json").read_bytes() == state


def test_cli_exports_never_replace_files_silently(street: Path, tmp_path: Path) -> None:
    import zipfile

    from click.testing import Result
    from typer.testing import CliRunner

    from app.cli import cli as app
    from leap_core.export import load_label_map

    def run(*args: str) -> Result:
        return CliRunner().invoke(
            app,
            [
                "run",
                str(street),
                "--out",
                str(tmp_path / "run"),
                "--frames",
                "0:2",
                "--labeler",
                "simulated",
                *args,
            ],
        )

    gt = {p.name: p.read_bytes() for p in (street / "labels").iterdir()}
    for bad in (street / "labels", street / "velodyne"):
        res = run("--export-to", str(bad), "--overwrite")
        assert res.exit_code == 2 and "--export-to:" in res.output.strip().splitlines()[-1], res.output
        assert not (tmp_path / "run").exists()  # refused before the run started
    assert {p.name: p.read_bytes() for p in (street / "labels").iterdir()} == gt

    # --export-to DIR writes DIR/sequences/<name>/predictions/, the layout SemanticKITTI tools read.
    target, zpath = tmp_path / "out", tmp_path / "out" / "labels.zip"
    preds = target / "sequences" / "00" / "predictions"
    res = run("--export-to", str(target), "--zip", str(zpath))
    assert res.exit_code == 0, res.output
    assert "unlabeled:" in res.output and "outside every camera view" in res.output
    assert sorted(p.name for p in preds.iterdir()) == ["000000.label", "000001.label"]
    with zipfile.ZipFile(zpath) as zf:
        lm = load_label_map(zf.read("label-map.yaml").decode())
        assert "sequences/00/predictions/000001.label" in zf.namelist()
    assert sum(lm.counts.values()) == sum(p.stat().st_size // 4 for p in preds.iterdir())

    (preds / "000000.label").write_bytes(b"mine")
    for args in (("--export-to", str(target)), ("--zip", str(zpath))):
        res = run(*args)
        assert res.exit_code == 2 and "--overwrite" in res.output.strip().splitlines()[-1], res.output
    assert (preds / "000000.label").read_bytes() == b"mine"
    res = run("--export-to", str(target), "--zip", str(zpath), "--overwrite")
    assert res.exit_code == 0 and f"wrote 2 files to {target}/sequences/{{00}}/predictions/" in res.output, (
        res.output
    )
    assert (preds / "000000.label").read_bytes() != b"mine"


def test_cli_refuses_a_sequence_folder_as_the_export_folder(street: Path, tmp_path: Path) -> None:
    """--export-to names the dataset folder holding sequences/: a sequence folder given instead (the
    place a one-sequence export used to go) would get a sequences/<name>/predictions/ tree inside the
    dataset; refused before the run."""
    from typer.testing import CliRunner

    from app.cli import cli as app

    seq = tmp_path / "data" / "sequences" / "00"
    shutil.copytree(street, seq)
    args = ["run", str(seq), "--out", str(tmp_path / "run"), "--frames", "0:1", "--export-to", str(seq)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and "--export-to:" in res.output.strip().splitlines()[-1], res.output
    assert not (tmp_path / "run").exists() and not (seq / "sequences").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--labeler", "dino"], "pipeline.labeler: must be one of"),
        (["--frames", "x:y"], "--frames 'x:y'"),
        (["--frames", "3:99"], "out of range"),
        (["--schema", "nope"], "--schema nope"),
        (["--3dcn-iterations", "3"], "--3dcn-iterations: must be 1 or 2, got 3"),
        (["--no-3dcn", "--3dcn-iterations", "2"], "drop --no-3dcn or --3dcn-iterations"),
        (["--3dcn-init", "nowhere.pt"], "--3dcn-init nowhere.pt: no such file"),
        (["--no-3dcn", "--3dcn-init", "x.pt"], "drop --no-3dcn or --3dcn-init"),
    ],
)
def test_cli_run_bad_inputs(street: Path, tmp_path: Path, args: list[str], message: str) -> None:
    from typer.testing import CliRunner

    from app.cli import cli as app

    res = CliRunner().invoke(app, ["run", str(street), "--out", str(tmp_path / "r"), *args])
    assert res.exit_code == 2
    last = res.output.strip().splitlines()[-1]
    assert last.startswith("error:") and message in last


def test_cli_3dcn_iterations_sets_the_rounds() -> None:
    """`leap run --3dcn-iterations 2` is the README's "+3D-CN x2" column: the 3D-CN on, two rounds, on top
    of the project's settings (the demo project's 3D-CN section is kept, only the two fields change)."""
    from app.cli import _run_config

    _, cfg = _run_config(None, None, None, None, 2)
    assert cfg.consistency.enabled and cfg.consistency.iterations == 2
    _, cfg = _run_config(None, None, None, True, 1)
    assert cfg.consistency.enabled and cfg.consistency.iterations == 1
    _, base = _run_config(None, None, None, None)
    assert not base.consistency.enabled and base.consistency.iterations == 1
    _, tuned = _run_config(None, None, None, None, init_3dcn="some.pt")
    assert tuned.consistency.enabled and tuned.consistency.iterations == 1
    _, demo = _run_config(None, "demo", None, None, 2)
    _, demo_base = _run_config(None, "demo", None, None)
    assert demo.consistency == dataclasses.replace(demo_base.consistency, enabled=True, iterations=2)


def test_demo_project_file_is_valid_and_in_sync() -> None:
    from leap_core.schema import load_project_file, projects_dir

    schema, pipeline = load_project_file(projects_dir() / "demo.yaml")
    cfg = config_from_dict(pipeline)
    # The demo's classes are a copy of the SemanticKITTI schema; its pipeline section spells out the defaults.
    assert schema.classes == builtin_schema("semantickitti").classes
    assert cfg == PipelineConfig()


@pytest.mark.slow
def test_3dcn_rows_and_caching(baseline, street: Path, schema, tmp_path: Path) -> None:
    """3D-CN wiring: rows +3D-CN x1/x2, every point labeled, a temperature change refits nothing upstream."""
    out = tmp_path / "cn"
    run_dir = _copy_run(baseline, out)
    # new_voxel_margin 0: every voxel the network predicts is created (this tiny network is sure of few).
    tiny = {
        "enabled": True,
        "iterations": 2,
        "points_per_scan": 1024,
        "num_threads": 1,
        "min_steps": 0,
        "new_voxel_margin": 0.0,
        "backbone": {"channels": 8, "layers": 1, "knn": 4},
    }
    cfg = config_from_dict({"consistency": tiny})
    result = label(street, schema, cfg, out)
    assert result.ran == ["3dcn", "label_points", "tracks", "evaluate", "export"]
    m = result.metrics
    assert m.rows == ["point", "voxel", "+3D-CN x1", "+3D-CN x2", "objects"]
    # The network predicts every point, so every point gets a label (all-points protocol share = 1).
    assert m.table("all")["+3D-CN x2"].labeled_share == pytest.approx(1.0)
    assert m.table("all")["voxel"] == baseline[1].metrics.table("all")["voxel"]
    with np.load(run_dir / "points" / "000000.npz") as z:
        assert (z["label"] >= 0).all()
    assert (out / "3dcn" / "3dcn_iter2.pt").is_file()
    # Temperature only changes the fusion back: round 1's checkpoint is reused and upstream stages are
    # cached. Round 2 trains on labels read from round 1's output, which T changed, so it retrains.
    ckpt1 = out / "3dcn" / "3dcn_iter1.pt"
    before = (ckpt1.stat().st_mtime_ns, ckpt1.read_bytes())
    grid_before = (run_dir / "grid_3dcn1.npz").read_bytes()
    warmer = config_from_dict({"consistency": {**tiny, "temperature": 4.0}})
    again = label(street, schema, warmer, out)
    assert again.ran == ["3dcn", "label_points", "tracks", "evaluate", "export"]
    assert (ckpt1.stat().st_mtime_ns, ckpt1.read_bytes()) == before  # not retrained, not rewritten
    assert (run_dir / "grid_3dcn1.npz").read_bytes() != grid_before  # ... yet fused back with the new T
    assert "+3D-CN x1" in (result_tables(run_dir) or "")


# ------------------------------------------------------------------------------------------ file modes
@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_written_files_get_the_mode_open_gives_under_the_umask(
    street: Path, schema, tmp_path: Path, umask: int
) -> None:
    """Run outputs, the shared 2D cache, a folder export and a zip export get 0o666 & ~umask (0644, 0664)
    like any file ``open()`` creates, not mkstemp's 0600, and folders 0o777 & ~umask."""
    import os
    import stat

    from leap_core.export import run_export, write_export_folder, write_export_zip

    run_dir, cache = tmp_path / "run", tmp_path / "cache"
    old = os.umask(umask)
    try:
        result = label(
            street, schema, PipelineConfig(), run_dir, frames=range(0, 2), runtime=Runtime(cache_dir=cache)
        )
        assert result.export_dir is not None
        labels = sorted(result.export_dir.glob("*.label"))
        write_export_folder(tmp_path / "out" / "predictions", labels)
        write_export_zip(
            tmp_path / "out" / "labels.zip",
            run_export(run_dir),
            {"summary.yaml": "a: 1\n"},
            include_confidence=True,
        )
    finally:
        os.umask(old)
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    names = {p.relative_to(tmp_path).as_posix() for p in files}
    for must in (
        "run/run.json",
        "run/metrics.json",
        "run/sequences/00/export/000001.label",
        "run/sequences/00/export/000001.conf",
        "run/sequences/00/points/000000.npz",
        "run/sequences/00/grid.npz",
        "run/sequences/00/stages.json",
        "run/sequences/00/metrics.json",
        "out/predictions/000000.label",
        "out/labels.zip",
    ):
        assert must in names
    assert any(n.startswith("cache/") for n in names)
    modes = {p.relative_to(tmp_path).as_posix(): oct(stat.S_IMODE(p.stat().st_mode)) for p in files}
    assert set(modes.values()) == {oct(0o666 & ~umask)}, modes
    folders = {
        p.relative_to(tmp_path).as_posix(): oct(stat.S_IMODE(p.stat().st_mode))
        for p in tmp_path.rglob("*")
        if p.is_dir()
    }
    assert set(folders.values()) == {oct(0o777 & ~umask)}, folders
