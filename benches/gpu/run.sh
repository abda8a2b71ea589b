#!/bin/bash
# springtime's CubeCL kernels on a GPU (wgpu over Vulkan) beside the PyTorch peer on CUDA, on
# the same machine and workload (32 x 32 cloth, 100 steps per clip), then flex on 2 threads.
#
# The GPU machine needs no Rust: build here, take the binary along.
#   cargo build --release --features autotune && mkdir -p .gpu && strip -o .gpu/springtime target/release/springtime
#   cp benches/gpu/* ../shared/bench/peer_torch.py .gpu/
#   (on the GPU machine, from the folder holding .gpu/) OUT=/some/dir bash .gpu/run.sh
# A machine without a Vulkan loader needs libvulkan1 (Debian/Ubuntu package); NVIDIA's ICD file
# is found through VK_DRIVER_FILES below where the driver is mounted under /usr/local/nvidia.
set -u
OUT=${OUT:-.}
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
[ -f "$icd" ] && export VK_DRIVER_FILES=$icd
S=${SPRINGTIME:-.gpu/springtime}
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
for B in ${BATCHES:-8 32 128 512}; do
  $S bench --backend wgpu --batch "$B" --steps 100 --iters 3 | grep '^{' | tee -a "$OUT/springtime_wgpu.jsonl"
  python3 .gpu/peer_cuda.py bench --B "$B" --T 100 --iters 3 | tail -1 | tee -a "$OUT/peer_cuda.jsonl"
done
RAYON_NUM_THREADS=2 $S bench --backend flex --batch 512 --steps 100 --iters 1 | grep '^{' | tee -a "$OUT/springtime_flex2.jsonl"
