"""The paper's Table 1 reproduced on the two synthetic domains: point, voxel, +3D-CN x1 and x2 per training
seed of the 3D Consistency Network, next to the paper's figures.

Domains (each a generated sequence and the CLI's own ``leap run``, through ``python -m lab``: the ``leap``
command line with the lab's labelers):

- ``street``: the demo street, ``leap synth DATA/demo --frames 60 --seed 0``, labeled by the lab's
  ``simulated-paper`` labeler with its ``paper`` preset (docs/RESULTS.md, "A paper-calibrated simulated
  labeler"; ``lab.paper_labeler``), evaluated on the paper's protocol: camera view, Table 1's 11 merged
  classes (``metrics.json`` key ``paper``); its 3D-CN rounds start from a *source network*
  (:attr:`Domain.source`), trained by ``leap train-3dcn`` on the ground truth of three ``street-32`` sequences
  (another LiDAR, another town: ``leap_core.synth.domains``), as the paper fine-tunes a network trained on
  another data set, and its seed runs set the 3D-CN temperature (:attr:`Domain.settings`, chosen on street
  tuning sequences 21-23; docs/METHOD.md C.5);
- ``agri``: the farm drone, ``leap synth DATA/agri40 --domain agri-uav --frames 40 --seed 0`` with
  ``projects/agri_uav.yaml`` and the simulated labeler (its default preset: the ``paper`` preset's
  confusions are street classes), evaluated in camera view over its 7 classes (``metrics.json`` key
  ``camera``; the paper's AgriUAV column is the same 7 classes).

Sharing the work across training seeds: the 2D labels, the projection, the fused and the smoothed grids do
not read ``consistency`` (each stage's fingerprint covers only its own config section), so one *base* run
per domain (3D-CN off) computes them, and each seed's run folder starts as hard links of the base run
(``leap run`` then skips every stage whose fingerprint matches; a stage that reruns replaces its files
atomically, so the base run's files are never written through the links). The seed's run differs only in
its project file, a copy of the domain's with ``pipeline.consistency.seed`` (and any ``--set``) added,
written next to the runs. Compute: one base run per domain, the source network once (``RUNS/sources/``,
shared by the report and the tuning sequences of the domain), then ``--iterations`` 3D-CN rounds per seed.
``--from-scratch`` (with ``--tag``) starts the rounds from random weights instead, for comparison.
Running with ``--iterations 1`` first and ``2`` later reuses round 1's checkpoint (its fingerprint does not
include the round count) and redoes only round 1's inference.

Usage (from the repository root)::

    .venv/bin/python -m lab.table1 --data /work/data --runs runs/table1          # everything
    .venv/bin/python -m lab.table1 --domains agri --seeds 0 --iterations 1      # one cell first
    .venv/bin/python -m lab.table1 --cached-only --readme   # tabulate finished runs, docs/RESULTS.md
    .venv/bin/python -m lab.table1 --domains agri --seeds 0 --iterations 1 \\
        --set consistency.class_balance=false --tag nobalance     # a variant, in its own run folders
    .venv/bin/python -m lab.table1 --domains agri --sequence-seed 101 --frames 30 --seeds 0 \
        --iterations 1 --set consistency.class_balance_power=0.25 --tag _p25   # on a tuning sequence

Prints the Markdown table (per seed, the mean, and the paper's row; gains = +3D-CN minus voxel, and the x1
gain once more on the same points: the camera view's points every row labels, ``metrics.json``'s
``common`` table, since the camera protocol scores the 3D-CN, which labels every point, on points the
voxel row leaves unlabeled and is not scored on) and, per domain, whether the acceptance of the
reproduction holds (+3D-CN x1 > voxel for every seed, mean gain >= 5 points: the 3D-CN must improve on the
voxel row as the paper's does).
``--readme`` writes the table between the ``table:table1`` markers of docs/RESULTS.md: the rows of the domains
measured replace theirs, the other domains' rows stay (:func:`merged_table`).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from leap_core.eval_view import PAPER_VIEW
from leap_core.io_utils import atomic_write_bytes
from leap_core.metrics import metrics_from_confusion
from leap_core.pipeline.evaluation import COMMON, PAPER, paper_metrics, read_metrics_json
from leap_core.run_layout import RunLayout, SequenceLayout, former_layout
from leap_core.synth.generator import VERSION_FILE

ROOT = Path(__file__).resolve().parents[1]

ROWS = ("point", "voxel", "+3D-CN x1", "+3D-CN x2")
"""``metrics.json`` columns, in Table 1's order (x2 is ours: the paper reports one round)."""
MIN_MEAN_GAIN = 5.0
"""The reproduction's acceptance: mean +3D-CN x1 gain over voxel, in mIoU points (the 3D-CN must lift the
voxel row clearly, as the paper's does: +8.7 on SemanticKITTI, +11.8 on AgriUAV)."""


