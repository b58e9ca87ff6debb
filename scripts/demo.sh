#!/usr/bin/env bash
# Installs LeAP Studio, generates the built-in demo sequence, labels it and serves the app on 127.0.0.1.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
exec .venv/bin/leap demo "$@"
