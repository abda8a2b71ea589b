"""The PyTorch peer (../shared/bench/peer_torch.py, copied beside this file) on CUDA.

Every tensor the peer creates goes to the GPU (torch.set_default_device), targets included,
and every timer reading waits for the GPU first (torch.cuda.synchronize), so its
`bench` mode times the same workload as on the CPU. Arguments are the peer's.
"""
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
torch.set_default_device("cuda")
_perf_counter = time.perf_counter


def synced_perf_counter():
    torch.cuda.synchronize()
    return _perf_counter()


time.perf_counter = synced_perf_counter

import peer_torch  # noqa: E402

if __name__ == "__main__":
    sys.argv[0] = peer_torch.__file__
    peer_torch.main()
