#!/usr/bin/env bash
# Installs everything gear needs on a Debian machine, idempotently (quick when already done):
# Mesa's software Vulkan driver, a Python 3.11 venv in .venv with the pinned dependencies,
# and the Rust extension built in release mode into that venv.
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
command -v python3.11 >/dev/null || { echo "setup: python3.11 not found" >&2; exit 1; }

# 3. The venv with maturin; maturin then installs the project's pinned dependencies.
[ -x .venv/bin/python ] || python3.11 -m venv .venv
.venv/bin/python -m pip install -q "maturin>=1.7,<2"

# 4. The Rust extension (gear._core) plus the package, editable, with dev extras.
.venv/bin/maturin develop --release --extras dev -q 2>&1 | grep -v -E "^(📦|🔗|🐍|⚠️ Warning: You|💻|🛠|📖|✏️|🎯)" || true
.venv/bin/python -c "import gear._core" || { echo "setup: the extension did not build" >&2; exit 1; }
