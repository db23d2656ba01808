#!/usr/bin/env bash
# One command for a machine with a GPU (NVIDIA, AMD or Intel): installs what
# is missing, builds, lists the OpenCL devices, and compares the GPU with the
# CPU device:
#   1. the test suite on the GPU device ($AG2GS_DEVICE);
#   2. ag2gs_bench on both devices (100k and 1M Gaussians at 800x600 and
#      1920x1080: forward, backward, blend G evals/s, error against the
#      double-precision reference);
#   3. training on both devices (time, test PSNR, Gaussians);
#   4. two GPU trainings with the same seed: identical model bytes?
#   5. GPU and CPU renders of the GPU-trained model: PSNR between them.
# Results go to OUT/summary.md (and the logs beside it).
#
#   scripts/gpu_check.sh [--gpu N] [--cpu N] [--scene DIR] [-r R] [--iters N] [--out DIR] [--quick] [--no-tests]
#                        [--no-build]
#
# --gpu/--cpu: device indices from `build/ag2gs devices` (default: the first
#   GPU and the first CPU). Without a GPU the CPU device stands in for it, so
#   the script runs end to end anywhere (the numbers then compare a device
#   with itself). Without a CPU device (a GPU machine without PoCL) the CPU
#   rows are left out; render the GPU-trained model elsewhere to compare.
# --no-build: use the build/ that is there (built elsewhere, or by hand).
# --scene: a scene folder (default ../shared/scenes/cup at -r 2 when present,
#   else data_samples/synth_small at -r 1); --iters: default 2000.
# --quick: small sizes (10k Gaussians, 400x300; 200 iterations) and no test
#   suite: a smoke run of the script itself.
set -euo pipefail
cd "$(dirname "$0")/.."

gpu="" cpu="" scene="" res="" iters=2000 out="out/gpu_check" quick=0 tests=1 build=1
while [ $# -gt 0 ]; do
  case "$1" in
    --gpu) gpu=$2; shift 2 ;;
    --cpu) cpu=$2; shift 2 ;;
    --scene) scene=$2; shift 2 ;;
    -r) res=$2; shift 2 ;;
    --iters) iters=$2; shift 2 ;;
    --out) out=$2; shift 2 ;;
    --quick) quick=1; tests=0; shift ;;
    --no-tests) tests=0; shift ;;
    --no-build) build=0; shift ;;
    -h|--help) sed -n '2,27p' "$0"; exit 0 ;;
    *) echo "gpu_check: unknown argument '$1' (see --help)" >&2; exit 1 ;;
  esac
done
if [ -z "$scene" ]; then
  if [ -d ../shared/scenes/cup ]; then scene=../shared/scenes/cup; res=${res:-2}; else scene=data_samples/synth_small; fi
fi
res=${res:-1}
counts=(100000 1000000) sizes=(800x600 1920x1080) repeats=3
if [ $quick = 1 ]; then counts=(10000) sizes=(400x300) repeats=1 iters=200; fi

if [ $build = 1 ]; then
  scripts/install_deps.sh --test
  scripts/build.sh -DAG2GS_BUILD_TESTS=ON
fi
mkdir -p "$out"
out=$(cd "$out" && pwd)
summary="$out/summary.md"

echo "== OpenCL devices"
command -v clinfo >/dev/null && clinfo -l || true
build/ag2gs devices | tee "$out/devices.txt"
# Device index of the first line "[i] ..." followed by "type: KIND".
first_of_type() {
  awk -v kind="$1" '/^\[[0-9]+\]/ { idx = substr($1, 2, index($1, "]") - 2) }
                    /type: / && $2 == kind && found == "" { found = idx } END { print found }' "$out/devices.txt"
}
stand_in=""
[ -n "$cpu" ] || cpu=$(first_of_type CPU)
[ -n "$gpu" ] || gpu=$(first_of_type GPU)
if [ -z "$gpu" ]; then
  gpu=${cpu:-0}
  stand_in=" (no GPU device found: the CPU device $cpu stands in, so GPU and CPU rows compare a device with itself)"
