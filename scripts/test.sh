#!/usr/bin/env bash
# Installs everything (incl. test extras and Chromium) and runs the whole test suite.
#
#   bash scripts/test.sh [--fast] [PYTEST ARGS]
#
# The tests run in 2 processes (pytest-xdist), each test file in one of them, so that a module's fixtures
# are built once, the longest files first (tests/conftest.py); -n 0 runs them in this process (a single
# file, a debugger).
# --fast: the edit loop: skips the tests marked slow (about 3 s or more each: pipeline and server runs, the
# wheel install) or browser (real Chromium), and installs only when .venv lacks the test tools (after a
# dependency change, run bash scripts/install.sh --test). CI runs the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
parallel=(-n 2 --dist loadfile --no-loadscope-reorder)
if [ "${1:-}" = "--fast" ]; then
  shift
  if ! .venv/bin/python -c "import pytest, xdist" 2>/dev/null; then bash scripts/install.sh --test; fi
  exec .venv/bin/python -m pytest "${parallel[@]}" -m "not slow and not browser" "$@"
fi
bash scripts/install.sh --test
exec .venv/bin/python -m pytest "${parallel[@]}" "$@"
