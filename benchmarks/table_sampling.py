"""Sampling the deformation field at a time table's keys: through its time sampler against one call per group of
times. `garo_ns.render.time_table.iter_field_offsets` samples a `DeformationField` through
`DeformationField.time_sampler` from `SAMPLER_TIMES` times on (the positions' share of the two layers that read the
encoding made once); before, every group of keys ran the whole field on repeated positions. Both ways here sample
the D-3DGS field (the recipe's shape: 8 layers of 256, the time network of 30) on `gaussians` random positions at
`keys` times, `repeats` times each in alternation; wall seconds (median), with the largest difference of the offsets.
On CUDA a third way samples through the time sampler with TF32 products (`time_table_tf32`,
`garo_ns.render.time_table.tf32_products`): its speed-up over fp32 and the largest difference it makes.

    python benchmarks/table_sampling.py --device cpu --output benchmarks/results/table_sampling_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from typing import Any, Dict, Tuple

import torch
from torch import Tensor, nn


class WholeField(nn.Module):
    """The field without its time sampler: every group of times runs the whole MLP on repeated positions."""

    times_per_row = True

    def __init__(self, field: nn.Module) -> None:
        super().__init__()
        self.field = field

    def forward(self, xyz: Tensor, time: Any) -> Tuple[Tensor, Tensor, Tensor]:
        return self.field(xyz, time)


def timed(field: Any, xyz: Tensor, times: list, tf32: bool = False) -> Tuple[float, Tensor]:
    from garo_ns.render.time_table import field_offsets, tf32_products

    if xyz.is_cuda:
        torch.cuda.synchronize()
    start = time.perf_counter()
    with tf32_products(tf32):
        out = field_offsets(field, xyz, times)
    if xyz.is_cuda:
        torch.cuda.synchronize()
    return time.perf_counter() - start, out


def main() -> None:
    from garo_ns.bench.benchmark import environment
    from garo_ns.deformation import DeformationField

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--gaussians", type=int, default=None, help="default: 34,000 on CUDA, 8,000 on a CPU")
    parser.add_argument("--keys", type=int, default=None, help="default: 1,000 on CUDA, 48 on a CPU")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    n = args.gaussians or (34_000 if cuda else 8_000)
    keys = args.keys or (1_000 if cuda else 48)
    torch.manual_seed(0)
    field = DeformationField(time_net=30).to(device).eval()
    xyz = (torch.rand(n, 3, device=device) * 2 - 1) * 1.5
    times = torch.linspace(0.0, 1.0, keys).tolist()
    ways: Dict[str, Tuple[Any, bool]] = {"whole_field": (WholeField(field), False), "time_sampler": (field, False)}
    if cuda:
        ways["time_sampler_tf32"] = (field, True)
    seconds: Dict[str, list] = {name: [] for name in ways}
    outs: Dict[str, Tensor] = {}
    with torch.no_grad():
        timed(field, xyz, times[:16])  # warm-up (libraries' handles)
        timed(field, xyz, times[:16], tf32=cuda)
        for _ in range(args.repeats):
            for name, (way, tf32) in ways.items():
                s, outs[name] = timed(way, xyz, times, tf32)
                seconds[name].append(s)
    median = {name: statistics.median(v) for name, v in seconds.items()}
    scale = float(outs["whole_field"].abs().max())
    result = {
        "environment": environment(device.type),
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "load_average": list(os.getloadavg()),
        "gaussians": n,
        "keys": keys,
        "seconds": seconds,
        "median_seconds": median,
        "ms_per_key": {name: 1000 * v / keys for name, v in median.items()},
        "speedup": median["whole_field"] / median["time_sampler"],
        "max_abs_difference": float((outs["whole_field"] - outs["time_sampler"]).abs().max()),
        "largest_offset": scale,
    }
    if "time_sampler_tf32" in median:
        result["speedup_tf32"] = median["time_sampler"] / median["time_sampler_tf32"]
        result["max_abs_difference_tf32"] = float((outs["time_sampler_tf32"] - outs["time_sampler"]).abs().max())
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    shown = ("median_seconds", "ms_per_key", "speedup", "max_abs_difference", "speedup_tf32", "max_abs_difference_tf32")
    print(json.dumps({k: result[k] for k in shown if k in result}))


if __name__ == "__main__":
    main()
