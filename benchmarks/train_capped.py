"""ns-train with this process held to a GPU memory cap, as on a smaller GPU (the caching allocator refuses to hold
more than the cap, so a run that would not fit stops with nerfstudio's out-of-memory error where it would there).

    python benchmarks/train_capped.py CAP_GB ns-train-arguments...
    python benchmarks/train_capped.py 24 deform-splatfacto-real --data data/teddy --vis tensorboard

Used for benchmarks/results/real_memory_teddy_H200.json (a 24 GB GPU's budget on an H200).
"""

import sys

import torch

cap_gb = float(sys.argv[1])
total = torch.cuda.get_device_properties(0).total_memory
torch.cuda.set_per_process_memory_fraction(min(cap_gb * 2**30 / total, 1.0))

from nerfstudio.scripts.train import entrypoint  # noqa: E402 (after the cap, before any CUDA memory)

sys.argv = ["ns-train"] + sys.argv[2:]
entrypoint()
