"""Regenerate the result tables of docs/RESULTS.md by running the commands that page names.

Every regenerated table in docs/RESULTS.md sits between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``;
this script runs the commands of each (``leap synth``, ``leap run``, through ``python -m app.cli`` so
they are exactly the CLI's), reads the runs' ``metrics.json`` and writes the tables back in place. Run
folders are reused (``leap run`` on an existing ``--out`` resumes and skips finished stages), so a second
call, or ``--check`` after a regeneration, runs nothing long.

Tables:

- ``demo-miou``: point / voxel / +3D-CN x1 / x2 on the demo sequence (``leap run ... --3dcn-iterations 2``);
- ``prompt-expansion``: bare, short and full prompt expansion, 3D-CN off.

Both are on the demo's seed 0, a *report* seed: no default was chosen on it (the 3D-CN defaults were
chosen on tuning seeds 101-103 by ``lab/tune_defaults.py``; the simulated labeler's lexicon on seed
1). The page's other figures are not regenerated here: the speed and timing figures come from the
``benchmarks/*.py`` scripts (machine-dependent), and the models' speed table needs real Grounding DINO /
SAM weights, which cannot be downloaded on the build machines.

Usage (from the repository root; about 20 min on 2 CPU cores for the first run, seconds afterwards)::

    .venv/bin/python scripts/readme_tables.py            # run what is missing, rewrite the tables
    .venv/bin/python scripts/readme_tables.py --check    # exit 1 when docs/RESULTS.md differs from the runs
    .venv/bin/python scripts/readme_tables.py --only prompt-expansion   # one table (no 3D-CN: minutes)

The 3D-CN trains on the CPU here; its figures depend on the machine's float rounding (thread count,
torch version), so ``--check`` is meant for the machine that regenerated the tables.
"""

from __future__ import annotations

import argparse
import difflib
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from leap_core.pipeline.evaluation import read_metrics_json  # noqa: E402  after the sys.path line

RESULTS = ROOT / "docs" / "RESULTS.md"
DEMO = "data/demo"
SEQ = f"{DEMO}/sequences/00"
DEMO_FRAMES, DEMO_SEED = 60, 0

SYNTH = ["synth", DEMO, "--frames", str(DEMO_FRAMES), "--seed", str(DEMO_SEED)]
RUN_DEMO = [
    "run",
    SEQ,
    "--schema",
    "semantickitti",
    "--labeler",
    "simulated",
    "--out",
    "runs/demo",
    "--3dcn-iterations",
    "2",
]
RUN_BARE = [
    "run",
    SEQ,
    "--project-file",
    "projects/semantickitti_bare.yaml",
    "--labeler",
    "simulated",
    "--no-3dcn",
    "--out",
    "runs/bare",
]
RUN_SHORT = [
    "run",
    SEQ,
    "--project-file",
    "projects/semantickitti.yaml",
    "--labeler",
    "simulated",
    "--no-3dcn",
    "--out",
    "runs/short",
]
RUN_EXPANDED = [
    "run",
    SEQ,
    "--project-file",
    "projects/semantickitti_expanded.yaml",
    "--labeler",
    "simulated",
    "--no-3dcn",
    "--out",
    "runs/expanded",
]
ROWS = ["point", "voxel", "+3D-CN x1", "+3D-CN x2"]
TABLES = ("demo-miou", "prompt-expansion")
"""Names of the docs/RESULTS.md tables this script writes (each between its markers)."""


def leap(args: list[str]) -> None:
    """Run ``leap ARGS`` (the CLI module of this checkout) in the repository root; stop on failure."""
    print("$ leap " + " ".join(args), flush=True)
    done = subprocess.run([sys.executable, "-m", "app.cli", *args], cwd=ROOT, check=False)
    if done.returncode != 0:
        sys.exit(f"readme_tables: `leap {' '.join(args)}` failed (exit {done.returncode})")


def ensure_demo() -> None:
    """The demo sequence: generated when missing; an existing one must have the demo's frame count."""
    scans = ROOT / SEQ / "velodyne"
    if not scans.is_dir():
        leap(SYNTH)
    n = len(list(scans.glob("*.bin")))
    if n != DEMO_FRAMES:
        sys.exit(
            f"readme_tables: {ROOT / SEQ} has {n} scans, the demo of docs/RESULTS.md has {DEMO_FRAMES}; "
            f"move it away or regenerate it with `leap {' '.join(SYNTH)} --force`"
        )


def metrics_of(run: list[str]) -> dict[str, Any]:
    """Run (or resume) ``leap run ...`` and return its ``metrics.json``."""
    leap(run)
    out = ROOT / run[run.index("--out") + 1]
    data = read_metrics_json(out)
    if data is None:
        sys.exit(f"readme_tables: {out} has no metrics.json (no ground truth?)")
    return data


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}"


def _share(x: float | None) -> str:
    if x is None:
        return "n/a"
    return f"{100 * x:.0f} %" if x > 0.995 else f"{100 * x:.1f} %"


def _cmd(args: list[str]) -> str:
    return "leap " + " ".join(args)


