#!/usr/bin/env bash
# One command for a fresh Debian machine: install what is missing, build, and
# run the main job on a sample scene: train stages 1-3 on the synthetic scene
# data_samples/synth_small (holding out every 8th view) and render the
# held-out views. Training and rendering take under a minute on 2 CPU cores.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install_deps.sh
# A fresh build leaves the tests out (faster); a build folder that already
# has them (scripts/test.sh) keeps them, so its test binaries never go stale.
if [ -f build/CMakeCache.txt ] && grep -q '^AG2GS_BUILD_TESTS:BOOL=ON' build/CMakeCache.txt; then
  scripts/build.sh
else
  scripts/build.sh -DAG2GS_BUILD_TESTS=OFF
fi
build/ag2gs devices
build/ag2gs info data_samples/synth_small --eval
# --force: a second run of this script replaces the demo model and renders it wrote before.
build/ag2gs train data_samples/synth_small -o out/synth_small --force --eval --iters 2000 --seed 1
build/ag2gs render out/synth_small --scene data_samples/synth_small --views test --outputs rgb,depth,alpha \
  -o out/synth_small/test_renders --force
# Text and click queries on the held-out views against the scene's labels.
build/ag2gs eval out/synth_small --scene data_samples/synth_small --labels data_samples/synth_small/label \
  --vocab data_samples/synth_small/vocab.json --clicks data_samples/synth_small/clicks.json -o out/synth_small/eval.json --force
echo "setup: done. Model in out/synth_small/ (point_cloud.ply, model.ag2gs, metrics.json);"
echo "       renders of the held-out views in out/synth_small/test_renders/; query scores in out/synth_small/eval.json"
