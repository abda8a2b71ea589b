#!/bin/bash
# Where a model's training time goes on a GPU: CubeCL's profiler times every kernel of a short
# `springtime train` (CONFIG, by default Table 2 with 32 rollouts) and profsum.awk sums them by kernel name.
#   OUT=/some/dir MODEL=gnn|neural_ode|springs ITERS=6 bash .gpu/profile.sh
# Profiling waits on every kernel, so iterations run slower than unprofiled: take the rates
# from a plain run and the shares from this one. The second half of the log is summarised
# (the first holds the warm-up and, with `--features autotune`, the tuning).
set -u
OUT=${OUT:-.}
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f "$icd" ] && export VK_DRIVER_FILES=$icd
S=${SPRINGTIME:-.gpu/springtime}
M=${MODEL:-gnn}
C=${CONFIG:-configs/table2_fem.toml}
D=${DATA:-/tmp/table2_profile_data}
here=$(dirname "$0")
sets=(--set "data.dir=$D" --set source.train_rollouts=32 --set source.test_rollouts=1)
[ -d "$D" ] || "$S" generate "$C" "${sets[@]}" 2>&1 | tail -1
log=$(mktemp -d)/profile.log
[ -e cubecl.toml ] && { echo "cubecl.toml exists here: move it away first" >&2; exit 1; }
trap 'rm -f cubecl.toml' EXIT
printf '[profiling.logger]\nlevel = "basic"\nfile = "%s"\nappend = false\n' "$log" >cubecl.toml
case $M in
  gnn) it=(--set "train.gnn.iterations=${ITERS:-6}") ;;
  springs) it=(--set "train.stiffness.iterations=${ITERS:-6}" --set train.damping.iterations=0) ;;
  *) it=(--set "train.single.iterations=${ITERS:-2}") ;;
esac
"$S" train "$C" --backend wgpu --no-eval --out "$(mktemp -d)/run" "${sets[@]}" \
  --set "model.kind=$M" "${it[@]}" >"$OUT/${M}_train.log" 2>&1
echo "train rc $?"
rm -f cubecl.toml
n=$(grep -c '^| ' "$log")
grep '^| ' "$log" | tail -n $((n / 2)) | awk -f "$here/profsum.awk" >"$OUT/${M}_kernels.txt"
head -20 "$OUT/${M}_kernels.txt"
