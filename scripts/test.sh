#!/usr/bin/env bash
# Installs what is missing, builds everything, and runs the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install_deps.sh --test
scripts/build.sh -DAG2GS_BUILD_TESTS=ON
cd build
ctest --output-on-failure -j"$(nproc)" "$@"
