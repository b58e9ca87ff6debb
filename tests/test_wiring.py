"""Stage wiring: each stored stage output equals that stage's pure function applied to the stored inputs.

One real pipeline run (tiny ray-cast street, simulated 2D labels, manual corrections, a tiny 3D-CN round)
and, per stage, the output recomputed from the files the run wrote, with the run's own config. The unit
tests check the maths; these check that the pipeline feeds each function the right inputs (a pipeline that
skipped smoothing or depth clustering, or gave the 3D-CN the unsmoothed grid or no view counts, would still
run and score well on a loose mIoU bound).
"""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from runhelpers import folder, label
from test_pipeline import make_street

from leap_core.config import PipelineConfig, config_from_dict
from leap_core.consistency.selection import view_counts
from leap_core.consistency.stage import (
    checkpoint_path,
    fuse_back,
    iteration_config,
    reliable_targets,
    training_fingerprint,
)
from leap_core.consistency.train import load_checkpoint, predict_log_probs, resolve_precision, torch_threads
from leap_core.datasets.kitti import KittiSequence
from leap_core.fusion import (
    Observations,
    VoxelGrid,
    apply_overrides,
    fuse,
    last_per_key,
    log_table,
    voxel_keys,
    world_points,
)
from leap_core.labelers.base import SoftMasks
from leap_core.pipeline import JOINT, SequenceSpec, run_pipeline
from leap_core.pipeline.context import load_view
from leap_core.projection import Painted, paint, project_points
from leap_core.run_layout import RunLayout, SequenceLayout, load_corrections, save_corrections
from leap_core.schema import Schema, builtin_schema
from leap_core.smoothing import SmoothedGrid, knn_smooth

TINY_3DCN = {
    "enabled": True,
    "iterations": 1,
    "points_per_scan": 1024,
    "num_threads": 1,
    "min_steps": 0,
    "backbone": {"channels": 8, "layers": 1, "knn": 4},
}


class Run:
    """The finished run and what the checks need from it."""

    def __init__(self, street: Path, root: Path, schema: Schema, cfg: PipelineConfig) -> None:
        self.seq = KittiSequence(street)
        self.root = root
        """The run folder."""
        self.lay = SequenceLayout(folder(root))
        """The street's folder in it."""
        self.cn_dir = RunLayout(root).cn_dir
        self.schema = schema
        self.cfg = cfg
        self.c = schema.num_classes
        self.frames = range(len(self.seq))
        self.calls: list[tuple[str, str, int, int]] = []
        """The run's progress calls (sequence, stage, done, total)."""

    def copy(self, out: Path) -> SequenceLayout:
        """A copy of the run folder at ``out``: its street's folder."""
        shutil.copytree(self.root, out)
        return SequenceLayout(folder(out))

    def observations(self) -> list[tuple[Painted, np.ndarray]]:
        """Per frame: the stored observation and the world voxel key of each painted point."""
        out = []
        for i in self.frames:
            frame = self.seq.frame(i)
            painted = Painted.load(self.lay.observation(frame.frame_id))
            keys = voxel_keys(
                world_points(frame.points[painted.point_idx], frame.pose), self.cfg.fusion.voxel_size
            )
            out.append((painted, keys))
        return out

    def corrections(self) -> tuple[np.ndarray, np.ndarray]:
        return load_corrections(self.lay.corrections, self.c)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    street = make_street(tmp_path_factory.mktemp("street") / "sequences" / "00", n_frames=4)
    schema = builtin_schema("semantickitti")
    root = tmp_path_factory.mktemp("runs") / "wired"
    folder(root).mkdir(parents=True, exist_ok=True)
    # Corrections made before the run: scattered voxels of frame 0 (each amid uncorrected neighbours, so
    # smoothing would move them), one voxel corrected twice (the later entry wins).
    seq = KittiSequence(street)
    f0 = seq.frame(0)
    keys = np.unique(voxel_keys(world_points(f0.points, f0.pose), 0.2))[::97]
    trunk, pole = schema.index("trunk"), schema.index("pole")
    save_corrections(
        folder(root) / "corrections.npz",
        np.concatenate([keys, keys[:1]]),
        np.concatenate([np.full(len(keys), trunk), [pole]]),
    )
    # Non-default settings in every section a stage reads: a stage that used a default config would differ.
    cfg = config_from_dict(
        {
            "consistency": TINY_3DCN,
            "smoothing": {"k": 6},
            "fusion": {"prob_floor": 0.002, "logp_clip": 12.0},
            "projection": {"cluster_gap": 0.8, "min_depth": 4.0},
        }
    )
    assert cfg.smoothing != PipelineConfig().smoothing
    calls: list[tuple[str, str, int, int]] = []
    result = run_pipeline([SequenceSpec.of(street)], schema, cfg, root, progress=lambda *a: calls.append(a))
    assert "3dcn" in result.only().ran
    out = Run(street, root, schema, cfg)
    out.calls = calls
    return out


