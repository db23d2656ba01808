#!/usr/bin/env bash
# Packs a built tree (build/) with the shared libraries it needs into one
# archive, for a machine where Debian's packages cannot be installed (no
# network, another distribution): a GPU server, say. There, unpack it in a
# checkout of the same commit and run scripts/gpu_check.sh --no-build:
#
#   scripts/portable_bundle.sh [OUT.tar.xz]          # default out/bundle.tar.xz
#   # on the other machine, in the checkout:
#   mkdir -p /tmp/ag2gs_bundle && tar -C /tmp/ag2gs_bundle -xJf bundle.tar.xz
#   cp -a /tmp/ag2gs_bundle/build/. build/
#   sed -i "s#$OLD_CHECKOUT#$PWD#g" build/CTestTestfile.cmake   # when the paths differ
#   export LD_LIBRARY_PATH=/tmp/ag2gs_bundle/lib
#   echo /usr/lib/libnvidia-opencl.so.1 >/etc/OpenCL/vendors/nvidia.icd  # NVIDIA: where the driver put it
#   scripts/gpu_check.sh --no-build
#
# glibc, libstdc++ and libgcc stay out: the other machine's own (as new as
# Debian 12's or newer) are used. Debian's OpenCV pulls in GDAL, GDCM,
# FFmpeg, GStreamer, libdc1394, libgphoto2 and GLX (over 200 MB with their
# own dependencies) for image formats, cameras and video that ag2gs does not
# read; each is replaced by a small library of the same name that defines
# the symbols OpenCV imports as functions returning 0. Image files (PNG,
# JPEG, TIFF, WebP, OpenEXR, JPEG 2000) keep their real libraries. Video
# writing is then unavailable: set OPENCV_VIDEOIO_PRIORITY_FFMPEG=0 and
# OPENCV_VIDEOIO_PRIORITY_GSTREAMER=0 there, and `ag2gs simulate` writes
# frames without a video file.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/bundle.tar.xz}
[ -x build/ag2gs ] || { echo "portable_bundle: build/ag2gs is missing: run scripts/build.sh -DAG2GS_BUILD_TESTS=ON first" >&2; exit 1; }
for tool in gcc nm readelf ldd xz; do
  command -v $tool >/dev/null || { echo "portable_bundle: '$tool' is missing (apt-get install binutils gcc xz-utils)" >&2; exit 1; }
done

stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
mkdir -p "$stage/lib" "$stage/build"
libdir=/lib/x86_64-linux-gnu
stubbed="libgdal.so.32 libgdcmMSFF.so.3.0 libgdcmDSED.so.3.0 libdc1394.so.25 libgstbase-1.0.so.0
 libgstreamer-1.0.so.0 libgobject-2.0.so.0 libglib-2.0.so.0 libgstapp-1.0.so.0 libgstriff-1.0.so.0
 libgstpbutils-1.0.so.0 libgstvideo-1.0.so.0 libgstaudio-1.0.so.0 libgphoto2.so.6 libavformat.so.59
 libswscale.so.6 libavcodec.so.59 libavutil.so.57 libgphoto2_port.so.12 libGLX.so.0"

# stub LIB: $stage/lib/LIB defining what the OpenCV libraries import from it
# (with LIB's symbol versions, which the dynamic loader checks at start).
stub() {
  local lib=$1 real=$libdir/$1 s=$stage/stub.S v=$stage/stub.map
  : >"$s"
  : >"$v"
  nm -D --defined-only "$real" | awk '{print $3}' | sed 's/@.*//' | sort -u >"$stage/def.txt"
  : >"$stage/und.txt"
  for user in $libdir/libopencv_*.so.4*; do
    nm -D --undefined-only "$user" | awk '{print $2}' >>"$stage/und.txt"
    readelf -V "$user" | awk -v f="$lib" '/File:/ {cur = $5} /Name:/ && cur == f {print $3}' >>"$stage/vers.txt"
  done
  sort -u "$stage/vers.txt" | { grep . || true; } | while read -r ver; do echo "$ver { global: *; };" >>"$v"; done
  local syms
  syms=$( (sed 's/@.*//' "$stage/und.txt" | sort -u | comm -12 "$stage/def.txt" -
    if [ -s "$v" ]; then grep -h -F -f <(sed 's/ .*//; s/^/@/' "$v") "$stage/und.txt" | sed 's/@.*//'; fi) | sort -u)
  for sym in $syms; do printf '.globl %s\n.type %s,@function\n%s: xor %%eax, %%eax\nret\n' "$sym" "$sym" "$sym" >>"$s"; done
  local vs=()
  if [ -s "$v" ]; then vs=(-Wl,--version-script="$v"); fi
  gcc -shared -nostdlib -o "$stage/lib/$lib" -Wl,-soname,"$lib" "${vs[@]}" "$s"
  rm -f "$stage/vers.txt"
}
for lib in $stubbed; do
  if [ -e "$libdir/$lib" ]; then stub "$lib"; fi
done

bins=(build/ag2gs build/ag2gs_bench* build/test_*)
for b in "${bins[@]}"; do if [ -x "$b" ] && [ -f "$b" ]; then LD_LIBRARY_PATH=$stage/lib ldd "$b"; fi; done | awk '$3 ~ /^\// {print $3}' |
  sort -u | grep -v -E "/(libc|libm|libdl|libpthread|librt|libstdc\+\+|libgcc_s)\.so" | grep -v "^$stage/" |
  xargs -r cp -L -t "$stage/lib/"
for b in "${bins[@]}"; do if [ -x "$b" ] && [ -f "$b" ]; then cp "$b" "$stage/build/"; fi; done
strip "$stage"/build/* 2>/dev/null || true
[ -f build/CTestTestfile.cmake ] && cp build/CTestTestfile.cmake "$stage/build/"

# The bundle must start: the program against the bundled libraries alone.
if ! LD_LIBRARY_PATH=$stage/lib "$stage/build/ag2gs" --help >/dev/null 2>&1; then
  echo "portable_bundle: the bundled ag2gs does not start:" >&2
  LD_LIBRARY_PATH=$stage/lib "$stage/build/ag2gs" --help >&2 || true
  exit 1
fi
mkdir -p "$(dirname "$out")"
tar -C "$stage" -cf - lib build | xz -T0 -6 >"$out.tmp"
mv "$out.tmp" "$out"
echo "wrote $out ($(du -h "$out" | cut -f1)): $(ls "$stage/build" | wc -l) programs, $(ls "$stage/lib" | wc -l) libraries"
