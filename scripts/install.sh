#!/usr/bin/env bash
# Installs everything LeAP Studio needs into ./.venv (idempotent). Used by scripts/demo.sh,
# scripts/test.sh and CI, so a fresh machine needs nothing installed by hand.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
# The CPU wheel of torch first: an unpinned torch would pull a multi-GB CUDA build.
.venv/bin/python -m pip install -q "torch==2.13.0"
# Every optional stack (pyproject.toml's extras: ray, ros, nuscenes, bench, fast), so every command works here;
# [test] includes them all and adds the test, lint and type-check tools.
extras="[ray,ros,nuscenes,bench,fast]"
if [ "${1:-}" = "--test" ]; then extras="[test]"; fi
# Editable: the checkout's code, presets (projects/) and web UI (web/) are what runs.
.venv/bin/python -m pip install -q -e ".${extras}"
# nuScenes devkit without its numpy<2 pin (see the nuscenes extra in pyproject.toml, which holds its imports).
.venv/bin/python -m pip install -q --no-deps "nuscenes-devkit==1.2.0"
if [ "${1:-}" = "--test" ] && [ ! -x /usr/bin/chromium ]; then
  # Real-browser tests drive Debian's Chromium (no browser download is possible here).
  if [ "$(id -u)" = "0" ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -q >/dev/null
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q chromium >/dev/null
fi