@dataclass(frozen=True)
class Source:
    """A network trained on the ground truth of *another* domain, that the domain's 3D-CN rounds start from
    (``leap train-3dcn``, then ``leap run --3dcn-init``), as the paper fine-tunes a network trained before."""

    domain: str
    """``leap synth --domain`` of the source sequences."""
    seeds: tuple[int, ...]
    """Their ``--seed``s (one sequence each, never the report sequence's)."""
    frames: int
    """Their length."""
    steps: int
    """``leap train-3dcn --steps``."""
    settings: tuple[str, ...] = ()
    """``KEY=VALUE`` settings of the seed runs that start from this network, over the domain's own (which
    were chosen for rounds from random weights); chosen on the domain's tuning sequences."""

    def data(self, seed: int) -> str:
        """Folder under ``--data`` of the source sequence of ``seed``."""
        return f"{self.domain}_seed{seed}_f{self.frames}"

    @property
    def checkpoint(self) -> str:
        """File name of the source network, in ``RUNS/sources``."""
        return f"source_{self.domain}_{'-'.join(map(str, self.seeds))}_f{self.frames}_s{self.steps}.pt"

    @property
    def title(self) -> str:
        return (
            f"3D-CN fine-tuned from a network trained on {self.domain}'s ground truth "
            f"({len(self.seeds)} × {self.frames} scans)"
        )


@dataclass(frozen=True)
class Domain:
    """One column group of Table 1: how its data is generated, run and scored."""

    key: str
    title: str
    data: str
    """Folder under ``--data`` that ``leap synth`` writes."""
    synth: tuple[str, ...]
    """``leap synth`` arguments after the output folder."""
    project: str
    """Project file (relative to the repository root) the seed's copy is made of."""
    run_flags: tuple[str, ...]
    protocol: str
    """``metrics.json`` key of the table scored: ``paper`` (11 merged classes) or ``camera``."""
    protocol_title: str
    paper: tuple[float, float, float]
    """The paper's Table 1 mIoU (%): point, voxel, +3D-CN (one round)."""
    paper_title: str
    settings: tuple[str, ...] = ()
    """``KEY=VALUE`` pipeline settings of the domain's seed runs (as ``--set`` takes them; ``--set`` adds to
    and overrides them), each chosen on the domain's tuning sequences, never on the report sequence."""
    source: Source | None = None
    """The network the seed runs' 3D-CN starts from (None, or ``--from-scratch``: random weights)."""


DOMAINS: dict[str, Domain] = {
    "street": Domain(
        key="street",
        # The README's table names its blocks by these titles (block_domain): kept as they were.
        title="street demo, `paper` labeler preset",
        data="demo",
        synth=("--frames", "60", "--seed", "0"),
        project="projects/semantickitti.yaml",
        run_flags=("--labeler", "simulated-paper", "--labeler-preset", "paper"),
        protocol="paper",
        protocol_title="the paper's 11 merged classes, camera view",
        paper=(46.8, 48.9, 57.6),
        paper_title="paper, SemanticKITTI",
        # The 3D-CN's temperature for camera labels as noisy as the paper preset's (docs/METHOD.md C.5:
        # chosen on the street's tuning sequences 21-23; the default, 2, was chosen with the milder labeler).
        settings=("consistency.temperature=1",),
        # The paper fine-tunes a network trained before (docs/METHOD.md C.2): here one trained on the ground
        # truth of another street domain (32 beams, another town; leap_core.synth.domains), never this one.
        # Fine-tuned from it, the network is trusted more: T = 0.25 (tuning sequences 21-23, C.5).
        source=Source(
            domain="street-32",
            seeds=(201, 202, 203),
            frames=60,
            steps=600,
            settings=("consistency.temperature=0.25",),
        ),
    ),
    "agri": Domain(
        key="agri",
        title="farm drone (agri-uav), `default` labeler preset",
        data="agri40",
        synth=("--domain", "agri-uav", "--frames", "40", "--seed", "0"),
        project="projects/agri_uav.yaml",
        run_flags=("--labeler", "simulated"),
        protocol="camera",
        protocol_title="7 classes, camera view",
        paper=(38.0, 49.7, 61.5),
        paper_title="paper, AgriUAV",
    ),
}


