#!/usr/bin/env bash
# Every kernel of kernels/*.cl under Oclgrind, a simulated OpenCL device that
# runs work-groups with real barrier semantics and reports out-of-bounds
# accesses, data races between work-items (--data-races), API misuse
# (--check-api) and barriers reached by only part of a work-group.
#
#   tests/oclgrind/run_oclgrind.sh gpu|cpu|selfcheck|pipeline BUILD_DIR
#
# gpu: the GPU layout (one pixel per work-item, 256-wide work-groups,
#      records staged through local memory, the work-group radix sort), as
#      on a real GPU.
# cpu: the CPU layout (16-pixel vectors, one work-item per tile, no staging).
# selfcheck: plants an out-of-bounds access and a local-memory race in copies
#      of our kernels and passes only if both are reported: the check can fail.
# pipeline: the whole program in the GPU layout on a small generated scene
#      with an open sky: `ag2gs train` (stage 1 with growth, the importance
#      prune and the sky, stage 2, stage 3's instance maps), then `remove` and
#      `simulate` for a frame on its model; as a user runs them, as one
#      process each, so races between kernels of different stages show too.
#
# Each step runs a program under Oclgrind with its messages sent to a log; a
# step fails when the program fails or the log has anything in it. At the
# end every __kernel in kernels/*.cl must have been launched (the runtime
# writes each launch to $AG2GS_LAUNCH_LOG). Exit 2 (CTest: skipped) when
# oclgrind is not installed.
set -uo pipefail

