"""Steering functions: class colours, raw ground-truth ids, setting scopes, the recompute preview, run
changes and the all-points labeled share."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from runhelpers import folder, label
from test_pipeline import make_street

from leap_core.colors import CANDIDATES, UNLABELED_RGB, distinct_color, srgb_to_lab
from leap_core.config import PipelineConfig, config_from_dict, config_to_dict
from leap_core.datasets.kitti import write_label
from leap_core.datasets.raw_ids import (
    SEMANTIC_KITTI_RAW_NAMES,
    raw_id_counts,
    raw_id_names,
    sample_indices,
    scan_raw_ids,
)
from leap_core.errors import DatasetError
from leap_core.pipeline import (
    STAGE_TABLE,
    SequenceMetrics,
    plan_stages,
    stage_fingerprints,
)
from leap_core.pipeline.context import read_state
from leap_core.pipeline.steering import (
    CorrectionNote,
    changed_sections,
    correction_changes,
    ignored_reason,
    recompute_plan,
    run_changes,
    setting_scope,
)
from leap_core.run_layout import SequenceLayout
from leap_core.schema import ClassDef, builtin_schema
from leap_core.synth.names import DEMO_EXTRA_RAW_IDS


# ------------------------------------------------------------------------------------------ colours
def _min_delta_e(color, others) -> float:
    lab = srgb_to_lab(np.asarray(color, float))
    return float(np.linalg.norm(srgb_to_lab(np.asarray(others, float)) - lab, axis=-1).min())


def test_lab_of_reference_colours() -> None:
    assert srgb_to_lab([255, 255, 255]) == pytest.approx([100.0, 0.0, 0.0], abs=1e-3)
    assert srgb_to_lab([0, 0, 0]) == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
    # sRGB red in CIELAB (D65): L 53.24, a 80.09, b 67.20 (the standard conversion's published values).
    assert srgb_to_lab([255, 0, 0]) == pytest.approx([53.24, 80.09, 67.20], abs=0.05)


def test_distinct_color_is_the_farthest_candidate_and_never_grey_or_used() -> None:
    schema = builtin_schema("semantickitti")
    used = [c.color for c in schema.classes]
    pick = distinct_color(used)
    assert list(pick) not in [list(u) for u in used]
    # Brute force over the candidates: nothing is farther from every used colour and from grey.
    best = max(_min_delta_e(c, [*used, UNLABELED_RGB]) for c in CANDIDATES.tolist())
    assert _min_delta_e(pick, [*used, UNLABELED_RGB]) == pytest.approx(best)
    assert _min_delta_e(pick, [UNLABELED_RGB]) > 30  # clearly not grey


def test_distinct_colors_added_one_by_one_stay_apart() -> None:
    used: list[tuple[int, int, int]] = []
    for _ in range(12):
        used.append(distinct_color(used))
    assert len(set(used)) == 12
    for a, b in itertools.combinations(used, 2):
        assert _min_delta_e(a, [b]) > 20
    assert all(_min_delta_e(c, [UNLABELED_RGB]) > 30 for c in used)
    assert distinct_color([]) == distinct_color([])  # deterministic
    # With no class yet, the first colour is the candidate farthest from unlabeled grey.
    farthest = max(_min_delta_e(c, [UNLABELED_RGB]) for c in CANDIDATES.tolist())
    assert _min_delta_e(distinct_color([]), [UNLABELED_RGB]) == pytest.approx(farthest)


# ------------------------------------------------------------------------------------------ raw ids
def test_raw_id_names_merge_semantic_kitti_and_the_ids_a_caller_passes() -> None:
    # The demo world's ids reach the names as data (the app passes them); leap_core/datasets knows none.
    names = raw_id_names(DEMO_EXTRA_RAW_IDS)
    assert names[10] == "car" and names[252] == "moving-car" and names[81] == "traffic-sign"
    assert names[300] == "traffic-cone" and names[301] == "bench" and names[302] == "bollard"
    assert len(SEMANTIC_KITTI_RAW_NAMES) == 34 and set(DEMO_EXTRA_RAW_IDS) <= set(names)
    assert not set(SEMANTIC_KITTI_RAW_NAMES) & set(DEMO_EXTRA_RAW_IDS)
    assert raw_id_names() == dict(SEMANTIC_KITTI_RAW_NAMES) and 300 not in raw_id_names()
    # A dataset's own name of an id wins over SemanticKITTI's.
    assert raw_id_names({10: "sedan", 400: "tractor"})[10] == "sedan"


def test_raw_id_counts_use_the_low_16_bits() -> None:
    labels = np.array([10 | (3 << 16), 10, 300 | (7 << 16), 0, 300], np.uint32)
    assert raw_id_counts(labels) == {0: 1, 10: 2, 300: 2}


@pytest.mark.parametrize(
    ("total", "k", "expected"),
    [(10, 4, [0, 3, 6, 9]), (3, 5, [0, 1, 2]), (5, 1, [0]), (0, 3, []), (7, 2, [0, 6])],
)
def test_sample_indices(total: int, k: int, expected: list[int]) -> None:
    assert sample_indices(total, k) == expected


def test_scan_raw_ids_reads_a_sample_and_names_the_bad_file(tmp_path: Path) -> None:
    root = tmp_path / "seq"
    for i in range(6):
        ids = np.array([40, 40, 10] + ([300] if i == 5 else []), np.uint32)
        write_label(root / "labels" / f"{i:06d}.label", ids)
    full = scan_raw_ids(root)
    assert full.counts == {10: 6, 40: 12, 300: 1} and (full.frames_read, full.frames_total) == (6, 6)
    part = scan_raw_ids(root, max_frames=2)  # files 0 and 5: the last one is always read
    assert part.counts == {10: 2, 40: 4, 300: 1} and part.frames_read == 2
    assert scan_raw_ids(tmp_path / "nothing").counts == {}
    (root / "labels" / "000002.label").write_bytes(b"abc")
    with pytest.raises(DatasetError, match=r"000002\.label"):
        scan_raw_ids(root)


# ------------------------------------------------------------------------------------ setting scopes
def test_setting_scopes_come_from_the_labeler_and_stage_records() -> None:
    assert setting_scope("grounded_sam.box_threshold").labeler == "grounded-sam"
    assert setting_scope("simulated.recall").labeler == "simulated"
    assert setting_scope("consistency.share").stage == "3dcn"
    assert setting_scope("consistency.enabled").stage is None  # the switch itself always applies
    assert setting_scope("smoothing.k") == setting_scope("fusion.voxel_size") == setting_scope("labeler")

    default = PipelineConfig()
    threshold = ignored_reason(default, "grounded_sam.box_threshold")
    assert threshold is not None and "simulated" in threshold
    assert ignored_reason(default, "consistency.share") == "the 3D-CN stage is off"
    # A caller's names of the settings (dotted path → label) name the switch.
    named = ignored_reason(default, "consistency.share", {"consistency.enabled": "3D-CN on"})
    assert named == "the 3D-CN stage is off (3D-CN on is unticked)"
    assert ignored_reason(default, "smoothing.k") is None
    gsam = config_from_dict({"labeler": "grounded-sam", "consistency": {"enabled": True}})
    assert ignored_reason(gsam, "grounded_sam.box_threshold") is None
    assert ignored_reason(gsam, "consistency.share") is None


# ------------------------------------------------------------------------------------- run changes
def _snapshot(schema, cfg: PipelineConfig, frames=None, *more: dict) -> dict:
    """A run's input snapshot as the app stores it: sequence 00 of /d/seq (``frames``), then ``more``."""
    return {
        "sequences": [{"name": "00", "dataset": "/d/seq", "frames": frames}, *more],
        "schema": schema.to_dict(),
        "pipeline": config_to_dict(cfg),
    }