# ----------------------------------------------------------------------------------------- pure logic
def retarget(dom: Domain, sequence_seed: int | None = None, frames: int | None = None) -> Domain:
    """The domain on another generated sequence: ``leap synth``'s ``--seed`` and/or ``--frames`` replaced,
    with data and run folders of its own (``agri`` → ``agri_seq101_f30``), so that runs on a tuning sequence
    never share a folder with the report runs. Unchanged when both are None."""
    if sequence_seed is None and frames is None:
        return dom
    synth = list(dom.synth)
    for flag, value in (("--seed", sequence_seed), ("--frames", frames)):
        if value is not None:
            synth[synth.index(flag) + 1] = str(value)
    seed, n = synth[synth.index("--seed") + 1], synth[synth.index("--frames") + 1]
    name = f"{dom.key}_seq{seed}_f{n}"
    return dataclasses.replace(
        dom, key=name, data=name, synth=tuple(synth), title=f"{dom.title}, sequence seed {seed}, {n} frames"
    )


@dataclass(frozen=True)
class SeedRow:
    """One training seed's mIoU (%) on a domain; ``None`` where the run has no such column."""

    seed: int
    point: float
    voxel: float
    x1: float | None
    x2: float | None
    same1: float | None = None
    """+3D-CN x1 minus voxel on the same points: the camera view's points that every row labels
    (:func:`same_points`); the other columns score each row on the points it labels itself."""

    @property
    def gain1(self) -> float | None:
        """+3D-CN x1 minus voxel (points)."""
        return None if self.x1 is None else self.x1 - self.voxel

    @property
    def gain2(self) -> float | None:
        """+3D-CN x2 minus voxel (points)."""
        return None if self.x2 is None else self.x2 - self.voxel


def same_points(metrics: Mapping[str, Any], protocol: str) -> dict[str, float]:
    """Row → mIoU (%) on the camera view's points that every row labels (``metrics.json``'s ``common``
    table), over ``protocol``'s classes: for ``paper`` the confusion matrices are merged into the paper's
    11 classes first (:data:`~leap_core.eval_view.PAPER_VIEW`). Empty when the file has no ``common``
    table (written before it existed)."""
    table = metrics.get(COMMON)
    if not table:
        return {}
    names, cats = list(metrics["class_names"]), list(metrics["categories"])
    mapping = PAPER_VIEW.mapping(names) if protocol == PAPER else None
    out = {}
    for row, cell in table.items():
        m = (
            metrics_from_confusion(
                np.asarray(cell["confusion"], np.int64), names, cats, ignore_unlabeled_pred=True
            )
            if mapping is None
            else paper_metrics(cell["confusion"], mapping)
        )
        out[row] = 100.0 * float(m.miou)
    return out


def seed_row(seed: int, metrics: Mapping[str, Any], protocol: str) -> SeedRow:
    """``metrics.json``'s mIoU of ``protocol`` as percentages: ``metrics[protocol][row]["miou"]`` × 100,
    and the x1 gain on the same points (:func:`same_points`) where the file has it.

    Raises:
        KeyError: ``protocol`` or the point / voxel column is missing (naming which).
    """
    try:
        table = metrics[protocol]
    except KeyError:
        raise KeyError(f"metrics have no {protocol!r} table (keys: {sorted(metrics)})") from None
    if table is None:
        raise KeyError(f"metrics' {protocol!r} table is empty (schema without it?)")

    def pct(row: str, required: bool) -> float | None:
        cell = table.get(row)
        if cell is None or cell.get("miou") is None:
            if required:
                raise KeyError(f"metrics' {protocol!r} table has no {row!r} column")
            return None
        return 100.0 * float(cell["miou"])

    point, voxel = pct("point", True), pct("voxel", True)
    assert point is not None and voxel is not None
    same = same_points(metrics, protocol)
    same1 = same["+3D-CN x1"] - same["voxel"] if "+3D-CN x1" in same and "voxel" in same else None
    return SeedRow(seed, point, voxel, pct("+3D-CN x1", False), pct("+3D-CN x2", False), same1)


