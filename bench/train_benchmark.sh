#!/usr/bin/env bash
# Speed against error of the trainer on one scene: trains with --eval,
# evaluates the held-out views at the listed iterations, and writes a table
# (Markdown) and a plot (SVG) of test PSNR against training time, with anchor
# and Gaussian counts and peak memory. With --baseline, the free-Gaussian
# baseline (`ag2gs baseline`) runs on the same settings for comparison.
#
#   bench/train_benchmark.sh SCENE_DIR OUT_DIR [-r R] [--iters N] [--at 1000,3000,7000]
#                            [--baseline] [-- extra train flags]
#
# Example (the 30000-iteration table of docs/benchmarks.md on a real capture, ~1 hour on 2 CPU cores):
#   bench/train_benchmark.sh scenes/cup out/bench_cup -r 2 --iters 30000 --at 1000,3000,7000
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
bin="${AG2GS_BIN:-$here/build/ag2gs}"
[ $# -ge 2 ] || { sed -n 2,13p "$0" | sed 's/^# \{0,1\}//'; exit 2; }
scene="$1"; out="$2"; shift 2
res=1; iters=30000; at="1000,3000,7000"; baseline=0; extra=()
while [ $# -gt 0 ]; do
  case "$1" in
    -r) res="$2"; shift 2 ;;
    --iters) iters="$2"; shift 2 ;;
    --at) at="$2"; shift 2 ;;
    --baseline) baseline=1; shift ;;
    --) shift; extra=("$@"); break ;;
    *) echo "train_benchmark: unknown argument '$1'" >&2; exit 2 ;;
  esac
done
[ -x "$bin" ] || { echo "train_benchmark: $bin not built; run scripts/build.sh first" >&2; exit 2; }
mkdir -p "$out"
runs=("$out/anchors")
"$bin" train "$scene" -o "$out/anchors" --force -r "$res" --iters "$iters" --eval --test-at "$at" --seed 1 \
  --log-every 500 "${extra[@]}" 2>&1 | tee "$out/anchors.log"
if [ "$baseline" = 1 ]; then
  "$bin" baseline "$scene" -o "$out/baseline" --force -r "$res" --iters "$iters" --eval --test-at "$at" --seed 1 \
    --log-every 500 2>&1 | tee "$out/baseline.log"
  runs+=("$out/baseline")
fi
python3 "$here/bench/report_metrics.py" "${runs[@]}" --md "$out/table.md" --svg "$out/psnr_vs_time.svg"
echo "wrote $out/table.md and $out/psnr_vs_time.svg"