def test_run_changes_list_classes_prompts_ids_and_parameters() -> None:
    schema = builtin_schema("semantickitti")
    car = schema.classes[0]
    edited = schema.with_classes(
        [
            dataclasses.replace(car, prompts=(*car.prompts[:-1], "sedan")),
            *schema.classes[1:],
            ClassDef(
                name="traffic-cone",
                color=(255, 120, 0),
                prompts=("traffic cone",),
                export_id=300,
                gt_ids=(300,),
            ),
        ]
    )
    old = _snapshot(schema, PipelineConfig())
    new = _snapshot(
        edited,
        config_from_dict({"smoothing": {"k": 4}, "grounded_sam": {"box_threshold": 0.3}}),
        frames=[0, 3],
    )
    labels = {"smoothing.k": "kNN smoothing k", "grounded_sam.box_threshold": "Box threshold"}
    texts = {c.text: c for c in run_changes(old, new, labels)}
    frames = texts["sequence 00: frames all → 0..2"]
    assert (frames.kind, frames.subject) == ("frames", "00")
    assert 'prompts of car: + "sedan", − "jeep"' in texts
    assert 'class traffic-cone added (prompts "traffic cone"; ground-truth ids 300)' in texts
    k = texts["kNN smoothing k (smoothing.k): 9 → 4"]
    assert k.kind == "parameter" and k.ignored is None
    thr = texts["Box threshold (grounded_sam.box_threshold): 0.25 → 0.3"]
    assert thr.ignored is not None and "simulated" in thr.ignored
    # Without names, a parameter is its dotted path.
    assert "smoothing.k: 9 → 4" in {c.text for c in run_changes(old, new)}
    assert run_changes(old, old) == []
    back = {c.text for c in run_changes(new, old)}
    assert "class traffic-cone removed" in back
    no_ids = schema.with_classes([dataclasses.replace(car, gt_ids=()), *schema.classes[1:]])
    ids = run_changes(old, _snapshot(no_ids, PipelineConfig()))
    assert [c.text for c in ids] == ["ground-truth ids of car: [10, 252] → none"]
    sections = changed_sections(config_to_dict(PipelineConfig()), new["pipeline"])
    assert sections == ["grounded_sam", "smoothing"]