def check_shared(rows: Sequence[SeedRow], tol: float = 1e-6) -> None:
    """The point and voxel columns of every seed must agree: they come from the one base run (the 3D-CN
    seed does not enter them). A difference means a seed's run recomputed them from other settings.

    Raises:
        ValueError: naming the seeds and the column that differ.
    """
    for r in rows[1:]:
        for name in ("point", "voxel"):
            a, b = getattr(rows[0], name), getattr(r, name)
            if abs(a - b) > tol:
                raise ValueError(
                    f"{name} mIoU differs between seed {rows[0].seed} ({a:.3f}) and seed "
                    f"{r.seed} ({b:.3f}): the runs do not share one base run"
                )


def _mean(xs: Sequence[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return sum(vals) / len(vals) if vals and len(vals) == len(xs) else None


def _std(xs: Sequence[float | None]) -> float | None:
    """Sample standard deviation (n − 1); None below two values or when one is missing."""
    m = _mean(xs)
    if m is None or len(xs) < 2:
        return None
    vals = [x for x in xs if x is not None]
    return math.sqrt(sum((x - m) ** 2 for x in vals) / (len(vals) - 1))


@dataclass(frozen=True)
class Verdict:
    """The reproduction's acceptance on one domain: +3D-CN x1 > voxel for every seed, mean x1 gain >= 5."""

    every_seed: bool
    mean_gain: float | None
    passed: bool


def verdict(rows: Sequence[SeedRow], min_mean_gain: float = MIN_MEAN_GAIN) -> Verdict:
    """Acceptance over ``rows`` (False when a seed has no x1 column or there are no rows)."""
    gains = [r.gain1 for r in rows]
    every = bool(rows) and all(g is not None and g > 0 for g in gains)
    mean = _mean(gains) if rows else None
    return Verdict(every, mean, every and mean is not None and mean >= min_mean_gain)


def _f(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


def _g(x: float | None) -> str:
    return "n/a" if x is None else f"{x:+.1f}"


def _pm(m: float | None, s: float | None, fmt: Any) -> str:
    return fmt(m) if s is None else f"{fmt(m)} ± {s:.1f}"


def domain_lines(dom: Domain, rows: Sequence[SeedRow]) -> list[str]:
    """Markdown rows of one domain: a line per seed, the mean (± sample std) over seeds, the paper's row.

    Columns: domain / protocol, seed, point, voxel, +3D-CN x1, +3D-CN x2, gain x1, gain x2 (gains are
    +3D-CN minus voxel; the paper's x1 gain is its +3D-CN minus its voxel; it has no x2 column), gain x1
    on the same points (:attr:`SeedRow.same1`; the paper has none).
    """
    check_shared(rows)
    lines = []
    for i, r in enumerate(rows):
        settings = "".join(f", `{kv}`" for kv in dom.settings)
        origin = "" if dom.source is None else f", {dom.source.title}"
        head = f"{dom.title}{origin}{settings} ({dom.protocol_title})" if i == 0 else ""
        lines.append(
            f"| {head} | {r.seed} | {_f(r.point)} | {_f(r.voxel)} | {_f(r.x1)} | {_f(r.x2)} "
            f"| {_g(r.gain1)} | {_g(r.gain2)} | {_g(r.same1)} |"
        )
    if len(rows) > 1:
        x1 = [r.x1 for r in rows]
        x2 = [r.x2 for r in rows]
        g1 = [r.gain1 for r in rows]
        g2 = [r.gain2 for r in rows]
        s1 = [r.same1 for r in rows]
        lines.append(
            f"| | mean | {_f(rows[0].point)} | {_f(rows[0].voxel)} | {_pm(_mean(x1), _std(x1), _f)} "
            f"| {_pm(_mean(x2), _std(x2), _f)} | {_pm(_mean(g1), _std(g1), _g)} "
            f"| {_pm(_mean(g2), _std(g2), _g)} | {_pm(_mean(s1), _std(s1), _g)} |"
        )
    p, v, cn = dom.paper
    lines.append(
        f"| | *{dom.paper_title}* | *{p:.1f}* | *{v:.1f}* | *{cn:.1f}* | — | *{cn - v:+.1f}* | — | — |"
    )
    return lines


def table_markdown(results: Sequence[tuple[Domain, Sequence[SeedRow]]]) -> str:
    """The whole Table 1 (Markdown), one block of rows per domain with at least one seed measured."""
    lines = [
        "| domain (protocol) | 3D-CN seed | point | voxel | +3D-CN ×1 | +3D-CN ×2 | gain ×1 | gain ×2 "
        "| gain ×1, same points |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for dom, rows in results:
        if rows:
            lines += domain_lines(dom, rows)
    return "\n".join(lines)


def table_blocks(table: str) -> list[list[str]]:
    """The body rows of a :func:`table_markdown` table, one block per domain (a row whose first cell is not
    empty starts a block)."""
    blocks: list[list[str]] = []
    for line in table.splitlines()[2:]:
        if line.split("|")[1].strip() or not blocks:
            blocks.append([])
        blocks[-1].append(line)
    return blocks


def block_domain(block: Sequence[str]) -> str | None:
    """The :data:`DOMAINS` key whose title the block's first cell starts with (None: no such domain)."""
    first = block[0].split("|")[1].strip()
    return next((k for k, d in DOMAINS.items() if first.startswith(d.title)), None)


def merged_table(old: str, new: str) -> str:
    """``new`` (a :func:`table_markdown` table) with the blocks of ``old`` kept for the domains ``new`` has
    no rows of (in :data:`DOMAINS` order; blocks of unknown domains last), so that measuring one domain
    rewrites its rows and keeps the others'."""
    fresh = {block_domain(b): b for b in table_blocks(new)}
    kept = {block_domain(b): b for b in table_blocks(old)}
    body = [line for key in DOMAINS for line in fresh.get(key) or kept.get(key) or []]
    unknown = [line for b in table_blocks(old) if block_domain(b) is None for line in b]
    return "\n".join([*new.splitlines()[:2], *body, *unknown])


def verdict_line(dom: Domain, rows: Sequence[SeedRow]) -> str:
    """One sentence: the reproduction's acceptance on this domain (:func:`verdict`), over the seeds
    measured."""
    v = verdict(rows)
    seeds = ", ".join(str(r.seed) for r in rows)
    return (
        f"{dom.key}: +3D-CN x1 > voxel for every seed ({seeds}): {'yes' if v.every_seed else 'no'}; "
        f"mean gain {_g(v.mean_gain)} (needs >= {MIN_MEAN_GAIN:.0f}): "
        f"{'PASS' if v.passed else 'not met'}"
    )


# --------------------------------------------------------------------------------------------- runs
def leap(args: Sequence[str]) -> None:
    """Run ``leap ARGS`` (this checkout's CLI, with the lab's labelers: ``python -m lab``) in the
    repository root; stop on failure."""
    print("$ python -m lab " + " ".join(args), flush=True)
    done = subprocess.run([sys.executable, "-m", "lab", *args], cwd=ROOT, check=False)
    if done.returncode != 0:
        sys.exit(f"table1: `leap {' '.join(args)}` failed (exit {done.returncode})")


def parse_sets(items: Sequence[str]) -> dict[str, Any]:
    """``--set a.b=VALUE`` (VALUE as JSON, else a string) → nested ``{"a": {"b": VALUE}}``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            sys.exit(f"--set {item!r}: expected KEY=VALUE, e.g. consistency.class_balance=false")
        try:
            value: Any = json.loads(raw)
        except ValueError:
            value = raw
        node = out
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def _merge(base: dict[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out.get(k) or {}, v) if isinstance(v, Mapping) else v
    return out


def with_settings(dom: Domain, extra: Sequence[str]) -> Domain:
    """``dom`` with ``extra`` (``--set``) added to its own settings, a key given again replacing the earlier
    value: what its seed runs use and its table rows name."""
    by_key = {kv.split("=", 1)[0]: kv for kv in (*dom.settings, *extra)}
    return dataclasses.replace(dom, settings=tuple(by_key.values()))


def as_run(dom: Domain, extra: Sequence[str] = (), *, from_scratch: bool = False) -> Domain:
    """The domain as its seed runs are made: from its source network with the source's settings over the
    domain's (or, ``from_scratch``, from random weights with the domain's own), then ``extra`` (``--set``)
    over both."""
    if from_scratch:
        dom = dataclasses.replace(dom, source=None)
    elif dom.source is not None:
        dom = with_settings(dom, dom.source.settings)
    return with_settings(dom, extra)


def seed_project(dom: Domain, seed: int, sets: Mapping[str, Any], folder: Path, tag: str) -> Path:
    """A copy of the domain's project file with ``pipeline.consistency.seed = seed`` and ``sets`` added."""
    doc = yaml.safe_load((ROOT / dom.project).read_text())
    pipeline = _merge(doc.get("pipeline") or {}, sets)
    doc["pipeline"] = _merge(pipeline, {"consistency": {"seed": seed}})
    path = folder / f"{dom.key}_seed{seed}{tag}.yaml"
    folder.mkdir(parents=True, exist_ok=True)
    text = f"# written by lab/table1.py from {dom.project}\n" + yaml.safe_dump(doc, sort_keys=False)
    atomic_write_bytes(path, text.encode())
    return path


def link_base(base: Path, run: Path) -> None:
    """Hard-link the stage outputs of the base run's sequence folders into a new seed run folder (copies
    across file systems); the run's own files (its log, lock, parameters, zips, metrics; a sequence's
    corrections and export counts) and hidden temporaries are not carried. A seed run folder that exists
    is left as it is (it resumes; ``leap run`` moves one an earlier version wrote)."""
    if RunLayout(run).sequences_dir.is_dir() or former_layout(run) is not None:
        return
    layout = RunLayout(base)
    names = layout.names()
    if not names or not layout.sequence(names[0]).state.is_file():
        sys.exit(
            f"table1: {base} has no sequence with its {SequenceLayout.STATE}: the base run did not finish"
        )

    def ignore(folder: str, entries: list[str]) -> set[str]:
        in_sequence = Path(folder).parent == layout.sequences_dir
        return {
            n for n in entries if n.startswith(".") or (in_sequence and n in SequenceLayout.RUN_OWN_FILES)
        }

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    tmp = run.with_name(run.name + ".linking")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(layout.sequences_dir, tmp / RunLayout.SEQUENCES, ignore=ignore, copy_function=link)
    tmp.rename(run)


def synth(root: Path, synth_args: Sequence[str]) -> Path:
    """``root``'s sequence 00, generated unless a finished one is there (``synth_version.txt`` is written
    last: a folder without it is an interrupted generation, replaced)."""
    seq = root / "sequences" / "00"
    if not (seq / VERSION_FILE).is_file():
        leap(["synth", str(root), *synth_args, *(["--force"] if seq.exists() else [])])
    return seq


def source_network(dom: Domain, args: argparse.Namespace) -> Path | None:
    """The domain's source network (:attr:`Domain.source`): generated and trained unless its checkpoint is
    there. None: the domain has none (its rounds start from random weights)."""
    src = dom.source
    if src is None:
        return None
    # One file for every sequence of the domain (the report's and the tuning ones): it reads none of them.
    ckpt = Path(args.runs) / "sources" / src.checkpoint
    if not ckpt.is_file():
        seqs = [
            synth(
                Path(args.data) / src.data(s),
                ["--domain", src.domain, "--frames", str(src.frames), "--seed", str(s)],
            )
            for s in src.seeds
        ]
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        leap(
            [
                "train-3dcn",
                *map(str, seqs),
                "--out",
                str(ckpt),
                "--project-file",
                dom.project,
                "--steps",
                str(src.steps),
            ]
        )
    return ckpt


def measure(dom: Domain, seeds: Sequence[int], args: argparse.Namespace) -> list[SeedRow]:
    """Run (or resume) the base run, the source network and each seed's run of ``dom``; the seeds' rows."""
    seq = synth(Path(args.data) / dom.data, dom.synth)
    runs = Path(args.runs) / dom.key
    ckpt = source_network(dom, args) if seeds else None
    init = [] if ckpt is None else ["--3dcn-init", str(ckpt)]
    base = runs / "base"
    leap(["run", str(seq), "--project-file", dom.project, *dom.run_flags, "--no-3dcn", "--out", str(base)])
    rows = []
    for s in seeds:
        run = runs / f"seed{s}{args.tag}"
        link_base(base, run)
        project = seed_project(dom, s, parse_sets(dom.settings), runs / "projects", args.tag)
        leap(
            [
                "run",
                str(seq),
                "--project-file",
                str(project),
                *dom.run_flags,
                "--3dcn-iterations",
                str(args.iterations),
                *init,
                "--out",
                str(run),
            ]
        )
        rows.append(read_row(run, s, dom))
    return rows


def sequence_metrics(run: Path) -> dict[str, Any] | None:
    """The ``metrics.json`` of the run's (one) sequence as written; None when it has none."""
    layout = RunLayout(run)
    names = layout.names()
    data = read_metrics_json(layout.sequence(names[0]).folder) if names else None
    return None if data is None else data.to_dict()


def read_row(run: Path, seed: int, dom: Domain) -> SeedRow:
    data = sequence_metrics(run)
    if data is None:
        sys.exit(f"table1: {run} has no metrics.json")
    return seed_row(seed, data, dom.protocol)


def cached(dom: Domain, seeds: Sequence[int], args: argparse.Namespace) -> list[SeedRow]:
    """Rows of the seeds whose run folder holds 3D-CN figures (nothing is run)."""
    rows = []
    for s in seeds:
        run = Path(args.runs) / dom.key / f"seed{s}{args.tag}"
        data = sequence_metrics(run)
        if data is not None:
            row = seed_row(s, data, dom.protocol)
            if row.x1 is not None:
                rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data"), help="Folder of the generated sequences.")
    ap.add_argument("--runs", default=str(ROOT / "runs" / "table1"), help="Folder of the run folders.")
    ap.add_argument("--domains", default="street,agri", help=f"Among {', '.join(DOMAINS)}.")
    ap.add_argument("--seeds", default="0,1,2", help="3D-CN training seeds (consistency.seed).")
    ap.add_argument("--iterations", type=int, default=2, choices=(1, 2), help="3D-CN rounds per seed.")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="Extra pipeline setting for the seed runs, e.g. consistency.class_balance=false.",
    )
    ap.add_argument("--tag", default="", help="Suffix of the seed run folders (for --set variants).")
    ap.add_argument(
        "--sequence-seed",
        type=int,
        default=None,
        help="Generate the domain's sequence with this seed (a tuning sequence, e.g. 101).",
    )
    ap.add_argument("--frames", type=int, default=None, help="Generate the domain's sequence this long.")
    ap.add_argument(
        "--from-scratch",
        action="store_true",
        help="Start the 3D-CN from random weights where a domain has a source network (needs --tag).",
    )
    ap.add_argument("--cached-only", action="store_true", help="Run nothing; tabulate finished seed runs.")
    ap.add_argument("--readme", action="store_true", help="Write the table into docs/RESULTS.md's markers.")
    args = ap.parse_args()
    if (args.set or args.from_scratch) and not args.tag:
        sys.exit("--set and --from-scratch need --tag (a variant gets its own run folders)")
    if args.readme and (args.sequence_seed is not None or args.frames is not None or args.tag):
        sys.exit("--readme writes the report sequences' table: not with --sequence-seed / --frames / --tag")
    names = [d.strip() for d in args.domains.split(",") if d.strip()]
    unknown = [d for d in names if d not in DOMAINS]
    if unknown:
        sys.exit(f"--domains: unknown {', '.join(unknown)} (known: {', '.join(DOMAINS)})")
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    results = []
    for name in names:
        dom = as_run(
            retarget(DOMAINS[name], args.sequence_seed, args.frames), args.set, from_scratch=args.from_scratch
        )
        rows = cached(dom, seeds, args) if args.cached_only else measure(dom, seeds, args)
        results.append((dom, rows))
    table = table_markdown(results)
    print(table)
    for dom, rows in results:
        if rows:
            print(verdict_line(dom, rows))
    if args.readme:
        # scripts/ is no package: load readme_tables.py for its marker replacement (same rule, same errors).
        spec = importlib.util.spec_from_file_location("readme_tables", ROOT / "scripts" / "readme_tables.py")
        assert spec is not None and spec.loader is not None
        rt = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(rt)
        readme: Path = rt.RESULTS
        text = readme.read_text()
        old = rt.table_body(text, "table1")
        new = rt.replace_tables(text, {"table1": table if old is None else merged_table(old, table)})
        if new != text:
            atomic_write_bytes(readme, new.encode())
            print(f"rewrote the table1 table of {readme}")


if __name__ == "__main__":
    main()
