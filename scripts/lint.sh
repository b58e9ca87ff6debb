#!/usr/bin/env bash
# Lint and type checks CI runs beside the tests: ruff (rule set and documented exceptions in
# pyproject.toml), ruff's formatter (check only) and mypy --strict on app and leap_core.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/mypy ]; then bash scripts/install.sh --test; fi
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy --strict app leap_core
echo "lint: ruff and mypy clean"
