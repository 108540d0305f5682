"""Reference rasterizer against gsplat's CUDA rasterizer on a real scene's cameras (GPU machine).

A random cloud of Gaussians in [-1.3, 1.3]^3 (the 3DGS synthetic init cube) is rendered through
each camera of a D-NeRF scene with both rasterizers; we report the largest absolute RGB difference
and the relative error of the means2d gradients, ||g_ref - g_cuda|| / ||g_cuda||, over all Gaussians
visible in both, for the same loss.

Views with identical poses render identical images (the static cloud ignores time; lego's val split
is one pose at 11 times), so each distinct pose is compared once.

Both rasterizers skip a Gaussian at a pixel when its alpha is below 1/255. Their alphas agree to
float rounding, not bit for bit (CUDA's fast exp, fused multiply-adds), so a Gaussian whose alpha
sits on the threshold can be kept by one and skipped by the other: a jump of up to 1/255 times its
colour at that pixel. To tell such flips from real disagreements, the reference also renders with
the threshold moved by +-band (relative); a CUDA value inside the span of the three renders is
explained by a flip, and `max_abs_rgb_diff_beyond_threshold_band` is the largest distance of a CUDA
value from that span.

    python benchmarks/rasterizer_parity.py --scene .scenes/lego --split test --n 50000 \
        --output benchmarks/results/rasterizer_parity.json
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from garo_ns.data.dnerf import read_split
from garo_ns.render.reference import ALPHA_MIN
from garo_ns.render.reference import rasterize as reference
from garo_ns.render.view import viewmat_from_c2w


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--n", type=int, default=50_000)
    p.add_argument("--views", type=int, default=0, help="0 = all views of the split")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--band", type=float, default=1e-4, help="relative shift of the 1/255 alpha threshold")
    p.add_argument("--output", type=Path, default=Path("benchmarks/results/rasterizer_parity.json"))
    a = p.parse_args()

    from gsplat import rasterization

    dev = torch.device("cuda")
    g = torch.Generator().manual_seed(a.seed)
    n = a.n
    means = ((torch.rand(n, 3, generator=g) * 2 - 1) * 1.3).to(dev)
    quats = torch.randn(n, 4, generator=g).to(dev)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.003), math.log(0.04), generator=g)).to(dev)
    opac = (torch.rand(n, generator=g) * 0.9 + 0.05).to(dev)
    sh = (torch.randn(n, 16, 3, generator=g) * 0.3).to(dev)
    paths, poses, times, angle, (h, w) = read_split(a.scene, a.split)
    focal = 0.5 * w / math.tan(0.5 * angle)
    K = torch.tensor([[focal, 0, w / 2], [0, focal, h / 2], [0, 0, 1.0]], device=dev)[None]
    _, distinct = torch.from_numpy(poses[:, :3]).round(decimals=6).flatten(1).unique(dim=0, return_inverse=True)
    first = sorted({int(torch.nonzero(distinct == i)[0]) for i in distinct.unique()})
    views = viewmat_from_c2w(torch.from_numpy(poses[first, :3]).float().to(dev))
    if a.views:
        views = views[: a.views]
    weight = torch.rand(1, h, w, 3, generator=g).to(dev)  # a generic linear loss on the image

    rgb_diff, alpha_diff, num, den, n_visible, t_ref, t_cuda = 0.0, 0.0, 0.0, 0.0, 0, 0.0, 0.0
    over, pixels, sum_diff, worst, worst_pixels = 0, 0, 0.0, [], []
    beyond_band, over_beyond_band, beyond_pixels = 0.0, 0, []
    for v in range(views.shape[0]):
        outs = {}
        for name in ("cuda", "reference"):
            m = means.clone().requires_grad_()
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            kwargs = dict(sh_degree=3, backgrounds=torch.zeros(1, 3, device=dev))
            if name == "cuda":
                img, alpha, info = rasterization(
                    m, quats, scales, opac, sh, views[v : v + 1], K, w, h, packed=False, **kwargs
                )
            else:
                img, alpha, info = reference(m, quats, scales, opac, sh, views[v : v + 1], K, w, h, **kwargs)
            info["means2d"].retain_grad()
            (img * weight).sum().backward()
            torch.cuda.synchronize()
            dt = time.perf_counter() - t0
            if name == "cuda":
                t_cuda += dt
            else:
                t_ref += dt
            outs[name] = (img.detach(), alpha.detach(), info["means2d"].grad.detach(), info["radii"])
        (ic, ac, gc, rc), (ir, ar, gr, rr) = outs["cuda"], outs["reference"]
        with torch.no_grad():
            cam = views[v : v + 1]
            shifted = [
                reference(means, quats, scales, opac, sh, cam, K, w, h, alpha_min=ALPHA_MIN * f, **kwargs)[0]
                for f in (1 - a.band, 1 + a.band)
            ]
        span = torch.stack([ir, *shifted])
        excess = (torch.relu(span.amin(0) - ic) + torch.relu(ic - span.amax(0))).amax(-1)
        beyond_band = max(beyond_band, float(excess.max()))
        over_beyond_band += int((excess > 1e-3).sum())
        diff = (ic - ir).abs().amax(-1).flatten()
        rgb_diff = max(rgb_diff, float(diff.max()))
        over += int((diff > 1e-3).sum())
        pixels += diff.numel()
        sum_diff += float(diff.sum())
        worst.append(diff.topk(min(100, diff.numel())).values.cpu())
        top_excess = excess.flatten().topk(3)
        for value, index in zip(top_excess.values.tolist(), top_excess.indices.tolist()):
            if value > 0:
                y, x = divmod(index, w)
                beyond_pixels.append(
                    {
                        "view": v,
                        "x": x,
                        "y": y,
                        "beyond_threshold_band": value,
                        "diff": float(diff[index]),
                        "rgb_cuda": ic[0, y, x].tolist(),
                        "rgb_reference": ir[0, y, x].tolist(),
                        "rgb_reference_band": [r[0, y, x].tolist() for r in shifted],
                    }
                )
        # Where the largest differences sit, to tell rounding at a threshold from a systematic cause.
        top = diff.topk(3)
        for value, index in zip(top.values.tolist(), top.indices.tolist()):
            y, x = divmod(index, w)
            worst_pixels.append(
                {
                    "view": v,
                    "x": x,
                    "y": y,
                    "diff": value,
                    "rgb_cuda": ic[0, y, x].tolist(),
                    "rgb_reference": ir[0, y, x].tolist(),
                    "alpha_cuda": float(ac[0, y, x]),
                    "alpha_reference": float(ar[0, y, x]),
                    "beyond_threshold_band": float(excess.flatten()[index]),
                }
            )
        alpha_diff = max(alpha_diff, float((ac - ar).abs().max()))
        both = (rc > 0) & (rr > 0)
        n_visible += int(both.sum())
        num += float(((gr - gc)[both] ** 2).sum())
        den += float((gc[both] ** 2).sum())
        print(f"view {v}: max |rgb diff| so far {rgb_diff:.2e}, radii equal: {bool(torch.equal(rc, rr))}")
    result = {
        "gpu": torch.cuda.get_device_name(0),
        "torch": torch.__version__,
        "scene": a.scene.name,
        "split": a.split,
        "views": int(views.shape[0]),
        "views_in_split": int(poses.shape[0]),
        "n_gaussians": n,
        "width": w,
        "height": h,
        "max_abs_rgb_diff": rgb_diff,
        "max_abs_alpha_diff": alpha_diff,
        "means2d_grad_rel_err": math.sqrt(num / max(den, 1e-30)),
        "pixels": pixels,
        "pixels_rgb_diff_over_1e-3": over,
        "mean_abs_rgb_diff": sum_diff / max(pixels, 1),
        "threshold_band_relative": a.band,
        "max_abs_rgb_diff_beyond_threshold_band": beyond_band,
        "pixels_rgb_diff_over_1e-3_beyond_threshold_band": over_beyond_band,
        "largest_100_rgb_diffs": [round(float(x), 6) for x in torch.cat(worst).topk(100).values],
        "worst_pixels_per_view": worst_pixels,
        "largest_beyond_threshold_band": sorted(beyond_pixels, key=lambda p: -p["beyond_threshold_band"])[:20],
        "visible_pairs": n_visible,
        "seconds_reference_fwd_bwd_per_view": t_ref / views.shape[0],
        "seconds_cuda_fwd_bwd_per_view": t_cuda / views.shape[0],
        "targets": {"max_abs_rgb_diff": 1e-3, "means2d_grad_rel_err": 1e-2},
    }
    a.output.parent.mkdir(parents=True, exist_ok=True)
    a.output.write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