def test_run_changes_name_a_class_s_thing_flag_and_moving_id() -> None:
    schema = builtin_schema("semantickitti")
    old = _snapshot(schema, PipelineConfig())
    edits = {"car": {"moving_id": None}, "truck": {"thing": False, "moving_id": None}}
    edited = [dataclasses.replace(c, **edits.get(c.name, {})) for c in schema.classes]
    assert edited[0].name == "car" and schema.classes[0].moving_id == 252
    changes = run_changes(old, _snapshot(schema.with_classes(edited), PipelineConfig()))
    assert [(c.kind, c.subject, c.field, c.text) for c in changes] == [
        ("class", "car", "moving_id", "moving id of car: 252 → none"),
        ("class", "truck", "thing", "truck is stuff (was a thing)"),
        ("class", "truck", "moving_id", "moving id of truck: 258 → none"),
    ]
    # A class stored before classes had the two keys reads as SemanticKITTI's defaults: no change.
    bare = copy.deepcopy(old)
    for entry in bare["schema"]["classes"]:
        del entry["thing"], entry["moving_id"]
    assert run_changes(bare, old) == []


def test_corrections_and_pose_estimation_are_changes() -> None:
    notes = {
        1: CorrectionNote("car, map, 3 voxels", made_after=False),
        2: CorrectionNote("road, map, 9 voxels", made_after=True),
        3: CorrectionNote("erase, scan 000004, 1 point", made_after=False),
        4: CorrectionNote("car, map, 1 voxel", made_after=False, exists=False),
        5: CorrectionNote("pole, map, 2 voxels", made_after=False),
    }
    old = {"00": [1, 3, 4, 5]}
    new = {"00": [5, 2, 1]}  # 3 switched off, 4 gone, 2 new; 1 and 5 in both (their order is the made order)
    texts = [c.text for c in correction_changes(old, new, notes)]
    assert texts == [
        "correction 2 (road, map, 9 voxels) added",
        "correction 3 (erase, scan 000004, 1 point) switched off",
        "correction 4 (car, map, 1 voxel) removed",
    ]
    assert {c.kind for c in correction_changes(old, new, notes)} == {"correction"}
    back = [c.text for c in correction_changes({"00": [1]}, {"00": [1, 3], "01": [5]}, notes)]
    assert back == [
        "correction 3 (erase, scan 000004, 1 point) in sequence 00 switched on",
        "correction 5 (pole, map, 2 voxels) in sequence 01 switched on",
    ]
    assert correction_changes(old, old, notes) == []
    schema = builtin_schema("semantickitti")
    off, on = _snapshot(schema, PipelineConfig()), _snapshot(schema, PipelineConfig())
    on["estimate_poses"] = True
    poses = run_changes(off, on)
    assert [(c.kind, c.subject, c.text) for c in poses] == [
        ("poses", "estimate_poses", "Estimate poses (KISS-ICP): off → on")
    ]
    assert [c.text for c in run_changes(on, off)] == ["Estimate poses (KISS-ICP): on → off"]


