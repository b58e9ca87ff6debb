"""Mutation score per module from mutmut's results (scripts/mutation.sh runs it after mutmut).

score = killed / (total − equivalent), where killed counts mutmut's "killed", "timeout" and "segfault" (a
mutant that makes the tests run past mutmut's limit, or crashes their process, is caught by them), and the
equivalent mutants are the rows of docs/mutation-survivors.csv (columns module, mutant, status, reason)
whose status is ``equivalent``. Rows of status ``killed on a GPU`` name mutants that only tests/test_cuda.py
tells apart (skipped where torch sees no GPU, as here and in CI): seen killed on a GPU machine, they count
as killed when mutmut reports them survived. Rows of status ``killed by a test mutmut did not run`` (the
reason names the test) name mutants that a fast test fails on, run by hand with the mutant switched on, but
that mutmut did not run against them (it maps code a module-scoped fixture runs to the fixture's first test
only, and a test added after a run has no place in that run's map): they count as killed too. Rows of
status ``not equivalent`` are survivors kept with the reason they are accepted; they count as not killed.
A mutant with no result yet ("not checked": a run stopped early) makes the module's line say "incomplete".

Usage: python scripts/mutation_score.py [--survivors] [MODULE_PATH ...]   (from the repository root)
  --survivors   also print every surviving / untested mutant that docs/mutation-survivors.csv does not list
                as equivalent, and listed equivalents that are no longer survivors (stale entries).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

from mutmut.stats import status_by_exit_code

ROOT = Path(__file__).resolve().parents[1]
SURVIVORS = ROOT / "docs" / "mutation-survivors.csv"
# A mutant that made the tests fail, run past mutmut's time limit or crash the test process was caught.
CAUGHT = ("killed", "timeout", "segfault")
COLUMNS = ["module", "mutant", "status", "reason"]
STATUSES = ("equivalent", "killed on a GPU", "killed by a test mutmut did not run", "not equivalent")


def listed_mutants(status: str, path: Path = SURVIVORS) -> set[str]:
    """Mutant names docs/mutation-survivors.csv lists with ``status`` ("equivalent", "killed on a GPU", ...),
    one row each. A file with other columns or an unknown status is an error naming the file and row."""
    if not path.exists():
        return set()
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != COLUMNS:
            sys.exit(f"{path}: columns must be {', '.join(COLUMNS)}, not {reader.fieldnames}")
        names = set()
        for line, row in enumerate(reader, start=2):
            if row["status"] not in STATUSES:
                sys.exit(f"{path}:{line}: unknown status {row['status']!r} (one of: {', '.join(STATUSES)})")
            if row["status"] == status:
                names.add(row["mutant"])
    return names


def module_results(path: str) -> dict[str, str]:
    """{mutant name: mutmut status} of one mutated file, from ``mutants/<path>.meta``."""
    meta = ROOT / "mutants" / f"{path}.meta"
    if not meta.exists():
        return {}
    codes = json.loads(meta.read_text())["exit_code_by_key"]
    return {name: status_by_exit_code[code] for name, code in codes.items()}


def main(argv: list[str]) -> int:
    show = "--survivors" in argv
    paths = [a for a in argv if not a.startswith("--")]
    if not paths:
        paths = sorted(
            str(p.relative_to(ROOT / "mutants"))[: -len(".meta")]
            for p in (ROOT / "mutants" / "leap_core").rglob("*.py.meta")
        )
    equivalent = listed_mutants("equivalent")
    # Killed by tests mutmut does not run against them: on a GPU machine, or by a test its map misses.
    outside = listed_mutants("killed on a GPU") | listed_mutants("killed by a test mutmut did not run")
    head = ("mutants", "killed", "survived", "no tests", "equiv.")
    print(f"{'module':38} " + " ".join(f"{h:>8}" for h in head) + f" {'score':>7}")
    tot = {"n": 0, "killed": 0, "equiv": 0, "survived": 0, "untested": 0}
    incomplete_any = False
    left: list[str] = []
    stale: list[str] = []
    for path in paths:
        res = module_results(path)
        if not res:
            print(f"{path:38} (no results: run scripts/mutation.sh first)")
            continue
        n_outside = sum(1 for n, s in res.items() if s == "survived" and n in outside)
        killed = sum(s in CAUGHT for s in res.values()) + n_outside
        eq = sum(1 for name in res if name in equivalent)
        survived = [n for n, s in res.items() if s == "survived" and n not in equivalent | outside]
        untested = [
            n for n, s in res.items() if s not in (*CAUGHT, "survived", "not checked") and n not in equivalent
        ]
        stale += [n for n in res if n in equivalent | outside and res[n] in CAUGHT]
        incomplete = any(s == "not checked" for s in res.values())
        incomplete_any |= incomplete
        denom = len(res) - eq
        score = f"{100 * killed / denom:6.1f}%" if denom else "    -  "
        cells = (len(res), killed, len(survived), len(untested), eq)
        print(
            f"{path:38} "
            + " ".join(f"{v:8d}" for v in cells)
            + f" {score}"
            + ("  incomplete" if incomplete else "")
            + (f"  ({n_outside} killed outside mutmut's run)" if n_outside else "")
        )
        tot["n"] += len(res)
        tot["killed"] += killed
        tot["equiv"] += eq
        tot["survived"] += len(survived)
        tot["untested"] += len(untested)
        left += [f"{n}: survived" for n in survived] + [f"{n}: {res[n]}" for n in untested]
    denom = tot["n"] - tot["equiv"]
    if denom:
        cells = (tot["n"], tot["killed"], tot["survived"], tot["untested"], tot["equiv"])
        print(
            f"{'overall':38} "
            + " ".join(f"{v:8d}" for v in cells)
            + f" {100 * tot['killed'] / denom:6.1f}%"
            + ("  incomplete" if incomplete_any else "")
        )
    if show:
        print("\nnot killed and not listed as equivalent in docs/mutation-survivors.csv:")
        print("\n".join(f"  {line}" for line in left) or "  (none)")
        if stale:
            print(
                "\nlisted as equivalent or killed outside mutmut's run, but killed by mutmut now "
                "(remove from docs/mutation-survivors.csv):"
            )
            print("\n".join(f"  {n}" for n in stale))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
