#!/usr/bin/env bash
# Sets up (see setup.sh), then shows the adapter and runs the GPU kernel self-check.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
.venv/bin/python -m gear info --check
