"""The labeling pipeline as separable, cached, resumable stages on a run directory.

Stages (:data:`STAGE_TABLE`, in order) and what each writes into a sequence's folder of the run
(:class:`~leap_core.run_layout.SequenceLayout`); the labels in brackets are sections of docs/METHOD.md:

============  ================================================================================================
labels2d      ``labels2d/<frame_id>.npz``: the 2D labeler's :class:`SoftMasks` per frame (stage A)
project       ``observations/<frame_id>.npz``: projection + per-mask depth clustering + painting (B.1-B.2)
fuse          ``grid.npz``: Bayesian log-space fusion of every observation, then manual corrections (B.3)
smooth        ``grid_smooth.npz``: distance-weighted kNN smoothing of the fused grid (B.4)
3dcn          ``grid_3dcn{i}.npz`` / ``grid_smooth_3dcn{i}.npz`` per iteration i (stage C, when enabled)
label_points  ``points/<frame_id>.npz``: label + confidence of every point from the final grid (B.5)
tracks        ``tracks.npz``: segments of thing points, tracks over the sequence, class votes, motion (B.6)
evaluate      ``metrics.json``: point / voxel / +3D-CN / objects rows; protocols camera, all and paper (D.5);
              object scores: PQ, MOS IoU, S_assoc (D.6)
export        ``export/<frame_id>.label`` + ``.conf`` per scan (instance ids, moving ids)
============  ================================================================================================

Caching. Every stage has a fingerprint: a hash of the config sections it reads, the fingerprints of its
upstream stages and its other inputs (labeler and dataset identity, frames, corrections, schema parts), as
its :class:`StageInfo` record says. ``stages.json`` records each stage's fingerprint and status; a stage
whose record matches and whose outputs exist is skipped. So editing, e.g., the smoothing ``k`` reruns
``smooth`` and what follows, and a class colour edit reruns nothing.

Resuming. Per-frame stages (labels2d, project, label_points, export) write one file per frame atomically and
only compute frames whose file is missing; the folder is cleared first only when the stage's fingerprint
changed. Everything is seeded per frame and reduced in frame order, so a run that was killed (or
cancelled through the progress callback) and run again yields byte-identical final labels.

A shared 2D cache (``Runtime.cache_dir``) lets runs of one project reuse 2D results: entries are keyed by
the labeler's fingerprint and a digest of the frame's input files, and hard-linked into the run folder.

A run labels one or several sequences with one schema and config (:func:`run_pipeline`, the entry point:
one folder per sequence, a 3D-CN trained on all of them, overall metrics); exports keep the
``sequences/<name>/predictions/`` layout (:mod:`leap_core.export`).

Modules: :mod:`.context` (stage record, run context), :mod:`.stages` (stage functions, the table),
:mod:`.evaluation` (evaluate stage, result tables), :mod:`.runner` (fingerprints, one sequence's stages,
plan / status), :mod:`.run` (the run), :mod:`.migration` (run folders of earlier versions).
"""

from __future__ import annotations

from leap_core.fusion import world_points
from leap_core.pipeline.context import FrameFiles, ProgressCallback, StageInfo, dataset_identity
from leap_core.pipeline.evaluation import (
    PAPER,
    PROTOCOLS,
    ROW_POINT,
    ROW_VOXEL,
    cn_row,
    load_metrics,
    overall_metrics,
    read_metrics_json,
    result_tables,
)
from leap_core.pipeline.metrics_file import RowScores, RunMetrics, SequenceMetrics
from leap_core.pipeline.migration import migrate_run_folder
from leap_core.pipeline.run import (
    JOINT,
    RunProgress,
    RunResult,
    SequenceSpec,
    read_run_metrics,
    run_pipeline,
    run_result_tables,
)
from leap_core.pipeline.runner import (
    PIPELINE_VERSION,
    SequenceResult,
    StageReport,
    plan_stages,
    skip_reason,
    stage_fingerprints,
    stage_status,
)
from leap_core.pipeline.stages import STAGE_TABLE, STAGES

__all__ = [
    "JOINT",
    "PAPER",
    "PIPELINE_VERSION",
    "PROTOCOLS",
    "ROW_POINT",
    "ROW_VOXEL",
    "STAGES",
    "STAGE_TABLE",
    "FrameFiles",
    "ProgressCallback",
    "RowScores",
    "RunMetrics",
    "RunProgress",
    "RunResult",
    "SequenceMetrics",
    "SequenceResult",
    "SequenceSpec",
    "StageInfo",
    "StageReport",
    "cn_row",
    "dataset_identity",
    "load_metrics",
    "migrate_run_folder",
    "overall_metrics",
    "plan_stages",
    "read_metrics_json",
    "read_run_metrics",
    "result_tables",
    "run_pipeline",
    "run_result_tables",
    "skip_reason",
    "stage_fingerprints",
    "stage_status",
    "world_points",
]
