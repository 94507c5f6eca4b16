#!/usr/bin/env bash
# Sets up (see setup.sh), then runs every check: formatting and lints, the Rust kernel parity
# tests (GPU kernels against the CPU reference), and the Python test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"  # silences Mesa's WSI probe

echo "== lint"
cargo fmt --all -- --check
cargo clippy --release --workspace --all-targets -q -- -D warnings
.venv/bin/ruff check -q python tests

echo "== cargo test"
cargo test --release --workspace -q 2>&1 | grep -v -E "^\s*$"

echo "== pytest"
.venv/bin/python -m pytest -q "$@"
