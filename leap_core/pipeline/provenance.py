"""Where a run's labels came from, for its exports: the ``provenance`` of an export's ``summary.yaml``
(``leap run --zip`` and the app's zip) and the lines the CLI and the app's export dialog show.

It answers what a reader of exported labels cannot see in them:

- **labeler**: which 2D labeler made them and what it rests on: real model weights, ``random`` ones (the
  tiny test models of ``leap make-tiny-models``: meaningless labels) or ``none`` (the simulated labelers
  read 2D ground truth), as the ``labels2d`` stage recorded it; its model ids, or its seed;
- **poses**: per sequence, from a file or estimated, and how (the note beside estimated poses: method and
  version; estimated by ``leap poses`` into the dataset, or by the run into its own folder);
- **corrections**: per sequence, the manual corrections the exported labels carry (map voxels, scan points)
  and a digest of them (SHA-256 of their arrays, 16 hex digits; equal digests = equal corrections);
- **silent classes**: classes the 2D labeler (almost) never gave a pixel (:mod:`.class_presence`);
- **code**: the package version and, when the code runs from a git checkout, its commit.
"""

from __future__ import annotations

import functools
import hashlib
import json
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import leap_core
from leap_core.config import PipelineConfig, config_to_dict
from leap_core.datasets.kitti import POSES_NOTE
from leap_core.errors import LeapError
from leap_core.labelers import LABELERS
from leap_core.pipeline.apply import RunCorrections
from leap_core.pipeline.context import read_state
from leap_core.pipeline.evaluation import read_metrics_json
from leap_core.pipeline.runner import recorded_silent_classes
from leap_core.run_layout import RunLayout, SequenceLayout
from leap_core.schema import Schema


