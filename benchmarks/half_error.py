"""Where the fp16 deformation field's error comes from: `python benchmarks/half_error.py`.

The `render_precision` fp16 path (garo_ns.render.half_field) runs the field's hidden layers in half precision
with fp32 accumulation, the position parts cached per Gaussian, the heads in fp32. On 40k-step models it changed
the worst test view by 0.012 to 0.045 dB, around the 0.02 dB bound that keeps it off by default. This measures,
on a trained model (a benchmark export) and on a CPU, the offsets' error against the fp32 field when chosen
layers run in fp32 instead, and when the position cache is kept in fp32: if one stage made most of the error,
keeping it in fp32 would buy accuracy cheaply.

    python benchmarks/half_error.py --scene data/dnerf/jumpingjacks --exports EXPORT... \
        --output benchmarks/results/half_error_jumpingjacks_cpu.json

Errors are per Gaussian at each of `--times`: position offset as a fraction of the scene's extent (the diagonal
of the canonical means' bounding box), rotation offset (quaternion, Euclidean) and log-scale offset (largest
axis); the file keeps the largest and the root mean square over Gaussians and times.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Any, Callable, Dict, List

import torch
import torch.nn.functional as F

from garo_ns import compat
from garo_ns.bench import transfer
from garo_ns.render.half_field import FieldWeights, Offsets, PositionCache, heads, time_features

LayerDtype = Callable[[int], torch.dtype]


def mixed_forward(w: FieldWeights, cache: PositionCache, tfeat: torch.Tensor, layer_dtype: LayerDtype) -> Offsets:
    """The cached field (as `half_field.cached_forward` computes it, from fp32 weights `w`) with layer i in
    `layer_dtype(i)` and the heads in fp32; `cache` holds the position parts in the dtype they are kept in."""
    dtype = layer_dtype(0)
    h = (cache.first.to(dtype) + F.linear(tfeat.to(dtype), w.first_time.to(dtype))).relu_()
    for i in range(1, len(w.layers)):
        dtype = layer_dtype(i)
        h = h.to(dtype)
        if i == w.skip + 1:
            base = cache.skip.to(dtype) + F.linear(tfeat.to(dtype), w.skip_time.to(dtype))  # type: ignore[union-attr]
            h = torch.addmm(base, h, w.skip_hidden.t().to(dtype)).relu_()  # type: ignore[union-attr]
        else:
            weight, bias = w.layers[i]
            h = F.linear(h, weight.to(dtype), bias.to(dtype)).relu_()
    return heads(w, h.float())


def configurations(layers: int) -> Dict[str, tuple]:
    """Name -> (layer dtype, cache dtype): today's fp16 path, then one stage at a time kept in fp32."""
    half, full = torch.float16, torch.float32
    return {
        "fp16 (the render path)": (lambda i: half, half),
        "position cache fp32": (lambda i: half, full),
        "first 2 layers fp32": (lambda i: full if i <= 1 else half, half),
        "last layer fp32": (lambda i: full if i == layers - 1 else half, half),
        "last 2 layers fp32": (lambda i: full if i >= layers - 2 else half, half),
        "last 4 layers fp32": (lambda i: full if i >= layers - 4 else half, half),
    }


@torch.no_grad()
def offset_errors(field: Any, xyz: torch.Tensor, times: List[float]) -> Dict[str, Dict[str, float]]:
    """Per configuration: largest and RMS error of each offset against the fp32 field, over Gaussians and times."""
    extent = float((xyz.max(0).values - xyz.min(0).values).norm())
    w = FieldWeights.of(field, torch.float32)
    caches = {dtype: PositionCache.build(field, xyz, dtype) for dtype in (torch.float16, torch.float32)}
    sums: Dict[str, Dict[str, float]] = {}
    for t in times:
        tfeat = time_features(field, t, xyz.device)
        ref = mixed_forward(w, caches[torch.float32], tfeat, lambda i: torch.float32)
        for name, (layer_dtype, cache_dtype) in configurations(len(field.layers)).items():
            got = mixed_forward(w, caches[cache_dtype], tfeat, layer_dtype)
            errors = {
                "xyz_of_extent": (got[0] - ref[0]).norm(dim=-1) / extent,
                "rotation": (got[1] - ref[1]).norm(dim=-1),
                "log_scale": (got[2] - ref[2]).abs().amax(dim=-1),
            }
            row = sums.setdefault(name, {})
            for key, e in errors.items():
                row[f"{key}_max"] = max(row.get(f"{key}_max", 0.0), float(e.max()))
                row[f"{key}_ms"] = row.get(f"{key}_ms", 0.0) + float(e.double().pow(2).mean()) / len(times)
    out = {}
    for name, row in sums.items():
        out[name] = {k: v for k, v in row.items() if k.endswith("_max")}
        out[name].update({k[: -len("_ms")] + "_rms": v**0.5 for k, v in row.items() if k.endswith("_ms")})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--exports", type=Path, nargs="+", required=True, help="benchmark exports (--export-dir)")
    parser.add_argument("--times", type=float, nargs="+", default=[0.0, 0.3, 0.6, 0.9])
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    compat.install()
    from garo_ns.tools.eval import load_run

    torch.manual_seed(0)
    result: Dict[str, Any] = {"scene": args.scene.name, "times": args.times, "models": {}}
    for export in args.exports:
        with tempfile.TemporaryDirectory() as work:
            record = transfer.import_run(export, Path(work), args.scene)
            _, pipeline, _, step = load_run(Path(record["config"]))
            model = pipeline.model.eval()
            xyz = model.gauss_params["means"].detach().float()
            result["models"][record["variant"]] = {
                "step": step,
                "num_gaussians": int(xyz.shape[0]),
                "layers": len(model.deformation.layers),
                "errors": offset_errors(model.deformation, xyz, args.times),
            }
        for name, e in result["models"][record["variant"]]["errors"].items():
            print(
                f"{record['variant']:18s} {name:24s} xyz max {e['xyz_of_extent_max']:.2e} "
                f"rms {e['xyz_of_extent_rms']:.2e}  rotation max {e['rotation_max']:.2e}  "
                f"log-scale max {e['log_scale_max']:.2e}",
                flush=True,
            )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
