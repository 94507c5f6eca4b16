#!/usr/bin/env bash
# Sets up (see setup.sh), then runs the main job on a built-in synthetic scene: generates the
# one-door fridge, trains it with the quick profile, and prints the recovered joint next to the
# scene's ground truth (gear eval). Outputs go to runs/demo/. Extra arguments go to `gear train`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"  # silences Mesa's WSI probe
py=.venv/bin/python
scene=runs/demo/fridge
out=runs/demo/fridge-quick

$py -m gear info
[ -f "$scene/transforms_train_start.json" ] ||
  $py -m gear synth fridge --out "$scene" --res 96 --views 24 --test-views 4
$py -m gear train "$scene" --out "$out" --profile quick --overwrite "$@"  # replaces an earlier demo run
$py -m gear eval "$out" "$scene"
echo "demo: outputs in $out (joints.json, meshes/, parts/, renders/); try"
echo "  $py -m gear render $out --t 0 0.5 1   and   $py -m gear export $out --urdf $out/urdf"
