#!/usr/bin/env bash
# Installs ag2gs-features (python/features/: SAM masks and CLIP features for
# the semantic stages) with its pinned packages into a Python venv; does
# nothing when that venv already holds this version of them.
#   scripts/install_features.sh [VENV]     (default build/features-venv)
# Then: VENV/bin/ag2gs-features --help (docs/usage.md). PyTorch comes from
# PyPI: its Linux wheel is the CUDA build (about 3 GB with its nvidia-*
# packages) and runs on the CPU as well.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-build/features-venv}"
src=python/features
# What decides the install: the pinned versions and the tool's sources.
want=$(cat "$src/pyproject.toml" "$src"/ag2gs_features/*.py | sha256sum | cut -d' ' -f1)
stamp="$venv/.ag2gs-features-installed"
if [ -x "$venv/bin/python" ] && [ "$(cat "$stamp" 2>/dev/null)" = "$want" ]; then
  echo "install_features: $venv already holds ag2gs-features and its packages"
  exit 0
fi
if [ ! -x "$venv/bin/python" ]; then
  python=/usr/bin/python3
  [ -x "$python" ] || python=python3
  "$python" -m venv "$venv" || {
    echo "install_features: cannot create the venv $venv; on Debian install python3-venv" >&2
    exit 1
  }
fi
echo "install_features: installing ag2gs-features and its pinned packages into $venv"
pip=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check --progress-bar off)
"${pip[@]}" "./$src[test]"
# pip may keep an installed copy of the same version: the tool itself is
# always replaced (its dependencies stay).
"${pip[@]}" --no-deps --force-reinstall "./$src"
echo "$want" >"$stamp"
echo "install_features: done; run $venv/bin/ag2gs-features --help"
