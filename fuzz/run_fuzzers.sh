#!/usr/bin/env bash
# Builds the libFuzzer targets into build_fuzz/ (clang, ASan + UBSan) and runs
# each for a bounded time, one after the other, writing everything to
# fuzz_out/ (gitignored): fuzz_out/<target>/corpus (inputs found, reused by
# the next run), findings/ (crashes, leaks, timeouts, out-of-memory inputs)
# and log-<date>.txt (one per run, with libFuzzer's final statistics).
#
# Usage: fuzz/run_fuzzers.sh [SECONDS_PER_TARGET (default 60)] [TARGET...]
#   TARGET: fuzz_npy fuzz_ply fuzz_colmap_bin fuzz_colmap_txt fuzz_model fuzz_json (default: all)
# Environment: CXX_FUZZ / CC_FUZZ (default clang++ / clang), JOBS (build
# parallelism, default 2), FUZZ_ARGS (extra libFuzzer flags), FUZZ_TMPDIR
# (where the targets write their inputs; default /dev/shm).
# Exit status: 0 when no target found anything, 1 otherwise.
set -euo pipefail

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
SECONDS_PER_TARGET=${1:-60}
shift || true
TARGETS=("$@")
[ ${#TARGETS[@]} -eq 0 ] && TARGETS=(fuzz_npy fuzz_ply fuzz_colmap_bin fuzz_colmap_txt fuzz_model fuzz_json)

pick() { for c in "$@"; do command -v "$c" >/dev/null 2>&1 && { command -v "$c"; return; }; done; }
CXX_FUZZ=${CXX_FUZZ:-$(pick clang++ clang++-14)}
CC_FUZZ=${CC_FUZZ:-$(pick clang clang-14)}
[ -n "$CXX_FUZZ" ] && [ -n "$CC_FUZZ" ] || { echo "run_fuzzers: clang not found (install clang and libclang-rt-dev)" >&2; exit 2; }

BUILD="$ROOT/build_fuzz"
OUT="$ROOT/fuzz_out"
cmake -S "$ROOT" -B "$BUILD" -DCMAKE_BUILD_TYPE=Debug -DCMAKE_CXX_COMPILER="$CXX_FUZZ" -DCMAKE_C_COMPILER="$CC_FUZZ" \
  -DAG2GS_BUILD_FUZZ=ON -DAG2GS_BUILD_TESTS=OFF -DAG2GS_BUILD_BENCH=OFF >/dev/null
# A failed build is a failure (exit 1), not CTest's "skipped" (make exits 2).
cmake --build "$BUILD" --target "${TARGETS[@]}" -j "${JOBS:-2}" || { echo "run_fuzzers: the build failed" >&2; exit 1; }
python3 "$ROOT/fuzz/make_seeds.py" "$OUT/seeds"

# The targets write each input to files (and fuzz_npy fsyncs a copy): in
# memory when /dev/shm is there, else inside fuzz_out. Removed at the end.
if [ -z "${FUZZ_TMPDIR:-}" ]; then
  if [ -d /dev/shm ] && [ -w /dev/shm ]; then FUZZ_TMPDIR=/dev/shm; else FUZZ_TMPDIR="$OUT"; fi
fi
mkdir -p "$OUT"
TMPDIR=$(mktemp -d "$FUZZ_TMPDIR/ag2gs_fuzz_run.XXXXXX")
export TMPDIR
trap 'rm -rf "$TMPDIR"' EXIT
export UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1"
export ASAN_OPTIONS="detect_leaks=1:abort_on_error=1"

status=0
for t in "${TARGETS[@]}"; do
  case "$t" in
    fuzz_npy) dict=npy.dict ;;
    fuzz_ply) dict=ply.dict ;;
    fuzz_colmap_bin) dict=colmap_bin.dict ;;
    fuzz_colmap_txt) dict=colmap_txt.dict ;;
    fuzz_model) dict=model.dict ;;
    fuzz_json) dict=json.dict ;;
    *) echo "run_fuzzers: unknown target '$t'" >&2; exit 2 ;;
  esac
  mkdir -p "$OUT/$t/corpus" "$OUT/$t/findings"
  log="$OUT/$t/log-$(date +%Y%m%d-%H%M%S).txt"
  echo "== $t: ${SECONDS_PER_TARGET} s, log $log"
  # shellcheck disable=SC2086
  "$BUILD/fuzz/$t" "$OUT/$t/corpus" "$OUT/seeds/$t" -dict="$ROOT/fuzz/$dict" \
    -max_total_time="$SECONDS_PER_TARGET" -timeout=10 -rss_limit_mb=2048 -max_len=65536 \
    -artifact_prefix="$OUT/$t/findings/" -print_final_stats=1 ${FUZZ_ARGS:-} >"$log" 2>&1 || true
  grep -E "^stat::number_of_executed_units|^stat::peak_rss_mb" "$log" | sort -u || true
  found=$(find "$OUT/$t/findings" -type f | wc -l)
  if [ "$found" -ne 0 ]; then
    echo "   FINDINGS in $OUT/$t/findings:"; find "$OUT/$t/findings" -type f | sed 's/^/     /'
    echo "   (reproduce: $BUILD/fuzz/$t FILE; details in $log)"
    status=1
  fi
done
exit $status
