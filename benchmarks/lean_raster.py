"""Per-frame cost of gsplat's `rasterization` wrapper against the lean path (same kernels).

Random Gaussians in front of an 800x800 pinhole camera, SH degree 3, one camera per frame as the
FPS protocol renders; each figure is the mean of synchronised frames after warm-up. Also the
largest pixel difference between the two paths.
    python benchmarks/lean_raster.py --output benchmarks/results/lean_raster.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from garo_ns.bench.benchmark import environment
from garo_ns.render.backend import rasterize


def frame_ms(fn, frames: int) -> float:
    for _ in range(20):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(frames):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return 1000.0 * sum(times) / len(times)


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--output", default="lean_raster.json")
    parser.add_argument("--frames", type=int, default=300)
    args = parser.parse_args()
    out = {**environment("cuda"), "width": 800, "height": 800, "sh_degree": 3, "frames": args.frames, "rows": []}
    g = torch.Generator().manual_seed(0)
    for n in (15_000, 50_000, 200_000):
        means = ((torch.rand(n, 3, generator=g) - 0.5) * 2.0).cuda()
        quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1).cuda()
        scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 4.5).cuda()
        opacities = torch.rand(n, generator=g).cuda()
        colors = (torch.randn(n, 16, 3, generator=g) * 0.3).cuda()
        viewmat = torch.eye(4)
        viewmat[2, 3] = 4.0
        viewmat = viewmat[None].cuda()
        K = torch.tensor([[[1111.0, 0.0, 400.0], [0.0, 1111.0, 400.0], [0.0, 0.0, 1.0]]]).cuda()
        bg = torch.zeros(1, 3, device="cuda")

        def call(lean: bool):
            return rasterize(
                means, quats, scales, opacities, colors, viewmat, K, 800, 800, sh_degree=3, backgrounds=bg, lean=lean
            )

        lean_rgb, lean_alpha, _ = call(True)
        diff = float((lean_rgb - call(False)[0]).abs().max())
        row = {
            "n_gaussians": n,
            "mean_alpha": float(lean_alpha.mean()),  # the cloud is in view (about 0.5 at 15k)
            "ms_wrapper": frame_ms(lambda: call(False), args.frames),
            "ms_lean": frame_ms(lambda: call(True), args.frames),
            "max_abs_rgb_diff": diff,
        }
        out["rows"].append(row)
        print(row, flush=True)
    with open(args.output, "w") as f:
        json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