def _expected_smoothed(run: Run, grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """knn_smooth of ``grid`` with the run's config, and the rows / classes of the corrected voxels."""
    smooth = knn_smooth(grid.centres(), grid.probs(), run.cfg.smoothing)
    keys, cls = last_per_key(*run.corrections())
    rows = grid.lookup(keys)
    assert (rows >= 0).all()  # corrected voxels are in every grid (apply_overrides adds them)
    return smooth, rows, cls


def _check_smoothed(run: Run, grid: VoxelGrid, stored: SmoothedGrid) -> None:
    smooth, rows, cls = _expected_smoothed(run, grid)
    np.testing.assert_array_equal(stored.keys, grid.keys)
    free = np.ones(grid.num_voxels, bool)
    free[rows] = False
    # Uncorrected voxels: exactly the smoothed distribution, stored as float16.
    np.testing.assert_array_equal(stored.probs[free], smooth[free].astype(np.float16))
    # Corrected voxels: exactly one-hot at the latest correction's class, whatever smoothing said.
    onehot = np.zeros((len(rows), run.c), np.float16)
    onehot[np.arange(len(rows)), cls] = 1.0
    np.testing.assert_array_equal(stored.probs[rows], onehot)
    # Guard: on this data smoothing and the corrections both change something, so the checks above bite.
    posterior = grid.probs().argmax(axis=1)
    assert (smooth[free].argmax(axis=1) != posterior[free]).sum() > 10
    assert (smooth[rows].argmax(axis=1) != cls).any()


# -------------------------------------------------------------------------------------------- tests
def test_observations_are_projection_depth_clustering_and_painting(run: Run) -> None:
    """observations/<frame>.npz = paint(labels2d/<frame>.npz, project_points(scan)) with the run's
    projection config (its per-mask depth clustering included)."""
    pcfg = run.cfg.projection
    assert pcfg.depth_clustering
    unclustered_differs = 0
    for i in run.frames:
        frame = run.seq.frame(i)
        soft = SoftMasks.load(run.lay.labels2d(frame.frame_id))
        proj = project_points(
            frame.points, run.seq.calib.lidar_to_image, soft.height, soft.width, pcfg.min_depth
        )
        expected = paint(soft, proj, pcfg)
        stored = Painted.load(run.lay.observation(frame.frame_id))
        np.testing.assert_array_equal(stored.point_idx, expected.point_idx)
        np.testing.assert_array_equal(stored.rows, expected.rows)
        np.testing.assert_array_equal(stored.table, expected.table)
        plain = paint(soft, proj, dataclasses.replace(pcfg, depth_clustering=False))
        unclustered_differs += int(
            len(plain.point_idx) != len(expected.point_idx) or not np.array_equal(plain.rows, expected.rows)
        )
    assert unclustered_differs > 0  # guard: clustering changes the painting of this street


def test_fused_grid_is_fusion_of_the_observations_then_corrections(run: Run) -> None:
    """grid.npz = apply_overrides(fuse(every stored observation), corrections) with the run's config; the
    last correction of a voxel replaces earlier ones (an erase, -1, then adds nothing)."""
    fcfg = run.cfg.fusion
    batches = [
        Observations(keys, p.rows, log_table(p.table, fcfg.prob_floor)) for p, keys in run.observations()
    ]
    keys, cls = last_per_key(*run.corrections())
    keys, cls = keys[cls >= 0], cls[cls >= 0]
    expected = apply_overrides(fuse(batches, run.c, fcfg), keys, cls, run.cfg.correction_strength, fcfg)
    stored = VoxelGrid.load(run.lay.grid)
    np.testing.assert_array_equal(stored.keys, expected.keys)
    np.testing.assert_array_equal(stored.logp, expected.logp)


def test_smoothed_grid_is_knn_smooth_of_the_fused_grid_with_corrections_reimposed(run: Run) -> None:
    """grid_smooth.npz = knn_smooth(grid.npz) with the run's smoothing config; corrected voxels one-hot."""
    _check_smoothed(run, VoxelGrid.load(run.lay.grid), SmoothedGrid.load(run.lay.grid_smooth))


def test_3dcn_trains_on_the_smoothed_grid_and_the_view_counts(run: Run) -> None:
    """The checkpoint was trained on reliable_targets(grid_smooth.npz, view counts of the observations): its
    stored fingerprint hashes exactly those labels."""
    cn = iteration_config(run.cfg.consistency, 1)
    assert cn.rank_by_views
    vs, clip = run.cfg.fusion.voxel_size, run.cfg.fusion.logp_clip
    views = view_counts(keys for _, keys in run.observations())
    smoothed = SmoothedGrid.load(run.lay.grid_smooth).to_voxel_grid(clip)

    def fingerprint(grid: VoxelGrid, views_used: tuple[np.ndarray, np.ndarray] | None) -> str:
        targets = reliable_targets(run.seq, grid, run.c, cn, vs, run.frames, views_used)
        return training_fingerprint(cn, run.c, run.frames, targets)

    meta = load_checkpoint(checkpoint_path(run.cn_dir, 1)).meta
    assert meta["fingerprint"] == fingerprint(smoothed, views)
    # Guards: the unsmoothed grid, or no view counts, select other labels on this data.
    assert fingerprint(VoxelGrid.load(run.lay.grid), views) != meta["fingerprint"]
    assert fingerprint(smoothed, None) != meta["fingerprint"]


def test_3dcn_grid_is_the_fused_grid_plus_network_evidence(run: Run) -> None:
    """grid_3dcn1.npz = fuse_back(grid.npz, the checkpoint's predictions of every scan); grid_smooth_3dcn1.npz
    = its knn_smooth with the corrections re-imposed."""
    cn, fcfg = run.cfg.consistency, run.cfg.fusion
    model = load_checkpoint(checkpoint_path(run.cn_dir, 1)).model
    precision = resolve_precision(cn, torch.device("cpu"))  # the run's arithmetic, as its stage resolved it
    preds, in_view = [], []
    with torch_threads(cn.num_threads):  # the stage's thread count: matmul sums in the same order
        for i in run.frames:
            frame = run.seq.frame(i)
            keys = voxel_keys(world_points(frame.points, frame.pose), fcfg.voxel_size)
            preds.append((keys, predict_log_probs(model, frame.points, precision=precision)))
            in_view.append(keys[load_view(run.lay.observation(f"{i:06d}"))[1]])
    fused = VoxelGrid.load(run.lay.grid)
    # The margin applies to the new voxels inside the camera view; some lie outside it here.
    in_view_keys = np.unique(np.concatenate(in_view))
    assert not np.isin(np.concatenate([k for k, _ in preds]), in_view_keys).all()
    expected = fuse_back(
        fused,
        preds,
        run.c,
        cn.temperature,
        fcfg,
        cn.network_evidence,
        new_voxel_margin=cn.new_voxel_margin,
        in_view=in_view_keys,
    )
    stored = VoxelGrid.load(run.lay.grid_3dcn(1))
    np.testing.assert_array_equal(stored.keys, expected.keys)
    np.testing.assert_array_equal(stored.logp, expected.logp)
    _check_smoothed(run, stored, SmoothedGrid.load(run.lay.grid_smooth_3dcn(1)))


def test_point_labels_come_from_the_final_grid(run: Run) -> None:
    """points/<frame>.npz: label/conf of each point's voxel in the final smoothed grid; point_label from the
    frame's observation alone."""
    final = SmoothedGrid.load(run.lay.final_grid(run.cfg.consistency))
    assert run.lay.final_grid(run.cfg.consistency) == run.lay.grid_smooth_3dcn(1)
    for (painted, _), i in zip(run.observations(), run.frames, strict=True):
        frame = run.seq.frame(i)
        keys = voxel_keys(world_points(frame.points, frame.pose), run.cfg.fusion.voxel_size)
        lab, conf = final.labels_at(keys)
        with np.load(run.lay.points(frame.frame_id)) as z:
            np.testing.assert_array_equal(z["label"], lab)
            np.testing.assert_array_equal(z["conf"], conf.astype(np.float16))
            np.testing.assert_array_equal(z["point_label"], painted.point_labels(len(frame.points)))


def test_a_changed_3dcn_setting_removes_every_round_grid(run: Run, tmp_path: Path) -> None:
    """The 3D-CN's outputs are its smoothed round grids, but what a changed fingerprint clears is every
    round's grids (fused ones too): none of them belongs to the new settings."""
    lay = run.copy(tmp_path / "copy")
    assert {p.name for p in lay.cn_grids()} == {"grid_3dcn1.npz", "grid_smooth_3dcn1.npz"}
    off = dataclasses.replace(run.cfg, consistency=dataclasses.replace(run.cfg.consistency, enabled=False))
    result = label(run.seq.root, run.schema, off, tmp_path / "copy", until="3dcn")
    assert result.ran == []  # the 3D-CN is now skipped, the stages before it are current
    assert lay.cn_grids() == []


def test_the_3dcn_is_current_only_while_its_last_smoothed_round_grid_exists(run: Run, tmp_path: Path) -> None:
    """A finished 3D-CN stage is cached as long as its outputs (the smoothed grid of each round) exist; a
    deleted one makes it run again, and only it (the later stages' inputs are its fingerprint)."""
    from leap_core.pipeline import plan_stages

    lay = run.copy(tmp_path / "copy")
    assert not any(plan_stages(run.seq.root, run.schema, run.cfg, lay.folder).values())
    lay.grid_smooth_3dcn(1).unlink()
    plan = plan_stages(run.seq.root, run.schema, run.cfg, lay.folder)
    assert [s for s, todo in plan.items() if todo] == ["3dcn"]


def test_a_sequence_links_its_staged_round_grids(run: Run, tmp_path: Path) -> None:
    """The 3D-CN stage of a sequence takes its round grids from the run's staging folder of the round
    (hard links), once its record (``3dcn_joint.json``) matches the run's round record; otherwise it
    refuses, naming the run."""
    import json
    import os

    from leap_core.errors import DatasetError, LeapError
    from leap_core.pipeline import stage_status
    from leap_core.pipeline.runner import run_sequence

    root = RunLayout(tmp_path / "multi")
    lay = root.sequence("00")
    shutil.copytree(run.lay.folder, lay.folder)
    staged = root.joint_rounds("00")
    staged.folder.mkdir(parents=True)
    # Staged grids that differ from the run's own rounds, so a link is told apart from the files left there.
    shutil.copyfile(run.lay.grid, staged.grid_3dcn(1))
    shutil.copyfile(run.lay.grid_smooth, staged.grid_smooth_3dcn(1))
    root.joint_state.write_text(json.dumps({"fingerprint": "f1", "sequences": ["00"]}))

    calls: list[tuple[str, int, int]] = []

    def link(note: object) -> None:
        lay.joint_3dcn.write_text(note if isinstance(note, str) else json.dumps(note))
        run_sequence(
            run.seq.root, run.schema, run.cfg, lay.folder, until="3dcn", progress=lambda *a: calls.append(a)
        )

    link({"fingerprint": "f1", "name": "00", "sequences": ["00"]})
    assert [c for c in calls if c[0] == "3dcn"] == [("3dcn", 1, 1)]
    assert os.path.samefile(staged.grid_3dcn(1), lay.grid_3dcn(1))
    assert os.path.samefile(staged.grid_smooth_3dcn(1), lay.grid_smooth_3dcn(1))
    record = stage_status(lay.folder)["3dcn"]
    assert (record["joint"], record["iterations"]) == ("f1", 1)
    assert record["voxels"] == VoxelGrid.load(run.lay.grid).num_voxels
    # A record of another round, or of another sequence, or with the staged grids gone: refused.
    for note in ({"fingerprint": "f0", "name": "00"}, {"fingerprint": "f1", "name": "01"}):
        with pytest.raises(LeapError, match=r"multi/sequences/00: sequence .* has not run"):
            link(note)
    staged.grid_smooth_3dcn(1).unlink()
    with pytest.raises(LeapError, match="has not run for these settings"):
        link({"fingerprint": "f1", "name": "00", "sequences": ["00", "01"]})
    # Unreadable records name their file.
    for bad in ("{not json", json.dumps({"name": "00"}), json.dumps(["f1"])):
        with pytest.raises(DatasetError, match=r"3dcn_joint\.json: unreadable 3D-CN record"):
            link(bad)
    root.joint_state.write_text("{not json")
    with pytest.raises(DatasetError, match=r"3dcn/joint\.json: unreadable 3D-CN record"):
        link({"fingerprint": "f1", "name": "00"})
    root.joint_state.write_text(json.dumps(["f1"]))
    with pytest.raises(DatasetError, match=r"3dcn/joint\.json: unreadable 3D-CN record"):
        link({"fingerprint": "f1", "name": "00", "x": 1})


def test_the_distributed_fusion_ends_with_the_grid_the_fuse_stage_wrote(run: Run, tmp_path: Path) -> None:
    """finish_fuse, the Ray engine's last fusion step (its partial grids already summed: here fuse() of
    every stored observation), applies the corrections and writes the fuse stage's grid.npz byte for byte."""
    from leap_core.pipeline.runner import _context
    from leap_core.pipeline.stages import finish_fuse

    lay = run.copy(tmp_path / "copy")
    lay.grid.unlink()
    calls: list[tuple[str, int, int]] = []
    ctx = _context(
        run.seq.root,
        run.schema,
        run.cfg,
        lay.folder,
        progress=lambda *a: calls.append(a),
        frames=None,
        runtime=None,
    )
    fcfg = run.cfg.fusion
    batches = [
        Observations(keys, p.rows, log_table(p.table, fcfg.prob_floor)) for p, keys in run.observations()
    ]
    record = finish_fuse(ctx, fuse(batches, run.c, fcfg))
    assert lay.grid.read_bytes() == run.lay.grid.read_bytes()
    n_corrected = len(last_per_key(*run.corrections())[0])
    assert record == {"voxels": VoxelGrid.load(run.lay.grid).num_voxels, "corrections": n_corrected}
    assert calls == [("fuse", len(run.frames), len(run.frames))]


def test_3dcn_record_and_progress(run: Run) -> None:
    """The 3D-CN's record (rounds, voxels of the last round's grid; fuse's: the corrected voxels) and the
    progress of its rounds in thousandths of a round, rising to 1000 per round, then the sequence's link of
    them."""
    from leap_core.pipeline import stage_status

    records = stage_status(run.lay.folder)
    assert records["3dcn"]["iterations"] == 1
    assert records["3dcn"]["voxels"] == VoxelGrid.load(run.lay.grid_3dcn(1)).num_voxels
    assert records["fuse"]["corrections"] == len(last_per_key(*run.corrections())[0])
    ticks = [(done, total) for name, stage, done, total in run.calls if (name, stage) == (JOINT, "3dcn")]
    assert [c for c in run.calls if c[:2] == ("00", "3dcn")] == [("00", "3dcn", 1, 1)]
    assert {total for _, total in ticks} == {1000} and ticks[-1] == (1000, 1000)
    assert all(type(d) is int for d, _ in ticks)  # whole thousandths, as progress(stage, done, total) counts
    done = [d for d, _ in ticks]
    assert done == sorted(done) and len(set(done)) > 3 and 0 <= done[0] < 1000


def test_3dcn_of_a_frame_subset_trains_on_those_frames_only(run: Run, tmp_path: Path) -> None:
    """A run over some of the scans trains its 3D-CN on the reliable labels of those scans only."""
    frames = range(0, 3)
    out = tmp_path / "subset"
    lay = SequenceLayout(label(run.seq.root, run.schema, run.cfg, out, frames=frames, until="3dcn").folder)
    cn = iteration_config(run.cfg.consistency, 1)
    vs, clip = run.cfg.fusion.voxel_size, run.cfg.fusion.logp_clip
    observed = []
    for i in frames:
        frame = run.seq.frame(i)
        painted = Painted.load(lay.observation(frame.frame_id))
        observed.append(voxel_keys(world_points(frame.points[painted.point_idx], frame.pose), vs))
    views = view_counts(iter(observed))
    smoothed = SmoothedGrid.load(lay.grid_smooth).to_voxel_grid(clip)
    targets = reliable_targets(run.seq, smoothed, run.c, cn, vs, frames, views)
    meta = load_checkpoint(checkpoint_path(RunLayout(out).cn_dir, 1)).meta
    assert meta["fingerprint"] == training_fingerprint(cn, run.c, frames, targets)


def test_a_round_missing_its_smoothed_grid_is_computed_again(run: Run, tmp_path: Path) -> None:
    """A 3D-CN round is kept on resume only when both its grids exist: one whose smoothed grid is gone is
    computed again (its checkpoint reused), to the same bytes."""
    lay = run.copy(tmp_path / "copy")
    staged = RunLayout(tmp_path / "copy").joint_rounds("00")
    staged.grid_smooth_3dcn(1).unlink()
    lay.grid_smooth_3dcn(1).unlink()
    trained = (RunLayout(tmp_path / "copy").cn_dir / "3dcn_iter1.pt").stat().st_mtime_ns
    assert label(run.seq.root, run.schema, run.cfg, tmp_path / "copy", until="3dcn").ran == ["3dcn"]
    assert (RunLayout(tmp_path / "copy").cn_dir / "3dcn_iter1.pt").stat().st_mtime_ns == trained
    assert lay.grid_smooth_3dcn(1).read_bytes() == run.lay.grid_smooth_3dcn(1).read_bytes()
    assert lay.grid_3dcn(1).read_bytes() == run.lay.grid_3dcn(1).read_bytes()
    assert lay.grid_smooth_3dcn(1).samefile(staged.grid_smooth_3dcn(1))


def _evaluate(
    run: Run,
    lay: SequenceLayout,
    cfg: PipelineConfig,
    seq: KittiSequence,
    progress: Callable[..., None] | None = None,
) -> dict[str, object]:
    """The evaluate stage on run folder ``lay`` (the stage only reads files; no stage table needed)."""
    from leap_core.pipeline.context import Ctx
    from leap_core.pipeline.evaluation import stage_evaluate

    return stage_evaluate(
        Ctx(
            seq=seq,
            schema=run.schema,
            cfg=cfg,
            layout=lay,
            frames=run.frames,
            runtime=None,
            progress=progress,
            table={},
        )
    )


def _rewrite_npz(path: Path, change: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]]) -> None:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(path, **change(arrays))


