#!/bin/bash
# One device call: the blend backward plan sweep (ag2gs_bench per plan), then side_by_side.sh with the
# fastest plan, then the GPU renders of the test views and the model for a comparison on PoCL elsewhere.
# Run ON the device machine from the folder side_by_side.sh describes (bundle, gsplat wheel, fox_half/):
#   OUT=results bash gpu_payload/blend_bwd_plans.sh
set -u
here=$(cd "$(dirname "$0")" && pwd)
O=${OUT:-/tmp/out}; mkdir -p "$O"
W=/tmp/w; mkdir -p $W
T0=$(date +%s)
S="$O/sweep.txt"; : >"$S"
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$here"/gsplat-*.whl >"$W/pip0.txt" 2>&1
( export PYTHONPATH=/tmp/site; TORCH_CUDA_ARCH_LIST=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())") MAX_JOBS=14 \
  python3 -c "from gsplat.cuda._backend import _C" >"$W/gsplat_prebuild.txt" 2>&1 ) &
mkdir -p /tmp/ag2gs_bundle && tar -C /tmp/ag2gs_bundle -xJf "$here/bundle.tar.xz"
export LD_LIBRARY_PATH=/tmp/ag2gs_bundle/lib
mkdir -p /etc/OpenCL/vendors; [ -e /etc/OpenCL/vendors/nvidia.icd ] || echo libnvidia-opencl.so.1 >/etc/OpenCL/vendors/nvidia.icd
A=/tmp/ag2gs_bundle/build
echo "setup at $(( $(date +%s) - T0 )) s" >>"$S"
for plan in 1:2:1 1:2:8 1:2:4 1:2:16 2:4:4 2:4:8 4:8:1 4:8:2 4:8:4 8:16:1; do
  echo "== plan $plan" >>"$S"
  AG2GS_BLEND_BWD=$plan timeout 60 $A/ag2gs_bench --device 0 --counts 100000 1000000 --sizes 800x600 1920x1080 \
    --repeats 5 --sample-pixels 4 2>&1 | grep -E '^\| [0-9]|device|rror' >>"$S"
done
echo "sweep done at $(( $(date +%s) - T0 )) s" >>"$S"
# Best plan: smallest sum of the fwd+bwd column over the four rows.
best=$(awk '/^== plan/ {p=$3} /^\| [0-9]/ {split($0, f, "|"); s[p] += f[7]; n[p]++}
  END {b=""; for (p in s) if (n[p] == 4 && (b == "" || s[p] < s[b])) b = p; print b}' "$S")
echo "best plan: $best" >>"$S"
[ -n "$best" ] && export AG2GS_BLEND_BWD=$best
OUT=$W bash "$here/side_by_side.sh" --iters 7000 "$here/fox_half" -r 1 >"$W/sbs_stdout.txt" 2>&1
cp $W/side_by_side.md "$O/" 2>/dev/null
echo "side by side done at $(( $(date +%s) - T0 )) s" >>"$S"
# GPU renders of the test views of the GPU-trained model, for a PoCL comparison elsewhere.
mkdir -p /tmp/pack
$A/ag2gs render /tmp/ag_fox_half1 --scene "$here/fox_half" --views test -o /tmp/pack/gpu_renders --device 0 >"$W/render.txt" 2>&1 || true
cp /tmp/ag_fox_half1/model.ag2gs /tmp/ag_fox_half1/metrics.json /tmp/pack/ 2>/dev/null
# In pieces under the 16 MiB a returned file may have (cat fox_gpu.tar.xz.* | tar -xJ).
tar -C /tmp/pack -cf - . | xz -1 -T8 | split -b 15M - "$O/fox_gpu.tar.xz."
tar -C $W -cJf "$O/logs.tar.xz" . 
echo "all done at $(( $(date +%s) - T0 )) s" >>"$S"