fi
name_of() { awk -v i="[$1]" '$1 == i { $1 = ""; sub(/^ *(\(default[^)]*\) *)?/, ""); print; exit }' "$out/devices.txt"; }
{
  echo "# ag2gs GPU check, $(date -u +%Y-%m-%d)"
  echo
  echo "- GPU role: device $gpu, $(name_of "$gpu")$stand_in"
  if [ -n "$cpu" ]; then echo "- CPU role: device $cpu, $(name_of "$cpu")"; else echo "- CPU role: no CPU OpenCL device here, CPU rows left out"; fi
  echo "- host: $(nproc) cores, $(uname -m); scene $scene at -r $res, $iters iterations"
  echo
} >"$summary"

if [ $tests = 1 ]; then
  echo "== test suite on device $gpu"
  if (cd build && AG2GS_DEVICE=$gpu ctest -j"$(nproc)" -E 'fuzz_smoke|oclgrind' --output-on-failure) \
    >"$out/ctest_gpu.txt" 2>&1; then
    verdict="passed"
  else
    verdict="FAILED (see ctest_gpu.txt)"
  fi
  echo "- test suite on the GPU device: $verdict: $(grep -E 'tests passed' "$out/ctest_gpu.txt" | tail -1)" >>"$summary"
  tail -n 3 "$out/ctest_gpu.txt"
fi

echo "== renderer benchmark"
roles="gpu"
[ -z "$cpu" ] || roles="cpu gpu"
for role in $roles; do
  dev=${!role}
  build/ag2gs_bench --device "$dev" --counts "${counts[@]}" --sizes "${sizes[@]}" --repeats "$repeats" \
    >"$out/bench_$role.txt" 2>&1 || echo "ag2gs_bench on device $dev failed (see bench_$role.txt)"
  { echo; echo "## ag2gs_bench, $role role (device $dev)"; echo; grep '^|' "$out/bench_$role.txt" || true; } >>"$summary"
done

echo "== training, $iters iterations"
metric() {  # metric FILE KEY: a number from metrics.json (final test PSNR: final.psnr)
  python3 -c "import json,sys; d=json.load(open(sys.argv[1])); v=d
for k in sys.argv[2].split('.'): v=v[k]
print(round(v, 3) if isinstance(v, float) else v)" "$1" "$2"
}
train() {  # train ROLE TAG
  local dev=${!1}
  rm -rf "$out/train_$2"
  local t0=$(date +%s.%N)
  build/ag2gs train "$scene" -o "$out/train_$2" -r "$res" --iters "$iters" --eval --seed 1 --stages 1 --device "$dev" \
    >"$out/train_$2.log" 2>&1
  local secs=$(python3 -c "print(round($(date +%s.%N) - $t0, 1))")
  local m="$out/train_$2/metrics.json"
  echo "| $2 | $dev | $secs | $(metric "$m" train_seconds) | $(metric "$m" final.psnr) | $(metric "$m" final.ssim) | $(metric "$m" gaussians) |" >>"$summary"
}
{
  echo
  echo "## Training: \`ag2gs train $scene -r $res --iters $iters --eval --seed 1 --stages 1\`"
  echo
  echo "| run | device | wall s | train s | test PSNR | SSIM | Gaussians |"
  echo "|---|---|---:|---:|---:|---:|---:|"
} >>"$summary"
[ -z "$cpu" ] || train cpu cpu
train gpu gpu
train gpu gpu_again

echo "== determinism and agreement"
if cmp -s "$out/train_gpu/model.ag2gs" "$out/train_gpu_again/model.ag2gs" &&
  cmp -s "$out/train_gpu/point_cloud.ply" "$out/train_gpu_again/point_cloud.ply"; then
  same="identical model bytes"
else
  same="DIFFERENT model bytes"
fi
for role in $roles; do
  rm -rf "$out/render_$role"
  build/ag2gs render "$out/train_gpu" --scene "$scene" --views test -o "$out/render_$role" --device "${!role}" \
    >"$out/render_$role.log" 2>&1
done
{
  echo
  echo "- two GPU trainings with seed 1: $same"
} >>"$summary"
if [ -n "$cpu" ]; then
  python3 scripts/psnr_dirs.py "$out/render_gpu/rgb" "$out/render_cpu/rgb" >"$out/render_psnr.txt"
  echo "- GPU against CPU renders of the GPU-trained model's test views: $(tail -n 1 "$out/render_psnr.txt")" >>"$summary"
fi
echo
cat "$summary"