def test_evaluate_scores_each_round_from_its_own_grid(run: Run, tmp_path: Path) -> None:
    """metrics.json of a two-round run: row ``voxel`` is each point's voxel in the smoothed camera grid, row
    ``+3D-CN x1`` its voxel in round 1's smoothed grid, the final row ``+3D-CN x2`` and ``point`` the
    points/ files; ``common`` the in-view points every row labels. The run's own round-1 grid gives the
    final labels, so round 1's grid is replaced by a different one (every other voxel dropped, the
    classes of the rest rolled by one): a stage that read a row from the wrong source scores differently.
    Fast stand-in for the slow two-round runs (the stage only reads files)."""
    import json

    from leap_core.metrics import confusion_matrix

    lay = run.copy(tmp_path / "two_rounds")
    own = SmoothedGrid.load(lay.grid_smooth_3dcn(1))
    round1 = SmoothedGrid(own.keys[::2], np.roll(own.probs[::2], 1, axis=1), own.voxel_size)
    round1.save(lay.grid_smooth_3dcn(1))
    lay.metrics.unlink()
    cfg = dataclasses.replace(
        run.cfg,
        consistency=dataclasses.replace(run.cfg.consistency, iterations=2),
        # The rows of the grids only: the objects row (the final row with the tracks) is test_objects.py's.
        tracking=dataclasses.replace(run.cfg.tracking, enabled=False),
    )
    calls: list[tuple[str, int, int]] = []
    assert _evaluate(run, lay, cfg, run.seq, progress=lambda *a: calls.append(a)) == {}
    n = len(run.frames)
    assert calls == [("evaluate", k, n) for k in range(n + 1)]

    rows = ("point", "voxel", "+3D-CN x1", "+3D-CN x2")
    voxel = SmoothedGrid.load(lay.grid_smooth)
    want = {p: {r: np.zeros((run.c, run.c + 1), np.int64) for r in rows} for p in ("all", "camera", "common")}
    labeled = dict.fromkeys(rows, 0)
    n_points = n_view = 0
    for i in run.frames:
        frame = run.seq.frame(i)
        _, in_view = load_view(lay.observation(frame.frame_id))
        keys = voxel_keys(world_points(frame.points, frame.pose), cfg.fusion.voxel_size)
        with np.load(lay.points(frame.frame_id)) as z:
            preds = {
                "point": z["point_label"],
                "voxel": voxel.labels_at(keys)[0],
                "+3D-CN x1": round1.labels_at(keys)[0],
                "+3D-CN x2": z["label"],
            }
        gt = run.schema.map_gt(frame.labels)
        common = in_view & np.logical_and.reduce([p >= 0 for p in preds.values()])
        for r, pred in preds.items():
            want["all"][r] += confusion_matrix(gt, pred, run.c)
            want["camera"][r] += confusion_matrix(gt[in_view], pred[in_view], run.c)
            want["common"][r] += confusion_matrix(gt[common], pred[common], run.c)
            labeled[r] += int((pred >= 0).sum())
        n_points += len(gt)
        n_view += int(in_view.sum())
    # The replaced round-1 grid scores unlike the final row, and the common points are fewer than the view.
    assert not np.array_equal(want["camera"]["+3D-CN x1"], want["camera"]["+3D-CN x2"])
    assert labeled["+3D-CN x1"] < labeled["+3D-CN x2"]
    assert want["common"]["+3D-CN x2"].sum() < want["camera"]["+3D-CN x2"].sum()

    got = json.loads(lay.metrics.read_text())
    assert got["rows"] == list(rows)
    assert (got["n_points"], got["n_points_in_view"]) == (n_points, n_view)
    assert got["labeled_points"] == labeled
    assert got["labeled_share_all_points"] == {r: labeled[r] / n_points for r in rows}
    assert got["coverage_ratio"] == {r: labeled[r] / labeled["point"] for r in rows}
    assert got["frames"] == [run.seq.frame_numbers[0], run.seq.frame_numbers[-1] + 1]
    assert (got["class_names"], got["labeler"]) == (run.schema.names, cfg.labeler)
    assert got["categories"] == run.schema.categories()
    assert list(got["protocols"]) == ["all", "camera", "common", "paper"]
    for p in ("all", "camera", "common"):
        for r in rows:
            conf = got[p][r]["confusion"]
            np.testing.assert_array_equal(np.asarray(conf), want[p][r], err_msg=f"{p} {r}")
            assert all(type(v) is int for line in conf for v in line), "counts are written as integers"