def _git(source: Path, *args: str) -> str | None:
    """``git -C source ARGS``'s output, None when git fails or is missing."""
    try:
        done = subprocess.run(
            ["git", "-C", str(source), *args], capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.cache
def code_version() -> dict[str, str | None]:
    """``{"package": leap_core.__version__, "commit": <git commit> | None}``; the commit is the checkout's
    HEAD when ``leap_core`` runs from the top of a git work tree (``+modified`` when tracked files have
    uncommitted changes), None for an installed package (whose folder may lie inside some other
    repository: only a work tree whose top is the package's parent folder counts)."""
    source = Path(leap_core.__file__).resolve().parent.parent
    commit = None
    top = _git(source, "rev-parse", "--show-toplevel")
    if top and Path(top).resolve() == source:
        commit = _git(source, "rev-parse", "HEAD") or None
        if commit and _git(source, "status", "--porcelain", "--untracked-files=no"):
            commit += "+modified"
    return {"package": leap_core.__version__, "commit": commit}


def _labeler(config: PipelineConfig, layouts: Sequence[SequenceLayout]) -> dict[str, Any]:
    spec = LABELERS.get(config.labeler)
    recorded = set()
    for lay in layouts:
        try:
            rec = read_state(lay).get("labels2d", {})
        except LeapError:
            rec = {}
        recorded.add(str(rec.get("weights") or "not recorded"))
    weights = recorded.pop() if len(recorded) == 1 else "mixed: " + ", ".join(sorted(recorded))
    out: dict[str, Any] = {
        "name": config.labeler,
        "description": None if spec is None else spec.label,
        "weights": weights,
    }
    section = config_to_dict(config).get(spec.section if spec is not None else "", {})
    if isinstance(section, Mapping):
        if "detector_id" in section:
            out["models"] = {"detector": section["detector_id"], "segmenter": section.get("segmenter_id")}
        if "seed" in section:
            out["seed"] = section["seed"]
    return out


def _poses(name: str, dataset: Path | None, layout: SequenceLayout) -> dict[str, Any]:
    """Where sequence ``name``'s poses came from, by the rule the run read them with
    (:meth:`SequenceLayout.open_sequence`: the dataset's ``poses.txt``, else the run's estimate)."""
    if dataset is None:
        return {"sequence": name, "source": "unknown"}
    own = Path(dataset) / "poses.txt"
    path = own if own.is_file() or not layout.poses.is_file() else layout.poses
    if not path.is_file():
        return {"sequence": name, "source": "none", "file": None}
    out: dict[str, Any] = {"sequence": name, "source": "file", "file": str(path)}
    note_path = path.parent / POSES_NOTE
    if note_path.is_file():
        try:
            note = json.loads(note_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            note = {}
        note = note if isinstance(note, dict) else {}
        out["source"] = "estimated"
        out["method"] = " ".join(str(note[k]) for k in ("method", "version") if note.get(k)) or "not recorded"
        out["estimated_by"] = "the run (into its own folder)" if path == layout.poses else "leap poses"
    return out


def _digest(corr: RunCorrections) -> str:
    h = hashlib.sha256()
    for arr in (corr.map_keys, corr.map_class, corr.scan.ptr, corr.scan.points, corr.scan.class_idx):
        h.update(arr.tobytes())
    h.update("\n".join(corr.scan.frame_ids).encode())
    return h.hexdigest()[:16]


def _corrections(name: str, layout: SequenceLayout, num_classes: int) -> dict[str, Any]:
    """The corrections sequence ``name``'s exported labels carry (after any immediate apply)."""
    corr = RunCorrections.applied(layout, num_classes)
    return {
        "sequence": name,
        "map_voxels": int(corr.map_keys.size),
        "scan_points": int(corr.scan.points.size),
        "scan_frames": len(corr.scan.frame_ids),
        "digest": _digest(corr) if corr.map_keys.size or corr.scan.points.size else None,
    }


def run_provenance(
    root: str | Path,
    schema: Schema,
    config: PipelineConfig,
    sequences: Sequence[tuple[str, Path | None]],
) -> dict[str, Any]:
    """The provenance of a run's labels (module docstring), as YAML-ready data.

    Args:
        root: the run folder.
        schema, config: the classes and settings the run labeled with.
        sequences: (name, dataset folder or None when unknown) per sequence, in run order.
    """
    layout = RunLayout(Path(root))
    lays = [layout.sequence(name) for name, _ in sequences]
    silent = []
    for (name, _), lay in zip(sequences, lays, strict=True):
        try:
            metrics = read_metrics_json(lay.folder)
        except LeapError:
            metrics = None
        silent += [{"sequence": name, **c.to_dict()} for c in recorded_silent_classes(lay, schema, metrics)]
    return {
        "labeler": _labeler(config, lays),
        "poses": [_poses(name, ds, lay) for (name, ds), lay in zip(sequences, lays, strict=True)],
        "corrections": [
            _corrections(name, lay, schema.num_classes)
            for (name, _), lay in zip(sequences, lays, strict=True)
        ],
        "silent_classes": silent,
        "code": code_version(),
    }


WEIGHTS_TEXT = {
    "real": "real model weights",
    "random": "RANDOM-weight test models (tiny models: the labels are meaningless)",
    "none": "no model (from the dataset's 2D ground truth)",
    "not recorded": "weights not recorded (a run from before they were)",
}


def provenance_lines(prov: Mapping[str, Any]) -> list[str]:
    """:func:`run_provenance` in a few lines, for the CLI and the app's export dialog."""
    lab = prov["labeler"]
    how = WEIGHTS_TEXT.get(lab["weights"], lab["weights"])
    seed = f", seed {lab['seed']}" if "seed" in lab else ""
    lines = [f"labels: {lab['name']} labeler, {how}{seed}"]
    several = len(prov["poses"]) > 1
    for p in prov["poses"]:
        head = f"poses of {p['sequence']}" if several else "poses"
        if p["source"] == "estimated":
            lines.append(f"{head}: estimated ({p['method']}, by {p['estimated_by']}), {p['file']}")
        elif p["source"] == "file":
            lines.append(f"{head}: from the file {p['file']}")
        else:
            lines.append(f"{head}: {p['source']}")
    corr = [c for c in prov["corrections"] if c["digest"] is not None]
    if not corr:
        lines.append("corrections: none applied")
    for c in corr:
        head = f"corrections of {c['sequence']}" if several else "corrections"
        lines.append(
            f"{head}: {c['map_voxels']} voxels and {c['scan_points']} scan points in "
            f"{c['scan_frames']} frames (digest {c['digest']})"
        )
    if prov["silent_classes"]:
        names = ", ".join(dict.fromkeys(s["class"] for s in prov["silent_classes"]))
        lines.append(f"classes the 2D labeler (almost) never found: {names} (see the run's warnings)")
    code = prov["code"]
    lines.append(
        f"code: leap-studio {code['package']}" + (f", commit {code['commit']}" if code["commit"] else "")
    )
    return lines


__all__ = ["WEIGHTS_TEXT", "code_version", "provenance_lines", "run_provenance"]
