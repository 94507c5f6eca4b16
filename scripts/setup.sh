#!/usr/bin/env bash
# Installs everything gear needs on a Debian machine, idempotently (quick when already done):
# Mesa's software Vulkan driver, a Python venv (3.11 in .venv by default; GEAR_PYTHON=python3.12
# GEAR_VENV=.venv-py312 for another) with the dependencies, and the Rust extension built in
# release mode into that venv.
set -euo pipefail
cd "$(dirname "$0")/.."

# 1. System packages: the Vulkan loader and Mesa's drivers (lavapipe = software Vulkan).
missing=()
for pkg in libvulkan1 mesa-vulkan-drivers; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing ${missing[*]}"
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# 1b. Headless Chromium and its WebDriver for the browser test of `gear view` (tests skip
#     without them). GEAR_NO_BROWSER=1 leaves them out.
if [ -z "${GEAR_NO_BROWSER:-}" ] && ! command -v chromedriver >/dev/null; then
  echo "setup: installing chromium chromium-driver (the viewer's browser test)"
  sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends chromium chromium-driver >/dev/null
fi

# 2. Toolchains the machine must already have.
command -v cargo >/dev/null || { echo "setup: cargo not found; install Rust (rustup)" >&2; exit 1; }
python="${GEAR_PYTHON:-python3.11}"
venv="${GEAR_VENV:-.venv}"
command -v "$python" >/dev/null || { echo "setup: $python not found" >&2; exit 1; }

# 3. The venv with maturin; maturin then installs the project's dependencies.
[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q "maturin>=1.7,<2"

# 4. torch only ever runs on the CPU here (the GPU work goes through wgpu), so where no CUDA GPU
# is present the CPU build is enough (PyPI's Linux build adds 4.5 GB of CUDA libraries and
# triton). It comes from the PyTorch CPU index; when that index is unreachable, PyPI's default
# build is installed with the other dependencies below. An installed torch is kept.
# GEAR_TORCH overrides the requirement (the tests pin the low end of the range this way).
if ! "$venv/bin/python" -c "import torch" 2>/dev/null; then
  # PyPI's torch with its CUDA libraries fills about 7 GB; fail here, with the reason, rather
  # than halfway through pip with "No space left on device".
  need_gib=8
  free_gib=$(df -Pk "$venv" | awk 'NR == 2 { print int($4 / 1048576) }')
  if [ "$free_gib" -lt "$need_gib" ]; then
    echo "setup: only ${free_gib} GiB free where $venv lives; installing torch and the other" \
      "dependencies needs about ${need_gib} GiB (free some space, or set GEAR_VENV to a venv" \
      "path on a larger disk)" >&2
    exit 1
  fi
  torch_req="${GEAR_TORCH:-$("$venv/bin/python" -c "import tomllib; print(next(d for d in
    tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']
    if d.startswith('torch')))")}"
  if ! { command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; }; then
    "$venv/bin/python" -m pip install -q --timeout 10 --retries 0 \
        --index-url https://download.pytorch.org/whl/cpu "$torch_req" 2>/dev/null \
      || echo "setup: the PyTorch CPU index is unreachable; installing PyPI's torch (with CUDA libraries)"
  fi
  "$venv/bin/python" -c "import torch" 2>/dev/null || "$venv/bin/python" -m pip install -q "$torch_req"
fi

# 5. The Rust extension (gear._core) plus the package, editable, with the dev and colmap
# extras. A venv made when the distribution was still called "gear" drops that name first.
"$venv/bin/python" -m pip show -q gear 2>/dev/null && "$venv/bin/python" -m pip uninstall -q -y gear
VIRTUAL_ENV="$PWD/$venv" "$venv/bin/maturin" develop --release --extras dev,colmap,batch -q 2>&1 | grep -v -E "^(📦|🔗|🐍|⚠️ Warning: You|💻|🛠|📖|✏️|🎯)" || true
"$venv/bin/python" -c "import gear._core" || { echo "setup: the extension did not build" >&2; exit 1; }