def test_evaluate_skips_without_ground_truth_and_refuses_point_files_of_another_size(
    run: Run, tmp_path: Path
) -> None:
    """A frame without its .label file: the stage is skipped and writes nothing. A points/ file without its
    labels, or whose labels are not one per point of the scan: an error naming the file or the scan. No
    point labeled by projection: the coverage ratios are None."""
    import json

    from leap_core.errors import DatasetError

    street = tmp_path / "street"
    shutil.copytree(run.seq.root, street)
    lay = run.copy(tmp_path / "run")
    lay.metrics.unlink()
    seq = KittiSequence(street)

    def evaluate() -> dict[str, object]:
        return _evaluate(run, lay, run.cfg, seq)

    # No point labeled by projection alone (a labeler that found nothing): no coverage ratio, no error.
    for i in run.frames:
        _rewrite_npz(
            lay.points(seq.frame_ids[i]), lambda a: {**a, "point_label": np.full_like(a["point_label"], -1)}
        )
    assert evaluate() == {}
    got = json.loads(lay.metrics.read_text())
    assert got["labeled_points"]["point"] == 0 and set(got["coverage_ratio"].values()) == {None}
    lay.metrics.unlink()

    fid = seq.frame_ids[1]
    points = lay.points(fid)
    with np.load(points) as z:
        arrays = {k: z[k] for k in z.files}
    _rewrite_npz(points, lambda a: {k: v for k, v in a.items() if k != "label"})
    with pytest.raises(DatasetError, match=f"{points.name}.*unreadable point labels"):
        evaluate()
    np.savez(points, **{k: v[:-1] for k, v in arrays.items()})
    with pytest.raises(DatasetError, match=str(seq.scan_path(1).name)):
        evaluate()
    label = seq.label_path(2)
    label.unlink()
    assert evaluate() == {"status": "skipped", "note": "no ground truth"}
    assert not lay.metrics.exists()
    label.mkdir()  # a directory where the file should be: the note names it
    assert evaluate() == {"status": "skipped", "note": f"no ground truth: {label} is a directory, not a file"}


