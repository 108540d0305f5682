"""The deformation field's training forward and backward alone on the GPU: torch's layers against the fused ones.

The recipe's field (8 x 256, skip after layer 4, the time network) on `n` random Gaussians at one time, the offsets
weighed by fixed random coefficients and the gradient taken to every parameter, as in a training step; under bf16
autocast (`deform_train_bf16`, the recipe) and in fp32. Each way eager and replayed from a CUDA graph (training's
path, `deform_cuda_graph`): device milliseconds per call from CUDA events around `calls` back-to-back calls (the
median of `repeats` blocks). Every row's offsets and gradients are compared with the plain field's in fp32 (norm of
the difference over the norm), so the fused layers' error shows beside bf16's own.

    python benchmarks/field_layers.py --output benchmarks/results/field_layers_<GPU>.json
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import Dict, List, Sequence

import torch
from torch import Tensor


def relative(a: Sequence[Tensor], b: Sequence[Tensor]) -> float:
    """|a - b| / |b| over the concatenation of each list's tensors."""
    x = torch.cat([t.float().flatten() for t in a])
    y = torch.cat([t.float().flatten() for t in b])
    return float((x - y).norm() / y.norm())


def markdown(result: Dict) -> str:
    lines = [
        f"The deformation field's forward and backward, {result['environment'].get('gpu')}: device ms per call "
        f"(median of {result['repeats']} blocks of {result['calls']}); error = |x - x_ref| / |x_ref| against the "
        "plain field in fp32 eager, for the offsets and for the parameters' gradients",
        "",
        "| Gaussians | precision | layers | eager ms | graphed ms | vs torch | offsets error | gradients error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['gaussians']:,} | {row['precision']} | {row['layers']} | {row['eager_ms']:.3f} | "
            f"{row['graphed_ms']:.3f} | x{row['graphed_speedup_vs_plain']:.2f} | {row['offsets_error']:.1e} | "
            f"{row['gradients_error']:.1e} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    from garo_ns.bench.benchmark import environment
    from garo_ns.bench.results import utc_stamp, write_with_table
    from garo_ns.bench.timing import device_ms
    from garo_ns.deformation import DeformationField

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, nargs="+", default=[60_000, 190_000])
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("field_layers.py times CUDA kernels: no GPU here")

    rows: List[Dict] = []
    for n in args.gaussians:
        g = torch.Generator(device="cuda").manual_seed(0)
        xyz = torch.randn(n, 3, device="cuda", generator=g)
        time = torch.full((1, 1), 0.37, device="cuda")
        torch.manual_seed(0)
        plain = DeformationField(time_net=30).cuda()
        fused = DeformationField(time_net=30, fused_layers=True).cuda()
        fused.load_state_dict(plain.state_dict())
        coefs = [torch.randn(n, k, device="cuda", generator=g) for k in (3, 4, 3)]

        def forward_backward(field: DeformationField, bf16: bool) -> List[Tensor]:
            autocast = torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False)
            with autocast if bf16 else contextlib.nullcontext():
                offsets = field(xyz, time)
            loss = sum((o.float() * c).sum() for o, c in zip(offsets, coefs))
            return [o.detach() for o in offsets] + list(torch.autograd.grad(loss, list(field.parameters())))

        reference = forward_backward(plain, False)
        for bf16 in (True, False):
            base_ms = None
            for name, field in (("torch", plain), ("fused", fused)):
                result = forward_backward(field, bf16)
                row = {
                    "gaussians": n,
                    "precision": "bf16" if bf16 else "fp32",
                    "layers": name,
                    "offsets_error": relative(result[:3], reference[:3]),
                    "gradients_error": relative(result[3:], reference[3:]),
                    "eager_ms": device_ms(lambda: forward_backward(field, bf16), args.calls, args.repeats),
                }
                stream = torch.cuda.Stream()
                stream.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(stream):
                    for _ in range(3):
                        forward_backward(field, bf16)
                torch.cuda.current_stream().wait_stream(stream)
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph):
                    forward_backward(field, bf16)
                row["graphed_ms"] = device_ms(graph.replay, args.calls, args.repeats)
                base_ms = base_ms or row["graphed_ms"]
                row["graphed_speedup_vs_plain"] = base_ms / row["graphed_ms"]
                rows.append(row)
                del graph
    result = {
        "date": utc_stamp(),
        "environment": environment("cuda"),
        "calls": args.calls,
        "repeats": args.repeats,
        "rows": rows,
    }
    write_with_table(result, markdown, args.output)


if __name__ == "__main__":
    main()