def demo_miou(m: dict[str, Any]) -> str:
    """The ``demo-miou`` table: camera-view mIoU, the paper's protocol (camera view, Table 1's 11 merged
    classes; when the run has it), all-points mIoU, and the share of the points with a ground-truth label
    that got a label (the all-points protocol's ``labeled_share``)."""
    cam, all_ = m["camera"], m["all"]
    paper = m.get("paper")
    lines = [
        f"*Report seed {DEMO_SEED} (the demo's seed; no default was chosen on it). "
        f"Command: `{_cmd(SYNTH)}`, then `{_cmd(RUN_DEMO)}`; regenerated by `scripts/readme_tables.py`.*",
        "",
        "| mIoU | point | voxel | +3D-CN ×1 | +3D-CN ×2 |",
        "|---|---|---|---|---|",
        "| camera view | " + " | ".join(_pct(cam[r]["miou"]) for r in ROWS) + " |",
        *(
            [
                "| paper's 11 classes (camera view) | "
                + " | ".join(_pct(paper[r]["miou"]) for r in ROWS)
                + " |"
            ]
            if paper
            else []
        ),
        "| all points | " + " | ".join(_pct(all_[r]["miou"]) for r in ROWS) + " |",
        "| points labeled | " + " | ".join(_share(all_[r]["labeled_share"]) for r in ROWS) + " |",
    ]
    return "\n".join(lines)


def prompt_expansion(bare: dict[str, Any], short: dict[str, Any], full: dict[str, Any]) -> str:
    """The ``prompt-expansion`` table: point and voxel mIoU per prompt file, both protocols."""

    def row(label: str, m: dict[str, Any]) -> str:
        cells = [m[p][r]["miou"] for p in ("camera", "all") for r in ("point", "voxel")]
        return f"| {label} | " + " | ".join(_pct(c) for c in cells) + " |"

    lines = [
        f"*Report seed {DEMO_SEED}. Commands: `{_cmd(RUN_BARE)}`, `{_cmd(RUN_SHORT)}`, "
        f"`{_cmd(RUN_EXPANDED)}`; regenerated by `scripts/readme_tables.py`.*",
        "",
        "| prompts | camera view: point | camera view: voxel | all points: point | all points: voxel |",
        "|---|---|---|---|---|",
        row("`semantickitti_bare.yaml` (each class's name only)", bare),
        row("`semantickitti.yaml` (short expansion; the demo project)", short),
        row("`semantickitti_expanded.yaml` (full expansion)", full),
    ]
    return "\n".join(lines)


def compute(only: list[str]) -> dict[str, str]:
    """Run the commands of the tables in ``only`` (resuming finished runs); ``{table name: markdown}``."""
    ensure_demo()
    tables: dict[str, str] = {}
    if "demo-miou" in only:
        tables["demo-miou"] = demo_miou(metrics_of(RUN_DEMO))
    if "prompt-expansion" in only:
        tables["prompt-expansion"] = prompt_expansion(
            metrics_of(RUN_BARE), metrics_of(RUN_SHORT), metrics_of(RUN_EXPANDED)
        )
    return tables


def _markers(name: str) -> re.Pattern[str]:
    """Table ``name``'s opening marker (group 1), body (group 2) and closing marker (group 3)."""
    return re.compile(
        rf"(<!-- table:{re.escape(name)} -->\n)(.*?)(\n<!-- /table:{re.escape(name)} -->)", re.DOTALL
    )


def table_body(text: str, name: str) -> str | None:
    """The body between table ``name``'s markers in ``text`` (None: no such markers)."""
    found = _markers(name).search(text)
    return None if found is None else found.group(2)


def replace_tables(text: str, tables: dict[str, str]) -> str:
    """``text`` with the body between each table's markers replaced; a missing marker pair is an error."""
    for name, body in tables.items():
        pattern = _markers(name)
        if not pattern.search(text):
            sys.exit(f"readme_tables: {RESULTS}: no <!-- table:{name} --> ... <!-- /table:{name} --> markers")
        text = pattern.sub(lambda mt, body=body: mt.group(1) + body + mt.group(3), text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--check", action="store_true", help="Write nothing; exit 1 when docs/RESULTS.md differs."
    )
    ap.add_argument("--only", default=",".join(TABLES), help=f"Tables to compute: {', '.join(TABLES)}.")
    args = ap.parse_args()
    only = [t.strip() for t in args.only.split(",") if t.strip()]
    unknown = [t for t in only if t not in TABLES]
    if unknown:
        sys.exit(f"--only: unknown table(s) {', '.join(unknown)} (tables: {', '.join(TABLES)})")
    tables = compute(only)  # minutes to hours: the page is read after, so edits made meanwhile are kept
    old = RESULTS.read_text()
    new = replace_tables(old, tables)
    if args.check:
        if new != old:
            sys.stdout.writelines(
                difflib.unified_diff(
                    old.splitlines(keepends=True),
                    new.splitlines(keepends=True),
                    "docs/RESULTS.md",
                    "computed",
                )
            )
            sys.exit("readme_tables: docs/RESULTS.md's tables differ from the runs (see the diff above)")
        print("docs/RESULTS.md's tables match the runs")
        return
    if new != old:
        tmp = RESULTS.with_suffix(".md.tmp")
        tmp.write_text(new)
        tmp.replace(RESULTS)
        print(f"rewrote the tables of {RESULTS}")
    else:
        print(f"{RESULTS}: tables already up to date")


if __name__ == "__main__":
    main()
