#!/usr/bin/env bash
# Query accuracy and the paper's ablation on a synthetic scene with exact
# ground truth: trains the full method (stage 2 with L_prop) and the same
# schedule without L_prop (--w-prop 0), evaluates both with and without
# region growing (`ag2gs eval`, --no-grow), and writes a table of text and
# click mIoU / mBIoU and query latency:
#
#   full                 = L_prop + region growing
#   L_prop only          = L_prop, plain feature similarity
#   region growing only  = no L_prop, region growing
#   neither
#
#   bench/query_benchmark.sh SCENE_DIR OUT_DIR [--iters N] [--generate SEED] [--views N]
#                            [--background-masks] [--eval-flags "..."] [-- extra train flags]
#
# --generate SEED writes a fresh hard scene (`ag2gs synth --hard`: touching
# objects, similar colours, a thin pole, occlusion) to SCENE_DIR first, with
# full-size masks as SAM gives them (at half size the thin pole's masks are
# about a pixel wide and stage 3 cannot match it); with --background-masks
# the floor, wall and ceiling get SAM-like masks too, cut differently in
# each view (`ag2gs synth --background-masks`). --views N: cameras of the
# generated scene (default 16: 14 training views, label frames view_000 and
# view_008; every 8th view is a test view and a label frame).
# Example (~6 minutes on 2 CPU cores):
#   bench/query_benchmark.sh out/synth_hard_7 out/bench_query --generate 7 --iters 3000 -- --top-cells 50
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
bin="${AG2GS_BIN:-$here/build/ag2gs}"
[ $# -ge 2 ] || { sed -n 2,25p "$0" | sed 's/^# \{0,1\}//'; exit 2; }
scene="$1"; out="$2"; shift 2
iters=3000; views=16; generate=""; eval_flags=""; extra=(); synth_flags=()
while [ $# -gt 0 ]; do
  case "$1" in
    --iters) iters="$2"; shift 2 ;;
    --generate) generate="$2"; shift 2 ;;
    --views) views="$2"; shift 2 ;;
    --background-masks) synth_flags+=(--background-masks); shift ;;
    --eval-flags) eval_flags="$2"; shift 2 ;;
    --) shift; extra=("$@"); break ;;
    *) echo "query_benchmark: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
[ -x "$bin" ] || { echo "query_benchmark: $bin not built; run scripts/build.sh first" >&2; exit 2; }
if [ -n "$generate" ]; then
  "$bin" synth "$scene" --force --hard --seed "$generate" --views "$views" --points 3000 "${synth_flags[@]}"
fi
for f in label vocab.json clicks.json; do
  [ -e "$scene/$f" ] || { echo "query_benchmark: $scene/$f missing (a scene from \`ag2gs synth\` has it)" >&2; exit 2; }
done
mkdir -p "$out"
for run in full no_prop; do
  flags=()
  [ "$run" = no_prop ] && flags=(--w-prop 0)
  "$bin" train "$scene" -o "$out/$run" --force --iters "$iters" --eval --seed 1 --log-every 1000 "${flags[@]}" "${extra[@]}" \
    2>&1 | tee "$out/$run.log"
  for grow in grow no_grow; do
    g=()
    [ "$grow" = no_grow ] && g=(--no-grow)
    # shellcheck disable=SC2086
    "$bin" eval "$out/$run" --scene "$scene" --labels "$scene/label" --vocab "$scene/vocab.json" \
      --clicks "$scene/clicks.json" -o "$out/eval_${run}_${grow}.json" --force "${g[@]}" $eval_flags | tee "$out/eval_${run}_${grow}.txt"
  done
done
python3 - "$out" <<'EOF'
import json, sys, os
out = sys.argv[1]
rows = [("full (L_prop + growing)", "full", "grow"), ("L_prop only", "full", "no_grow"),
        ("region growing only", "no_prop", "grow"), ("neither", "no_prop", "no_grow")]
lines = ["| variant | text mIoU | text mBIoU | click mIoU | click mBIoU | query ms (mean / max) |",
         "|---|---:|---:|---:|---:|---:|"]
for name, run, grow in rows:
    j = json.load(open(os.path.join(out, f"eval_{run}_{grow}.json")))
    t, c = j["text"], j["click"]
    lines.append(f"| {name} | {100*t['mean_iou']:.2f} | {100*t['mean_biou']:.2f} | {100*c['mean_iou']:.2f} | "
                 f"{100*c['mean_biou']:.2f} | {max(t['mean_ms'], c['mean_ms']):.1f} / {max(t['max_ms'], c['max_ms']):.1f} |")
table = "\n".join(lines) + "\n"
open(os.path.join(out, "table.md"), "w").write(table)
print(table)
EOF
echo "wrote $out/table.md"
