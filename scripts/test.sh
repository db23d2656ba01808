#!/usr/bin/env bash
# Installs what is missing, builds everything, and runs the whole test suite.
#   scripts/test.sh [--sanitize] [ctest arguments...]
# --sanitize: the same suite built with AddressSanitizer and
# UndefinedBehaviorSanitizer in build_sanitize/ (slower; any finding fails;
# the Python module, which would need ASan preloaded into Python, is left out).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install_deps.sh --test
# ag2gs-features and its PyTorch (about 3 GB from PyPI), for the features
# test (CTest label python). Should PyPI fail, the rest of the suite still
# runs and that entry says it was skipped, and why.
scripts/install_features.sh build/features-venv ||
  echo "test.sh: WARNING: ag2gs-features could not be installed; the features test will be skipped" >&2
if [ "${1:-}" = "--sanitize" ]; then
  shift
  cmake -S . -B build_sanitize -DCMAKE_BUILD_TYPE=RelWithDebInfo -DAG2GS_BUILD_TESTS=ON -DAG2GS_BUILD_BENCH=ON -DAG2GS_BUILD_PYTHON=OFF \
    -DAG2GS_SANITIZE=ON >/dev/null
  cmake --build build_sanitize -j"$(nproc)"
  cd build_sanitize
  # PoCL's compiler keeps process-lifetime allocations: leaks are not
  # findings here; every other error stops the test that hit it. The fuzz
  # smoke test has its own sanitizer build; the Oclgrind tests are left out
  # (Oclgrind preloads its OpenCL runtime ahead of ASan's, which ASan
  # refuses) and run in the plain suite.
  export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:${ASAN_OPTIONS:-}"
  export UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1:${UBSAN_OPTIONS:-}"
  ctest --output-on-failure -j"$(nproc)" -E fuzz_smoke -LE oclgrind "$@"
  exit
fi
scripts/build.sh -DAG2GS_BUILD_TESTS=ON
cd build
ctest --output-on-failure -j"$(nproc)" "$@"