def test_run_changes_list_the_sequences_added_removed_and_moved() -> None:
    """Sequences are matched by name: one added or removed, one whose folder or frames changed; each
    change names the sequence as its subject, the sequences' changes coming first."""
    schema, cfg = builtin_schema("semantickitti"), PipelineConfig()
    old = _snapshot(schema, cfg, [0, 5], {"name": "01", "dataset": "/d/one", "frames": None})
    new = _snapshot(schema, config_from_dict({"smoothing": {"k": 4}}), [0, 5])
    new["sequences"] = [
        {"name": "02", "dataset": "/d/two", "frames": None},
        {"name": "00", "dataset": "/e/seq", "frames": [2, 5]},
    ]
    changes = run_changes(old, new)
    assert [(c.kind, c.subject, c.text) for c in changes[:4]] == [
        ("dataset", "02", "sequence 02 added (/d/two)"),
        ("dataset", "00", "sequence 00: dataset /d/seq → /e/seq"),
        ("frames", "00", "sequence 00: frames 0..4 → 2..4"),
        ("dataset", "01", "sequence 01 removed (/d/one)"),
    ]
    assert [c.subject for c in changes[4:]] == ["smoothing.k"]
    # The order of the sequences alone changes nothing; neither does a snapshot without sequences.
    swapped = {**old, "sequences": old["sequences"][::-1]}
    assert run_changes(old, swapped) == []
    bare = {k: v for k, v in old.items() if k != "sequences"}
    assert [c.text for c in run_changes(bare, old)] == [
        "sequence 00 added (/d/seq)",
        "sequence 01 added (/d/one)",
    ]


def test_a_snapshot_stored_before_the_noise_terms_moved_shows_no_spurious_change() -> None:
    # A run of an older version stored the simulated section with every moved term at its off value: the
    # next run's snapshot (today's form, without them) changed nothing.
    schema = builtin_schema("semantickitti")
    stored = json.loads(
        (Path(__file__).parent / "data" / "pipeline_config_with_simulated_terms.json").read_text()
    )
    old = {**_snapshot(schema, PipelineConfig()), "pipeline": stored}
    new = _snapshot(schema, PipelineConfig())
    assert (
        "box_leak_prob" in old["pipeline"]["simulated"]
        and "box_leak_prob" not in new["pipeline"]["simulated"]
    )
    assert run_changes(old, new) == [] and run_changes(new, old) == []
    assert changed_sections(old["pipeline"], new["pipeline"]) == []
    # A term that was on (a run with the former paper preset) did change the labels: it is listed.
    stored["simulated"]["box_leak_prob"] = 0.1
    assert [c.text for c in run_changes(old, new)] == ["simulated.box_leak_prob: 0.1 → null"]
    assert changed_sections(stored, new["pipeline"]) == ["simulated"]


# -------------------------------------------------------------------------------------- recompute plan
@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_street(tmp_path_factory.mktemp("street") / "sequences" / "00", n_frames=3)


