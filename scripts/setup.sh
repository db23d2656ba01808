#!/usr/bin/env bash
# One command for a fresh Debian machine: install what is missing, build, and
# run the main job on the sample scene (render data_samples/tiny_scene).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install_deps.sh
scripts/build.sh -DAG2GS_BUILD_TESTS=OFF
build/ag2gs devices
build/ag2gs info data_samples/synth_small --eval
build/ag2gs render --ply data_samples/tiny_scene/gaussians.ply --scene data_samples/tiny_scene \
  -o out/tiny_scene --bg 0,0,0
echo "setup: done. Rendered images are in out/tiny_scene/rgb/"
