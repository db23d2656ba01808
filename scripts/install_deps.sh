#!/usr/bin/env bash
# Installs the Debian packages ag2gs needs to build and test; does nothing
# when they are all present. Run as root or with sudo available.
set -euo pipefail

PACKAGES=(
  build-essential cmake pkg-config
  ocl-icd-opencl-dev opencl-headers opencl-clhpp-headers pocl-opencl-icd clinfo
  libeigen3-dev libopencv-dev libspdlog-dev libgtest-dev
  libcli11-dev nlohmann-json3-dev libcpp-httplib-dev
  colmap
  python3-dev pybind11-dev python3-numpy
)
# --test: also what the test suite needs beyond the build: clang with its
# libFuzzer and sanitizer runtimes (the fuzz smoke test), Oclgrind (the
# simulated GPU the oclgrind tests run every kernel on), and headless
# Chromium with its WebDriver and Selenium (the viewer's browser test),
# pytest (the Python module's test), and python3-venv (the venv that
# scripts/install_features.sh makes for the features test; scripts/test.sh
# runs it). The build itself includes the Python module (pybind11, Python's
# headers, NumPy for its arrays).
if [ "${1:-}" = "--test" ]; then
  PACKAGES+=(clang libclang-rt-14-dev oclgrind chromium chromium-driver python3-selenium python3-pytest python3-venv)
fi

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "install_deps: all ${#PACKAGES[@]} Debian packages present"
  exit 0
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "install_deps: need root (or sudo) to install: ${missing[*]}" >&2; exit 1; }
  SUDO=sudo
fi
echo "install_deps: installing ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
