#!/usr/bin/env bash
# Installs everything (incl. test extras and Chromium) and runs the whole test suite.
#
#   bash scripts/test.sh [--fast] [PYTEST ARGS]
#
# --fast: the edit loop: skips the tests marked slow (a few seconds or more each, e.g. whole pipeline runs,
# the wheel install) or browser (real Chromium), and installs only when .venv has no pytest yet (after a
# dependency change, run bash scripts/install.sh --test). CI runs the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--fast" ]; then
  shift
  if [ ! -x .venv/bin/pytest ]; then bash scripts/install.sh --test; fi
  exec .venv/bin/python -m pytest -m "not slow and not browser" "$@"
fi
bash scripts/install.sh --test
exec .venv/bin/python -m pytest "$@"
