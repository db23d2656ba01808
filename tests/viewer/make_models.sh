#!/usr/bin/env bash
# The viewer tests' models (a CTest fixture): the sample scene trained
# through stages 1-3 (500 iterations, ~15 s on 2 cores) and a stage-1-only
# model (no clusters, so no text queries), both in BUILD_DIR/test_view/.
#   tests/viewer/make_models.sh BUILD_DIR
set -euo pipefail
src="$(cd "$(dirname "$0")/../.." && pwd)"
out="$1/test_view"
bin="${AG2GS_BINARY:-$1/ag2gs}"
mkdir -p "$out"
"$bin" train "$src/data_samples/synth_small" -o "$out/model" --iters 500 --eval --seed 1 --quiet --force
"$bin" train "$src/data_samples/synth_small" -o "$out/model_stage1" --iters 100 --stages 1 --eval --seed 1 \
  --quiet --force
# The selections `ag2gs query` makes, which the viewer must reproduce byte for byte.
rm -rf "$out/query_click" "$out/query_text"
"$bin" query "$out/model" --scene "$src/data_samples/synth_small" --view view_000 --click 70,62 \
  --views view_000,view_003 -o "$out/query_click" >/dev/null
"$bin" query "$out/model" --scene "$src/data_samples/synth_small" --text "blue mug" \
  --vocab "$src/data_samples/synth_small/vocab.json" --views view_000,view_003 -o "$out/query_text" >/dev/null
echo "make_models: $out/{model,model_stage1,query_click,query_text}"
