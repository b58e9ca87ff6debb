#!/usr/bin/env bash
# Mutation testing of the core modules with mutmut (config: pyproject.toml [tool.mutmut]; results and the
# list of equivalent mutants: docs/MUTATION.md, docs/mutation-survivors.csv). Not part of CI: hours on 2 cores.
#
#   scripts/mutation.sh [--fresh] [--survivors] [MODULE ...]
#
# MODULE: fusion smoothing projection metrics cn-selection cn-stage stages runner evaluation simulated
# export kitti (default: all, one after the other). Each module's mutants run against the fast tests that
# reach the mutated function (no slow, browser or app-server tests). Prints the score per module and overall.
#   --fresh      delete mutants/ first (mutmut otherwise reuses its copy and its test-to-function map)
#   --survivors  re-test only the mutants that survived the last run (after adding tests)
# Environment: MUTMUT (default .venv/bin/mutmut), MUTMUT_CHILDREN (parallel mutants, default 2).
set -euo pipefail
cd "$(dirname "$0")/.."

MUTMUT="${MUTMUT:-.venv/bin/mutmut}"
PYTHON="$(dirname "$MUTMUT")/python"
CHILDREN="${MUTMUT_CHILDREN:-2}"

declare -A FILE=(
    [fusion]=leap_core/fusion.py
    [smoothing]=leap_core/smoothing.py
    [projection]=leap_core/projection.py
    [metrics]=leap_core/metrics.py
    [cn-selection]=leap_core/consistency/selection.py
    [cn-stage]=leap_core/consistency/stage.py
    [stages]=leap_core/pipeline/stages.py
    [runner]=leap_core/pipeline/runner.py
    [evaluation]=leap_core/pipeline/evaluation.py
    [simulated]=leap_core/labelers/simulated.py
    [export]=leap_core/export.py
    [kitti]=leap_core/datasets/kitti.py
)
ORDER=(cn-selection metrics evaluation smoothing projection fusion cn-stage stages runner simulated export kitti)

fresh=0
survivors=0
modules=()
for arg in "$@"; do
    case "$arg" in
        --fresh) fresh=1 ;;
        --survivors) survivors=1 ;;
        -h|--help) sed -n '2,12p' "$0"; exit 0 ;;
        *)
            if [[ -z "${FILE[$arg]:-}" ]]; then
                echo "unknown module '$arg' (one of: ${ORDER[*]})" >&2
                exit 2
            fi
            modules+=("$arg") ;;
    esac
done
[[ ${#modules[@]} -gt 0 ]] || modules=("${ORDER[@]}")
[[ -x "$MUTMUT" ]] || { echo "mutmut not found at $MUTMUT (bash scripts/install.sh --test, or set MUTMUT)" >&2; exit 2; }

[[ $fresh -eq 1 ]] && rm -rf mutants
paths=()
for m in "${modules[@]}"; do
    path="${FILE[$m]}"
    paths+=("$path")
    dotted="${path%.py}"
    dotted="${dotted//\//.}"
    start=$(date +%s)
    if [[ $survivors -eq 1 ]]; then
        mapfile -t names < <("$PYTHON" - "$path" <<'EOF'
import json, sys
from pathlib import Path
meta = Path("mutants") / f"{sys.argv[1]}.meta"
if meta.exists():
    for name, code in json.loads(meta.read_text())["exit_code_by_key"].items():
        if code in (0, 5, 33, None):  # survived, no tests, not checked
            print(name)
EOF
)
        if [[ ${#names[@]} -eq 0 ]]; then
            echo "== $m: no survivors to re-test"
            continue
        fi
        echo "== $m: re-testing ${#names[@]} survivors"
    else
        names=("$dotted.*")
        echo "== $m ($path)"
    fi
    # mutmut redraws its progress line (spinner first) many times a second: keep one in 200 of those.
    nice -n 19 "$MUTMUT" run --max-children "$CHILDREN" "${names[@]}" 2>&1 | stdbuf -o0 tr '\r' '\n' \
        | awk '!/^(⠋|⠙|⠹|⠸|⠼|⠴|⠦|⠧|⠇|⠏)/ || ++n % 200 == 0 { print; fflush() }' || true
    echo "== $m took $(( $(date +%s) - start )) s"
done

echo
"$PYTHON" scripts/mutation_score.py "${paths[@]}"
