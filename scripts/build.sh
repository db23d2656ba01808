#!/usr/bin/env bash
# Configures and builds ag2gs into build/ (the program lands at build/ag2gs).
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release "$@" >/dev/null
cmake --build build -j"$(nproc)"