@pytest.fixture(scope="module")
def finished(street: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The street's folder in a finished run."""
    out = tmp_path_factory.mktemp("runs") / "base"
    return label(street, builtin_schema("semantickitti"), PipelineConfig(), out).folder


def _cone_schema():
    schema = builtin_schema("semantickitti")
    return schema.with_classes(
        [
            *schema.classes,
            ClassDef(
                name="traffic-cone",
                color=(255, 120, 0),
                prompts=("traffic cone",),
                export_id=300,
                gt_ids=(300,),
            ),
        ]
    )


VARIANTS = {
    "same": (None, {}),
    "k": (None, {"smoothing": {"k": 4}}),
    "ignored threshold": (None, {"grounded_sam": {"box_threshold": 0.3}}),
    "voxel": (None, {"fusion": {"voxel_size": 0.3}}),
    "cluster gap": (None, {"projection": {"cluster_gap": 0.7}}),
    "3dcn on": (None, {"consistency": {"enabled": True}}),
    "class added": (_cone_schema, {}),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_the_preview_agrees_with_the_runner(
    variant: str, street: Path, finished: Path, tmp_path: Path
) -> None:
    """The plan from fingerprints says exactly what the runner would recompute in a folder seeded from the
    finished run (the runner's own decision, ``plan_stages``), for every enabled stage."""
    make_schema, overrides = VARIANTS[variant]
    schema = make_schema() if make_schema else builtin_schema("semantickitti")
    cfg = config_from_dict(overrides)
    shutil.copytree(finished.parent.parent, tmp_path / "seeded")
    seeded = folder(tmp_path / "seeded")
    fresh = tmp_path / "fresh"  # the preview's folder: no outputs, only what fingerprints read
    fps = stage_fingerprints(street, schema, cfg, fresh)
    assert fps == stage_fingerprints(street, schema, cfg, seeded)
    previous = read_state(SequenceLayout(finished))
    plan = {
        p.name: p
        for p in recompute_plan(
            cfg, fps, previous, changed_sections(config_to_dict(PipelineConfig()), config_to_dict(cfg))
        )
    }
    truth = plan_stages(street, schema, cfg, seeded)
    for stage in STAGE_TABLE:
        if stage.is_enabled(cfg):
            assert (plan[stage.name].action == "recompute") == truth[stage.name], (variant, stage.name)
        else:
            assert plan[stage.name].action == "off"
    if variant in ("same", "ignored threshold"):
        assert all(p.action != "recompute" for p in plan.values())
    if variant == "k":
        assert plan["smooth"].reason == "settings changed: smoothing"
        assert plan["labels2d"].action == "reuse" and plan["export"].reason == "after Point labels, Objects"


def test_plan_reasons_without_a_previous_run_and_for_unfinished_stages() -> None:
    cfg = PipelineConfig()
    fps = {s.name: f"fp-{s.name}" for s in STAGE_TABLE}
    empty = recompute_plan(cfg, fps, None)
    assert {p.action for p in empty if p.name not in ("motion", "3dcn")} == {"recompute"}
    assert empty[0].reason == "no earlier run to reuse"
    prev = {s.name: {"fingerprint": fps[s.name], "status": "done"} for s in STAGE_TABLE}
    prev["3dcn"]["status"] = "skipped"
    prev["fuse"]["status"] = "cancelled"
    plan = {p.name: p for p in recompute_plan(cfg, fps, prev)}
    assert plan["project"].action == "reuse"
    assert plan["fuse"].reason == "unfinished in the latest run (cancelled)"
    # As in the runner, a stage whose own fingerprint and outputs are current is reused even when an
    # upstream stage with an unchanged fingerprint is finished again.
    assert plan["smooth"].action == "reuse"
    # The 3D-CN switched off after a run that used it: what read its grids recomputes.
    prev2 = {**{k: dict(v) for k, v in prev.items()}, "fuse": {"fingerprint": fps["fuse"], "status": "done"}}
    prev2["3dcn"]["status"] = "done"
    plan2 = {p.name: p for p in recompute_plan(cfg, {**fps, "label_points": "other"}, prev2)}
    assert plan2["3dcn"].action == "off" and plan2["label_points"].reason == "after 3D-CN (switched off)"


# ------------------------------------------------------------------------------ all-points labeled share
def test_all_points_labeled_share(finished: Path, street: Path) -> None:
    import json

    metrics = json.loads(SequenceLayout(finished).metrics.read_text())
    share = SequenceMetrics.from_dict(metrics).all_points_labeled_share()
    assert share == metrics["labeled_share_all_points"]
    n = metrics["n_points"]
    assert share["voxel"] == pytest.approx(metrics["labeled_points"]["voxel"] / n)
    # What the exported .label files label is that share of the final row.
    labeled = sum(
        int((np.fromfile(p, np.uint32) & 0xFFFF).astype(bool).sum())
        for p in sorted(SequenceLayout(finished).export_dir.glob("*.label"))
    )
    assert labeled / n == pytest.approx(share["voxel"])
    older = {k: v for k, v in metrics.items() if k != "labeled_share_all_points"}
    assert SequenceMetrics.from_dict(older).all_points_labeled_share() == pytest.approx(share)
    empty = {**older, "labeled_points": {"voxel": 3}, "n_points": 0}
    assert SequenceMetrics.from_dict(empty).all_points_labeled_share() == {"voxel": None}