def test_smoothing_reimposes_class_0_and_leaves_erased_voxels_smoothed(run: Run, tmp_path: Path) -> None:
    """A correction to class 0 is imposed like any other, an erase (-1) imposes nothing (its voxel keeps its
    smoothed row), and without corrections the stored grid is knn_smooth exactly, its first row included;
    also when the rows are smoothed in several blocks."""
    from leap_core.pipeline.runner import _context
    from leap_core.pipeline.stages import _fuse_overrides, _smooth_and_save

    grid = VoxelGrid.load(run.lay.grid)
    smooth = knn_smooth(grid.centres(), grid.probs(), run.cfg.smoothing).astype(np.float16)
    run_dir = tmp_path / "r"
    run_dir.mkdir()
    ctx = _context(run.seq.root, run.schema, run.cfg, run_dir, progress=None, frames=None, runtime=None)
    _smooth_and_save(grid, ctx, tmp_path / "plain.npz")
    np.testing.assert_array_equal(SmoothedGrid.load(tmp_path / "plain.npz").probs, smooth)
    assert _fuse_overrides(ctx) == (None, 0)

    rows, cls = np.array([3, 10, 20]), np.array([0, -1, 5])
    assert smooth[3].argmax() != 0 and smooth[20].argmax() != 5 and smooth[10].argmax() != run.c - 1
    save_corrections(run_dir / "corrections.npz", grid.keys[rows], cls)
    _smooth_and_save(grid, ctx, tmp_path / "corrected.npz")
    expected = smooth.copy()
    for r, c in ((3, 0), (20, 5)):
        expected[r] = 0.0
        expected[r, c] = 1.0
    np.testing.assert_array_equal(SmoothedGrid.load(tmp_path / "corrected.npz").probs, expected)
    # In blocks of 7 rows the corrected rows lie in the first, second and third block: the same grid.
    _smooth_and_save(grid, ctx, tmp_path / "blocks.npz", chunk=7)
    np.testing.assert_array_equal(SmoothedGrid.load(tmp_path / "blocks.npz").probs, expected)
    overrides, n = _fuse_overrides(ctx)
    assert overrides is not None and n == 3
    np.testing.assert_array_equal(overrides[0], grid.keys[[3, 20]])
    np.testing.assert_array_equal(overrides[1], [0, 5])
