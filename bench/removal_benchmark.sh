#!/usr/bin/env bash
# Object removal against exact ground truth: generates a scene with
# `ag2gs synth --removal-gt`, trains stages 1-3, removes each object category
# in turn by text (`ag2gs remove`, with its defaults, and `--no-fill`, which
# deletes only), renders the test views (never trained on) and scores them
# with ag2gs_bench_removal against the scene traced without that category:
# hole PSNR (inside the object's exact mask), kept PSNR (outside it) and
# residue, for the original model, deleting only, the removal, and a
# per-view 2D inpainting of the original render; and the fill's ceiling: the
# best any fill behind what the deleted model shows could score, each pixel
# given the colour nearest the truth through the part the model leaves open.
#
#   bench/removal_benchmark.sh OUT_DIR [--seed S] [--iters N] [--no-backdrop] [--width W --height H]
#                              [--reuse] [-- remove flags, e.g. --iters 300]
#
# --reuse keeps OUT_DIR/scene and OUT_DIR/model when both exist (an earlier
# run's, same settings: generating and training are deterministic).
#
# Example (about a minute on 2 CPU cores):
#   bench/removal_benchmark.sh out/bench_removal --seed 1 --iters 2000
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
bin="${AG2GS_BIN:-$here/build/ag2gs}"
score="$(dirname "$bin")/ag2gs_bench_removal"
[ $# -ge 1 ] || { sed -n 2,20p "$0" | sed 's/^# \{0,1\}//'; exit 2; }
out="$1"; shift
seed=1; iters=2000; synth=(); size=(--width 160 --height 120); remove_flags=(); reuse=0
while [ $# -gt 0 ]; do
  case "$1" in
    --seed) seed="$2"; shift 2 ;;
    --iters) iters="$2"; shift 2 ;;
    --no-backdrop) synth+=(--no-backdrop); shift ;;
    --reuse) reuse=1; shift ;;
    --width) size[1]="$2"; shift 2 ;;
    --height) size[3]="$2"; shift 2 ;;
    --) shift; remove_flags=("$@"); break ;;
    *) echo "removal_benchmark: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
mkdir -p "$out"
scene="$out/scene"; model="$out/model"
t0=$(date +%s)
if [ "$reuse" = 1 ] && [ -f "$scene/synth.json" ] && [ -f "$model/model.ag2gs" ]; then
  echo "reusing $scene and $model"
else
  "$bin" synth "$scene" --force --seed "$seed" --hard --removal-gt "${size[@]}" "${synth[@]}" -q
  "$bin" train "$scene" -o "$model" --force --eval --iters "$iters" --seed 1 -q
fi
t_train=$(($(date +%s) - t0))
rm -rf "$out/renders_original"
"$bin" render "$model" --scene "$scene" --views test --outputs rgb -r 1 -o "$out/renders_original" -q
table="$out/removal.txt"
: >"$table"
categories=$(python3 -c "import json,sys; print('\n'.join(sorted({o['category'] for o in json.load(open(sys.argv[1]))['objects']})))" "$scene/synth.json")
while IFS= read -r cat; do
  [ -n "$cat" ] || continue
  dir="$out/removed/${cat// /_}"
  rm -rf "$dir" "$dir.renders" "$dir.deleted" "$dir.deleted.renders" "$dir.deleted.black"
  ceiling=()
  # Deleting only, for reference: its "removed" row is reported as "deleted".
  if "$bin" remove "$model" --scene "$scene" --text "$cat" --vocab "$scene/vocab.json" -o "$dir.deleted" --no-fill -q &&
    "$bin" render "$dir.deleted" --scene "$scene" --views test --outputs rgb -r 1 -o "$dir.deleted.renders" -q &&
    "$score" "$scene" --category "$cat" --original "$out/renders_original" --removed "$dir.deleted.renders" \
      --json "$dir.deleted.score.json" >"$dir.deleted.score.txt"; then
    grep '^removed ' "$dir.deleted.score.txt" | sed 's/^removed /deleted /' | tee -a "$table"
    "$bin" render "$dir.deleted" --scene "$scene" --views test --outputs rgb,alpha --bg 0,0,0 -r 1 \
      -o "$dir.deleted.black" -q && ceiling=(--deleted "$dir.deleted.black")
  else
    echo "FAILED delete-only: $cat" | tee -a "$table"
  fi
  t1=$(date +%s.%N)
  # A category that fails is reported and left out of the means (they say over how many).
  if ! "$bin" remove "$model" --scene "$scene" --text "$cat" --vocab "$scene/vocab.json" -o "$dir" -q \
    ${remove_flags[@]+"${remove_flags[@]}"}; then
    echo "FAILED remove: $cat" | tee -a "$table"
    continue
  fi
  t2=$(date +%s.%N)
  if ! "$bin" render "$dir" --scene "$scene" --views test --outputs rgb -r 1 -o "$dir.renders" -q ||
    ! "$score" "$scene" --category "$cat" --original "$out/renders_original" --removed "$dir.renders" \
      ${ceiling[@]+"${ceiling[@]}"} --json "$dir.score.json" >"$dir.score.txt"; then
    echo "FAILED render or score: $cat" | tee -a "$table"
    continue
  fi
  tee -a "$table" <"$dir.score.txt"
  python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(f\"{sys.argv[2]:<12} counts: removed {d['anchors_removed']} anchors / {d['gaussians_removed']} Gaussians, kept {d['gaussians_kept']}, added {d['anchors_added']} anchors / {d['gaussians_added']} Gaussians, hole pixels {d['holes']['pixels']}, fine-tune {d['iterations']} it, remove {float(sys.argv[4]) - float(sys.argv[3]):.1f} s\")" \
    "$dir/removal.json" "$cat" "$t1" "$t2" | tee -a "$table"
done <<<"$categories"
if [ "$reuse" = 1 ] && [ "$t_train" -lt 5 ]; then
  echo "train: reused" | tee -a "$table"
else
  echo "train (stages 1-3, $iters iterations): ${t_train} s" | tee -a "$table"
fi
# Means over the categories, per method.
for method in original deleted removed inpaint_2d ceiling; do
  grep "^$method " "$table" | awk -v m="$method" '{h+=$4; k+=$7; r+=$9; n++} END {if (n) printf "mean %-18s hole PSNR %6.2f  kept PSNR %6.2f  residue %.4f  (%d categories)\n", m, h/n, k/n, r/n, n}'
done | tee -a "$table"