layout=${1:?usage: run_oclgrind.sh gpu|cpu|selfcheck|pipeline BUILD_DIR}
build=$(cd "${2:?usage: run_oclgrind.sh gpu|cpu|selfcheck|pipeline BUILD_DIR}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
src=$(cd "$here/../.." && pwd)

if ! command -v oclgrind >/dev/null; then
  echo "oclgrind is not installed (Debian: apt-get install oclgrind; scripts/install_deps.sh --test does it): skipped"
  exit 2
fi

work="$build/oclgrind_$layout"
rm -rf "$work"
mkdir -p "$work"
failures=0
t_start=$(date +%s)

# step NAME COMMAND...: COMMAND under Oclgrind; its output in $work/NAME.out.
step() {
  local name=$1
  shift
  local t0=$(date +%s)
  oclgrind --data-races --check-api --log "$work/$name.log" "$@" >"$work/$name.out" 2>&1
  local rc=$?
  local secs=$(($(date +%s) - t0))
  if [ $rc -ne 0 ]; then
    echo "FAIL  $name (exit $rc, ${secs} s): $*"
    tail -n 30 "$work/$name.out" | sed 's/^/      /'
    failures=$((failures + 1))
  elif [ -s "$work/$name.log" ]; then
    echo "FAIL  $name (${secs} s): Oclgrind reported:"
    head -n 40 "$work/$name.log" | sed 's/^/      /'
    failures=$((failures + 1))
  else
    echo "ok    $name (${secs} s)"
  fi
}

# remove_and_simulate MODEL SCENE: the applications on a trained model, for
# selections of its first anchors (a few iterations train no features or
# geometry that a click could rely on): remove a quarter of them (holes,
# inpainted targets, the fill), and simulate four for one frame of 1/250 s
# (particles, 14 MPM substeps, the Gaussians following them, the frame's
# render; a 1/25 s frame of a quarter of the anchors took 3 minutes under
# the simulator).
remove_and_simulate() {
  local model=$1 scene=$2
  if python3 -c 'import json, sys; n = json.load(open(sys.argv[1]))["anchors"]
json.dump({"anchors": list(range(max(1, n // 4)))}, open(sys.argv[2], "w"))
json.dump({"anchors": list(range(min(4, n)))}, open(sys.argv[3], "w"))' \
    "$model/metrics.json" "$work/remove.json" "$work/simulate.json" 2>"$work/selection.out"; then
    step remove "$build/ag2gs" remove "$model" --scene "$scene" -o "$work/removed" --selection "$work/remove.json"
    step simulate "$build/ag2gs" simulate "$model" --scene "$scene" -o "$work/simulated" \
      --selection "$work/simulate.json" --frames 1 --fps 250 --grid 16
  else
    echo "FAIL  no selection from $model/metrics.json: $(cat "$work/selection.out")"
    failures=$((failures + 1))
  fi
}

if [ "$layout" = selfcheck ]; then
  # Our own kernels with two bugs put in: adam_step without its bounds check
  # (the padding work-items of the last group read and write past the
  # buffers), and the GPU layout's blend_bwd without the barrier before its
  # partial sums are read (a race on local memory). Each step must fail, with
  # the report in its log.
  mutated="$work/kernels"
  cp -r "$src/kernels" "$mutated"
  perl -0pi -e 's/if \(i >= n\) return;//' "$mutated/adam.cl"
  perl -0pi -e 's/barrier\(CLK_LOCAL_MEM_FENCE\);(\s*\/\/ Sum the work-items)/$1/' "$mutated/blend_bwd.cl"
  if cmp -s "$src/kernels/adam.cl" "$mutated/adam.cl" || cmp -s "$src/kernels/blend_bwd.cl" "$mutated/blend_bwd.cl"; then
    echo "FAIL  the selfcheck's mutations no longer apply to kernels/adam.cl and kernels/blend_bwd.cl: update them"
    exit 1
  fi
  export AG2GS_KERNEL_DIR="$mutated" AG2GS_VECTOR_WIDTH=1 AG2GS_BLEND_STAGING=1 AG2GS_DEVICE=0
  export AG2GS_SOURCE_DIR="$src" AG2GS_FILL_SENTINEL=1
  # Both steps must fail; what they print goes to steps.txt, not to the test's output.
  step adam_without_bounds_check "$build/test_adam" --gtest_filter='Adam.ConstantGradientMovesByLearningRate' \
    >>"$work/steps.txt"
  step blend_bwd_without_barrier "$build/test_render_backward" --gtest_filter='RenderBackward.OddSize' \
    >>"$work/steps.txt"
  ok=1
  grep -q "Invalid \(read\|write\)" "$work/adam_without_bounds_check.log" ||
    { echo "FAIL  the out-of-bounds accesses were not reported"; ok=0; }
  grep -qi "data race" "$work/blend_bwd_without_barrier.log" || { echo "FAIL  the data race was not reported"; ok=0; }
  [ $ok = 1 ] || exit 1
  echo "ok    both planted bugs were reported: $(grep -c "^Invalid" "$work/adam_without_bounds_check.log") \
invalid accesses, $(grep -ci "data race" "$work/blend_bwd_without_barrier.log") data races"
  exit 0
fi

if [ "$layout" = pipeline ]; then
  # 6 views of 160x120 trained at 40x30 (-r 4), the schedule squeezed into 4
  # iterations: growth at 2, the importance prune at 3, stage 2's propagation
  # loss once, stage 3 over the 5 training views.
  export AG2GS_VECTOR_WIDTH=1 AG2GS_BLEND_STAGING=1 AG2GS_DEVICE=0 AG2GS_FILL_SENTINEL=1
  echo "Oclgrind, the whole pipeline in the GPU layout, in $work"
  scene="$work/scene"
  if ! "$build/ag2gs" synth "$scene" --views 6 --width 160 --height 120 --objects 2 --points 1500 --feature-dim 84 \
    --samples 1 --no-backdrop >"$work/synth.out" 2>&1; then
    echo "FAIL  ag2gs synth:"
    tail -n 20 "$work/synth.out" | sed 's/^/      /'
    exit 1
  fi
  step train "$build/ag2gs" train "$scene" -o "$work/model" -r 4 --iters 4 --grow-from 2 --grow-every 2 --top-cells 8 \
    --prop-iters 1 --seed 1
  for want in "stage 3:" "removed the" "sky: SH degree"; do
    grep -q "$want" "$work/train.out" ||
      { echo "FAIL  the training log has no '$want': that path did not run"; failures=$((failures + 1)); }
  done
  remove_and_simulate "$work/model" "$scene"
  echo "pipeline: $(($(date +%s) - t_start)) s"
  [ $failures -eq 0 ] || { echo "$failures failure(s)"; exit 1; }
  exit 0
fi

case "$layout" in
  gpu) export AG2GS_VECTOR_WIDTH=1 AG2GS_BLEND_STAGING=1 AG2GS_SORT=group ;;
  cpu) export AG2GS_VECTOR_WIDTH=16 AG2GS_BLEND_STAGING=0 AG2GS_SORT=block ;;
  *) echo "unknown layout '$layout' (gpu, cpu or selfcheck)" >&2; exit 1 ;;
esac
export AG2GS_SOURCE_DIR="$src" AG2GS_BINARY="$build/ag2gs" AG2GS_FILL_SENTINEL=1
export AG2GS_LAUNCH_LOG="$work/launches.txt"
export AG2GS_DEVICE=0  # Oclgrind is the only platform its loader shows
echo "Oclgrind, $layout layout (vector width $AG2GS_VECTOR_WIDTH, staging $AG2GS_BLEND_STAGING), in $work"

# Renderer forward and backward against the double-precision reference:
# odd sizes, partial tiles, background, SH degrees, every output gradient,
# a tile with more Gaussians than a staging batch next to empty tiles.
step render_forward "$build/test_render_forward" \
  --gtest_filter='RenderForward.OnePixel:RenderForward.OddSize17x9:RenderForward.Background:RenderForward.LowerActiveShDegree'
step render_backward "$build/test_render_backward" \
  --gtest_filter='RenderBackward.OddSize:RenderBackward.BackgroundAndActiveDegree:RenderBackward.CrowdedTileAndEmptyTiles'
# The blend backward's other plans: one pixel per work-item with its values
# summed in 8 segments, and 8 pixels per work-item (the default is 4:8:2).
if [ "$layout" = gpu ]; then
  for plan in 1:2:8 8:3:1; do
    AG2GS_BLEND_BWD=$plan step render_backward_plan_${plan//:/_} "$build/test_render_backward" \
      --gtest_filter='RenderBackward.OddSize:RenderBackward.CrowdedTileAndEmptyTiles'
  done
fi
# The radix sorts (the CPU block sort and the GPU work-group sort, every
# digit width and work-group shape) against std::stable_sort, once; and
# renders with the other layout's sort and scans (AG2GS_SORT picks both).
if [ "$layout" = gpu ]; then
  step radix_sort "$build/test_radix_sort" --gtest_filter='RadixSort.EveryPlanGivesTheSameOrder'
  other_sort=block
else
  other_sort=group
fi
AG2GS_SORT=$other_sort step render_${other_sort}_sort "$build/test_render_forward" \
  --gtest_filter='RenderForward.OnePixel:RenderForward.OddSize17x9:RenderForward.Background'
# The one-launch sort in two halves and their merge (rs_merge_runs), which
# the GPU layout's own plan takes under Oclgrind: here with tiles of 32 keys,
# so that this small frame's depth sort splits.
if [ "$layout" = cpu ]; then
  AG2GS_SORT=group:4:32:1:auto:64:2 step render_split_sort "$build/test_render_forward" \
    --gtest_filter='RenderForward.OddSize17x9'
fi
# Under Oclgrind the work-group sort sorts and scans these frames in one
# launch each (rs_one_group, scan_one_group_wg); with that off it takes
# three launches a pass and a scan.
AG2GS_SORT=group:4:32:32:auto:0 step render_three_launch_sort "$build/test_render_forward" \
  --gtest_filter='RenderForward.OddSize17x9'
# The runtime's own checks of a launch (bin.cl's iota, which only they use).
step runtime "$build/test_runtime" --gtest_filter='Runtime.KernelCallChecksNamesAndBufferSizes'
# Culling, clamps, NaN and infinite parameters, empty scenes, bad input.
step hard_cases "$build/test_render_hard_cases" --gtest_filter='-HardCases.DeepStackSaturatesTransmittance'
# Losses, optimiser and the graph-stage kernels, each against its reference.
step image_loss "$build/test_image_loss" \
  --gtest_filter='ImageLoss.WeightedMatchesReference:ImageLoss.DeviceApiPlanarLayout'
step mask_loss "$build/test_mask_loss" \
  --gtest_filter='MaskLoss.Weights:MaskLoss.DegenerateViews:MaskLoss.AlphaNormalisation:MaskLoss.DeviceApiAndMaskCache'
step adam "$build/test_adam" \
  --gtest_filter='Adam.ConstantGradientMovesByLearningRate:Adam.VisibleRowsOnly:Adam.CountsNonFiniteValues:Adam.GatherRows'
step instance_map "$build/test_instance_map" --gtest_filter='InstanceMap.NearHalfTies'
# On the simulator the GPU layout's instance walk takes 4 pixels per
# work-item (device_policy.h); GPUs run it with the renderer's 1.
if [ "$layout" = gpu ]; then
  AG2GS_INSTANCE_VW=1 step instance_map_one_pixel "$build/test_instance_map" \
    --gtest_filter='InstanceMap.NearHalfTies'
fi
step propagation "$build/test_anchor_graph" --gtest_filter='PropagationLoss.DeviceMatchesReference'
step expander "$build/test_anchors" --gtest_filter='Expander.ForwardMatchesReference:Expander.ExtremeLogitsStayFinite'
step sky "$build/test_sky" \
  --gtest_filter='Sky.ComposeMatchesTheDoubleReference:Sky.ConstantStartAndArchiveRoundTrip:Sky.FitRecoversAKnownSky:Sky.FitResidualMatchesThePixelError:Sky.BackwardAfterComposeGivesTheBitsOfBackwardAlone'
# The MLS-MPM solver's substep against its double reference (every material),
# and the Gaussians that follow the particles.
step mpm "$build/test_mpm" --gtest_filter='Mpm.FewParticlesMatchTheDoubleReference'
step simulation "$build/test_simulation" --gtest_filter='Simulation.GaussiansFollowTheirParticles'

# The program end to end on a 32x32 generated scene with masks and features:
# stage 1 with growth, the mask losses and the regularisers, stage 2's
# propagation loss, stage 3's instance maps, the free-Gaussian baseline
# with densification, then (CPU layout) remove and simulate on the trained
# model. The GPU layout's remove and simulate run in the pipeline entry,
# on its larger scene; here they launched no kernel the steps above had not
# (about 30 s under Oclgrind).
scene="$work/scene"
if "$build/ag2gs" synth "$scene" --width 32 --height 32 --views 4 --objects 2 --points 200 --feature-dim 84 \
  --samples 1 >"$work/synth.out" 2>&1; then
  step train "$build/ag2gs" train "$scene" -o "$work/model" --iters 2 --grow-from 1 --grow-every 1 --mask-from 1 \
    --prop-iters 1
  step baseline "$build/ag2gs" baseline "$scene" -o "$work/baseline" --iters 2 --densify-from 1 --densify-every 1
  [ "$layout" = gpu ] || remove_and_simulate "$work/model" "$scene"
else
  echo "FAIL  ag2gs synth:"
  tail -n 20 "$work/synth.out" | sed 's/^/      /'
  failures=$((failures + 1))
fi

# Coverage: every kernel of kernels/*.cl launched at least once.
perl -0777 -ne 'while (/__kernel\b[^{;]*?\bvoid\s+(\w+)\s*\(/sg) { print "$1\n" }' "$src"/kernels/*.cl | sort -u \
  >"$work/kernels.txt"
touch "$work/launches.txt"
awk '{print $1}' "$work/launches.txt" | sort -u >"$work/launched.txt"
missing=$(comm -23 "$work/kernels.txt" "$work/launched.txt")
n_kernels=$(wc -l <"$work/kernels.txt")
n_covered=$(comm -12 "$work/kernels.txt" "$work/launched.txt" | wc -l)
n_launches=$(wc -l <"$work/launches.txt")
echo "coverage: $n_covered of $n_kernels kernels, $n_launches launches, $(($(date +%s) - t_start)) s"
if [ -n "$missing" ]; then
  echo "FAIL  never launched: $(echo $missing)"
  failures=$((failures + 1))
fi
[ $failures -eq 0 ] || { echo "$failures failure(s)"; exit 1; }
