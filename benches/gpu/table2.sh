#!/bin/bash
# Paper-scale Table 2 on a GPU: generate configs/table2_fem.toml's rollouts (on the CPU cores),
# then `springtime compare` with every model on wgpu. Baseline iterations can be cut for a
# short lease (NODE_IT, GNN_IT; the config's are 256 and 2000): metrics.csv keeps the seconds
# of every iteration, so the full run's time follows from the cut one.
#
# Build here, take the binary along (see run.sh), then on the GPU machine:
#   OUT=/some/dir NODE_IT=64 GNN_IT=400 BUDGET=480 bash .gpu/table2.sh
# Extra `--set` pairs for every command go in SETS (e.g. for a dry run on lavapipe).
set -u -o pipefail
OUT=${OUT:-.}
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f "$icd" ] && export VK_DRIVER_FILES=$icd
S=${SPRINGTIME:-.gpu/springtime}
D=${DATA:-/tmp/table2_fem_data}
C=${CMP:-/tmp/table2_fem_compare}
sets=(--set "data.dir=$D")
for s in ${SETS:-}; do sets+=(--set "$s"); done
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
nproc
t0=$(date +%s)
$S generate configs/table2_fem.toml "${sets[@]}" 2>&1 | tail -2 || exit 1
t1=$(date +%s)
echo "generate: $((t1 - t0)) s"
timeout "${BUDGET:-480}" $S compare configs/table2_fem.toml --backend wgpu --out "$C" "${sets[@]}" \
  --set "train.single.iterations=${NODE_IT:-256}" --set "train.gnn.iterations=${GNN_IT:-2000}" \
  >"$OUT/compare.log" 2>&1
echo "compare: rc $? after $(($(date +%s) - t1)) s"
tail -25 "$OUT/compare.log"
(cd "$C" && tar czf "$OUT/table2_runs.tgz" --ignore-failed-read comparison.* */metrics.csv \
  */run.json */eval.json */config.toml 2>/dev/null)
ls -la "$OUT"
