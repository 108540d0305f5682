"""The training loss's forward and backward alone on the GPU: the SSIM's convolutions against its fused kernels.

One [H, W, 3] render against its ground truth (splatfacto's `main_loss`: 0.8 L1 + 0.2 (1 - SSIM), the recipe's
lambda), the gradient taken to the render as in a training step; each way eager and replayed from the loss's CUDA
graph (`loss_cuda_graph`, garo_ns.engine.losses.ImageLoss). Device milliseconds per call from CUDA events around `calls`
back-to-back calls (the median of `repeats` such blocks), and the largest difference of the fused loss and
gradient from the convolutions'.

    python benchmarks/loss_speed.py --output benchmarks/results/loss_speed_<GPU>.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict

import torch


def main() -> None:
    from garo_ns.bench.benchmark import environment
    from garo_ns.bench.timing import device_ms
    from garo_ns.engine.losses import ImageLoss
    from garo_ns.engine.ssim import SSIM

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--height", type=int, default=800)
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("loss_speed.py times CUDA kernels: no GPU here")

    g = torch.Generator(device="cuda").manual_seed(0)
    gt = torch.rand(args.height, args.width, 3, device="cuda", generator=g)
    pred = (gt + 0.1 * torch.randn(gt.shape, device="cuda", generator=g)).clamp(0, 1).requires_grad_(True)
    rows: Dict[str, Dict[str, float]] = {}
    results = {}
    for fused in (False, True):
        for graphed in (False, True):
            loss = ImageLoss(SSIM(fused=fused).cuda(), 0.2, graphed=graphed)

            def step() -> None:
                pred.grad = None
                loss(gt, pred).backward()

            name = ("fused" if fused else "convolutions") + (" graphed" if graphed else " eager")
            rows[name] = {"ms_forward_backward": device_ms(step, args.calls, args.repeats)}
            pred.grad = None
            value = loss(gt, pred)
            value.backward()
            results[name] = (value.detach().clone(), pred.grad.detach().clone())
    ref_value, ref_grad = results["convolutions eager"]
    for name, (value, grad) in results.items():
        rows[name]["loss_difference"] = float((value - ref_value).abs())
        rows[name]["gradient_difference_relative"] = float((grad - ref_grad).abs().max() / ref_grad.abs().max())
    base = rows["convolutions graphed"]["ms_forward_backward"]
    for row in rows.values():
        row["speedup_vs_convolutions_graphed"] = base / row["ms_forward_backward"]
    out = {
        "environment": environment("cuda"),
        "image": [args.height, args.width, 3],
        "calls": args.calls,
        "repeats": args.repeats,
        "rows": rows,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(out, indent=2) + "\n")
    for name, row in rows.items():
        print(f"{name:22s} {row['ms_forward_backward']:.3f} ms  x{row['speedup_vs_convolutions_graphed']:.2f}")


if __name__ == "__main__":
    main()
