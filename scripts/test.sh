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

# Python 3.12, the second supported version, with torch at the low end of its range (2.10; the
# 3.11 venv above has the newest): the tests of the Python-facing surface, in .venv-py312.
echo "== pytest on Python 3.12"
py312=""
for candidate in python3.12 "$(pyenv root 2>/dev/null)"/versions/3.12*/bin/python3.12; do
  if "$candidate" -c "" 2>/dev/null; then py312=$(command -v "$candidate"); break; fi
done
if [ -z "$py312" ]; then
  echo "skipped: no Python 3.12 interpreter on this machine"
else
  GEAR_PYTHON="$py312" GEAR_VENV=.venv-py312 GEAR_TORCH="torch==2.10.*" \
    bash scripts/setup.sh >/dev/null
  .venv-py312/bin/python -m pytest -q tests/test_install.py tests/test_core.py \
    tests/test_camera.py tests/test_data.py tests/test_data_layouts.py tests/test_splat.py
fi
