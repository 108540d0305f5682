"""Micro-benchmark of the deformation field alone (issue 19): every candidate fast path against fp32 eager
and against the GPU's FLOP-rate limit, at N moving Gaussians.

The field is the current recipe's, built by `GaroModelConfig.make_deformation` from its defaults
(8 layers of 256 with the input re-injected after layer 4, a time network of 30 features). Its weights are
random, not trained: the hidden layers are He-initialised (activations keep their scale through the depth, as
a trained field's do; PyTorch's default initialisation shrinks them layer by layer) and the heads are scaled so
that position offsets are a few hundredths of the extent (the JSON records their size). Canonical positions
are uniform in the unit cube, so the scene extent is taken as 1.0 and `relative_error` is the largest absolute
difference of the position offset from fp32 eager, in units of that extent (rotation and log-scale offsets:
`rot_error`, `scale_error`, absolute). Errors are taken at one time (EVAL_TIME); the timed repeats cycle
through several times so that nothing can be reused between calls.

Paths (each one computes the three offsets at a time for all N Gaussians):
  fp32           the field as the product runs it (`DeformationField.forward`, position encoded every frame)
  fp16           half weights and activations (encoding computed in fp32, then rounded), the three heads as
                 one matrix product in fp32 (as the product's half field); cuBLAS accumulates in fp32 with
                 torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction=False
  <p>_cached     (p in fp32, fp16) the first layer and the skip layer split into a position part,
                 computed once per Gaussian (fixed until the parameters change; `prepare_ms`, `cache_mb`),
                 plus a time part that is one row per frame; exact up to float reassociation
  render_fp16    fp16_cached as the product runs it (`render_precision=fp16`: garo_ns.render.half_field.HalfField,
                 its parameter-version checks and its outputs cast back to fp32 included)
  <p>+graph      each of the above replayed as one CUDA graph (garo_ns.render.graphs.TimeGraph; CUDA only)
  compile        torch.compile(mode="max-autotune-no-cudagraphs") of the fastest eager path whose error is
                 within --compile-max-error (or of --compile-from; `compiled_from`, `compile_s`), and
                 compile+graph; CUDA only, skipped with the reason when compiling fails, when
                 TORCHDYNAMO_DISABLE is set, or when --compile-budget-s would be passed
tf32 and tf32_cached (TF32 tensor-core products of the fp32 field) were deleted with `render_precision=tf32`
(benchmarks/HISTORY.md); older result files still hold their rows.

Per N and path the JSON holds `ms` (median of synchronised repeats after warm-up, CUDA events on a GPU),
`speedup` (fp32 eager's ms over this one), `tflops` (the FLOPs the path executes, counted from the layer shapes,
over `ms`), `limit_ms` (those FLOPs at the GPU's dense peak for the path's precision) and `peak_fraction`;
`field_limit_ms` per N is the whole field at the dense 16-bit peak (the issue's yardstick). A path that cannot
run here is a row with `skipped` and the reason. Output: benchmarks/results/deform_mlp_<GPU>.json (GPU: H100,
H200, ..., or cpu) and a printed table.

    python benchmarks/deform_mlp.py                        # CUDA, N = 50k 10k 200k (in that order)
    python benchmarks/deform_mlp.py --device cpu --n 2000  # the CPU-capable paths (a test of the script)

Next GPU session: one call of the `run` (device) tool from a checkout that has the device kit (`.device/`, made
by ../shared/device/make-device-kit.sh; the prelude installs nerfstudio's wheels, which the recipe's config
imports, and puts the project root on PYTHONPATH). No scene and no gsplat compile are needed. Expected: under
3 minutes on a fresh machine (wheel install under a minute, every eager and graph path a few seconds, the rest
torch.compile's autotuning, which stops starting new compiles at --compile-budget-s 120):

    kind:      nvidia-h200            (the issue's numbers are an H200's; nvidia-h100-x1 for the H100 file)
    carry:     [".device"]
    timeout_s: 420
    command (one line):
      source .device/prelude.sh && timeout 400 python3 benchmarks/deform_mlp.py --output $OUT 2>&1 | tee $OUT/log

The product's half path alone (issue 31's yardstick: render_fp16 <= 0.25 ms at 50k on an H200):

      source .device/prelude.sh && timeout 360 python3 benchmarks/deform_mlp.py --no-compile
      --paths fp16_cached render_fp16 --output $OUT 2>&1 | tee $OUT/log

The result comes back as $OUT/deform_mlp_<GPU>.json (written after every N, so a cut-off run keeps what it
measured) with the log: copy the JSON to benchmarks/results/. Do not set TORCHDYNAMO_DISABLE (tests/conftest.py
and benchmarks/device_run.sh do; this script is not run through either).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

from garo_ns.deformation import DeformationField
from garo_ns.render.graphs import TimeGraph, graphs_available
from garo_ns.render.half_field import (
    FieldWeights,
    HalfField,
    PositionCache,
    cached_forward,
    fp32_accumulation,
    heads,
    time_features,
)

# Measured in this order (the target N first: the compile budget may run out); reported sorted.
NS = (50_000, 10_000, 200_000)
EVAL_TIME = 0.37
EXTENT = 1.0  # positions uniform in the unit cube
Offsets = Tuple[Tensor, Tensor, Tensor]
Step = Callable[[Any], Offsets]

# Dense (no 2:4 sparsity) peak rates in TFLOP/s, from NVIDIA's H100 and H200 datasheets, whose tensor-core
# figures are quoted with sparsity: halved here. SXM parts (the device tool's "NVIDIA H100 80GB HBM3",
# "NVIDIA H200"): FP32 66.9 (CUDA cores), FP16 989.4; PCIe and NVL parts are lower. Only the precisions the
# paths run in (TF32 and BF16 went with their deleted paths). First matching substring of
# torch.cuda.get_device_name() wins.
PEAKS: List[Tuple[str, Dict[str, float]]] = [
    ("H200 NVL", {"fp32": 60.0, "fp16": 835.5}),
    ("H200", {"fp32": 66.9, "fp16": 989.4}),
    ("H100 NVL", {"fp32": 60.0, "fp16": 835.5}),
    ("H100 PCIe", {"fp32": 51.2, "fp16": 756.5}),
    ("H100", {"fp32": 66.9, "fp16": 989.4}),
]


# HBM bandwidth in TB/s from the same datasheets (SXM: H100 3.35, H200 4.8), for the memory-bound limit of the
# per-layer breakdown; first matching substring wins.
BANDWIDTH_TBS: List[Tuple[str, float]] = [
    ("H200 NVL", 4.8),
    ("H200", 4.8),
    ("H100 NVL", 3.9),
    ("H100 PCIe", 2.0),
    ("H100", 3.35),
]


def bandwidth_for(device_name: str) -> Optional[float]:
    """HBM bandwidth (TB/s) for a device name, None when not in the table (a CPU)."""
    return next((bw for key, bw in BANDWIDTH_TBS if key in device_name), None)


def peaks_for(device_name: str) -> Optional[Dict[str, float]]:
    """The dense peak table's row for a device name (None: not in the table, e.g. a CPU)."""
    return next((row for key, row in PEAKS if key in device_name), None)


def gpu_tag(device_name: str) -> str:
    """H100, H200, ... from the device name (the result file's suffix); 'cpu' for the CPU."""
    if device_name == "cpu":
        return "cpu"
    match = re.search(r"\b([A-Z]{1,2}\d{2,4}[A-Za-z]?)\b", device_name)
    return match.group(1) if match else re.sub(r"[^A-Za-z0-9]+", "_", device_name).strip("_")


# --- the field ---------------------------------------------------------------------------------------------


def recipe_field() -> DeformationField:
    """The field of the current recipe: `GaroModelConfig().make_deformation()`, the model's own construction.
    Imports nerfstudio (the device kit's wheels on the GPU machine)."""
    from garo_ns.garo_model import GaroModelConfig

    return GaroModelConfig().make_deformation()


@torch.no_grad()
def trained_looking(field: DeformationField, seed: int = 0, offset_scale: float = 0.05) -> DeformationField:
    """Random weights with a trained field's scales: He-normal hidden layers (ReLU activations keep their size
    through the depth), small random biases, heads of standard deviation `offset_scale / sqrt(width)`."""
    g = torch.Generator().manual_seed(seed)
    hidden = list(field.layers)
    if field.time_net is not None:
        hidden += [m for m in field.time_net if isinstance(m, torch.nn.Linear)]
    for layer in hidden:
        layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) * math.sqrt(2.0 / layer.in_features))
        layer.bias.copy_(torch.randn(layer.bias.shape, generator=g) * 0.1)
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        head.weight.copy_(torch.randn(head.weight.shape, generator=g) * offset_scale / math.sqrt(head.in_features))
        head.bias.copy_(torch.randn(head.bias.shape, generator=g) * offset_scale * 0.1)
    return field


def layer_dims(field: DeformationField) -> Dict[str, int]:
    """Input widths of the field's MLP: position encoding, time features, hidden width, heads' outputs."""
    pos = 3 * (1 + 2 * field.pos_freqs)
    return {
        "pos": pos,
        "time": field.layers[0].in_features - pos,
        "width": field.layers[0].out_features,
        "heads": field.d_xyz.out_features + field.d_rot.out_features + field.d_scale.out_features,
    }


def flops_per_gaussian(field: DeformationField, cached: bool = False) -> int:
    """Multiply-add FLOPs (2 per weight) of the MLP and heads for one Gaussian, from the layer shapes. The
    time network runs on one row per frame and is not counted. `cached`: without the position parts of the
    first and the skip layer (computed once per Gaussian, not per frame)."""
    linears = list(field.layers) + [field.d_xyz, field.d_rot, field.d_scale]
    total = sum(2 * m.in_features * m.out_features for m in linears)
    if cached:
        d = layer_dims(field)
        n_split = 2 if field.skip + 1 < len(field.layers) else 1
        total -= n_split * 2 * (d["pos"] + d["time"]) * d["width"]
    return total


# --- the paths ---------------------------------------------------------------------------------------------


def plain_forward(w: FieldWeights, x: Tensor) -> Offsets:
    """The MLP on its full input `x` [N, F] with weights `w` (any dtype), heads as one product."""
    h = x
    for i, (weight, bias) in enumerate(w.layers):
        h = F.linear(h, weight, bias).relu_()
        if i == w.skip:
            h = torch.cat([x, h], dim=-1)
    return heads(w, h)


@dataclass
class PathSpec:
    """A deformation path: `build(field, xyz)` does the input-independent set-up once (not timed, except as
    `prepare_ms`) and returns the per-frame step `inner(time)`; `mode` is the matmul precision set around it."""

    name: str
    mode: str  # fp32 or fp16: the precision context and the peak rate it is held against
    cached: bool
    description: str

    def build(
        self, field: DeformationField, xyz: Tensor, a: Optional[argparse.Namespace] = None
    ) -> Tuple[Step, Dict[str, Any]]:
        device = xyz.device
        extra: Dict[str, Any] = {}
        if not self.cached and self.mode != "fp16":
            return (lambda t: field(xyz, t)), extra  # the product's forward
        if self.name == "render_fp16":  # the product's render_precision=fp16, checks and all
            half = HalfField(devices=(device.type,))
            half(field, xyz, EVAL_TIME, "points")  # builds its weight copies and position cache
            extra["cache_mb"] = round(half.cache_megabytes(), 4)
            return (lambda t: half(field, xyz, t, "points")), extra
        dtype = torch.float16 if self.mode == "fp16" else torch.float32
        w = FieldWeights.of(field, dtype)
        if not self.cached:
            return (lambda t: plain_forward(w, field.encode(xyz, t).to(dtype))), extra
        cache = PositionCache.build(field, xyz, dtype)
        extra["cache_mb"] = round(cache.megabytes(), 4)
        return (lambda t: cached_forward(w, cache, time_features(field, t, device))), extra

    @contextlib.contextmanager
    def context(self, device: torch.device) -> Iterator[None]:
        """The precision of the matrix products: fp32 as they are (`run` turns TF32 off), and for fp16 fp32
        accumulation in cuBLAS (no reduced-precision reduction)."""
        if self.mode != "fp16":
            yield
            return
        with fp32_accumulation():
            yield


def path_specs() -> List[PathSpec]:
    specs = [
        PathSpec("fp32", "fp32", False, "the product's forward in fp32 (reference)"),
        PathSpec("fp16", "fp16", False, "half weights and activations, fp32 accumulation, heads in fp32"),
    ]
    for base in list(specs):
        desc = f"{base.name} with the position parts of the first and skip layers cached per Gaussian"
        specs.append(PathSpec(base.name + "_cached", base.mode, True, desc))
    desc = "render_precision=fp16 as the frame path runs it (garo_ns.render.half_field.HalfField: fp16_cached)"
    specs.append(PathSpec("render_fp16", "fp16", True, desc))
    return specs


# --- measuring ---------------------------------------------------------------------------------------------


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_ms(call: Callable[[float], Any], device: torch.device, warmup: int, repeats: int) -> float:
    """Median wall time of `call(time)` in ms over `repeats` synchronised calls after `warmup` ones (CUDA
    events on a GPU); the time changes between calls so that nothing can be reused."""
    times = [(k % 16) / 15.0 for k in range(warmup + repeats)]
    for t in times[:warmup]:
        call(t)
    sync(device)
    samples = []
    for t in times[warmup:]:
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            call(t)
            end.record()
            end.synchronize()
            samples.append(start.elapsed_time(end))
        else:
            t0 = time.perf_counter()
            call(t)
            samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples)


def errors(out: Offsets, ref: Offsets) -> Dict[str, float]:
    """Largest absolute differences from the reference: position offset over EXTENT, rotation, log-scale."""
    diff = [float((a.float() - b.float()).abs().max()) for a, b in zip(out, ref)]
    return {"relative_error": diff[0] / EXTENT, "rot_error": diff[1], "scale_error": diff[2]}


def measure(
    label: str,
    spec: PathSpec,
    call: Callable[[float], Offsets],
    ref: Offsets,
    flops: float,
    peaks: Optional[Dict[str, float]],
    device: torch.device,
    a: argparse.Namespace,
) -> Dict[str, Any]:
    """One row: errors at EVAL_TIME, then the timing."""
    out = tuple(o.clone() for o in call(EVAL_TIME))  # graph outputs are overwritten by the next replay
    row: Dict[str, Any] = {"mode": spec.mode, **errors(out, ref)}  # type: ignore[arg-type]
    ms = median_ms(call, device, a.warmup, a.repeats)
    # Four significant digits: a tiny field on a busy CPU runs at well under a GFLOP/s.
    tflops = float(f"{flops / (ms * 1e-3) / 1e12:.4g}")
    row.update(ms=round(ms, 5), tflops=tflops, gflop=round(flops / 1e9, 4))
    if peaks is not None:
        limit = flops / (peaks[spec.mode] * 1e12) * 1e3
        row.update(limit_ms=round(limit, 5), peak_fraction=round(limit / ms, 4))
    print(f"  {label:<22} {ms:9.4f} ms  err {row['relative_error']:.2e}", flush=True)
    return row


def graph_call(step: Step, spec: PathSpec, device: torch.device) -> Callable[[float], Offsets]:
    """`step` replayed as one CUDA graph (captured on the first call, under the path's precision)."""
    graph = TimeGraph()

    def fn(t: Tensor) -> Offsets:
        with spec.context(device):
            return step(t)

    return lambda t: graph("deform", fn, t, device)


def compile_skip_reason(device: torch.device) -> Optional[str]:
    if device.type != "cuda":
        return "CUDA only (max-autotune tunes GPU kernels)"
    if os.environ.get("TORCHDYNAMO_DISABLE", "") not in ("", "0"):
        return "TORCHDYNAMO_DISABLE is set (torch.compile would return the function unchanged)"
    return None


def run(
    field: DeformationField,
    device: torch.device | str,
    ns: Sequence[int],
    a: argparse.Namespace,
    output: Optional[Path] = None,
    paths: Optional[Sequence[str]] = None,
    construction: str = "given",
) -> Dict[str, Any]:
    """Measure every path at every N; the result dictionary (also written to `output` after every N)."""
    device = torch.device(device)
    torch.backends.cuda.matmul.allow_tf32 = False  # fp32 means fp32, whatever the process set before
    field = field.to(device).eval()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    peaks = peaks_for(name)
    specs = [s for s in path_specs() if paths is None or s.name in paths or s.name == "fp32"]
    full_flops, cached_flops = flops_per_gaussian(field), flops_per_gaussian(field, cached=True)
    result: Dict[str, Any] = {
        "benchmark": "deform_mlp",
        "device": name,
        "gpu": gpu_tag(name),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "git_commit": git_commit(),
        "field": {
            "construction": construction,
            "depth": len(field.layers),
            "width": layer_dims(field)["width"],
            "skip": field.skip,
            "pos_freqs": field.pos_freqs,
            "time_freqs": field.time_freqs,
            "time_net": 0 if field.time_net is None else field.time_net[-1].out_features,
            "input_dims": layer_dims(field),
            "weights": "random, not trained: He-normal hidden layers, heads scaled to small offsets (seed "
            f"{a.seed}); positions uniform in the unit cube",
            "flops_per_gaussian": full_flops,
            "flops_per_gaussian_cached": cached_flops,
        },
        "extent": EXTENT,
        "eval_time": EVAL_TIME,
        "relative_error": "max |d_xyz - d_xyz(fp32 eager)| / extent at eval_time (extent 1.0: the unit cube)",
        "timing": {
            "statistic": "median",
            "warmup": a.warmup,
            "repeats": a.repeats,
            "clock": "torch.cuda.Event" if device.type == "cuda" else "time.perf_counter",
        },
        "peaks_tflops": peaks,
        "peaks_source": "NVIDIA H100/H200 datasheets, dense (tensor-core figures with sparsity halved)",
        "paths": {s.name: s.description for s in specs},
        "results": {},
    }
    budget = {"spent": 0.0, "last": 0.0}  # seconds compiling so far, and the last compile's
    for n in ns:
        print(f"N = {n}", flush=True)
        g = torch.Generator().manual_seed(a.seed + n)
        xyz = torch.rand(n, 3, generator=g).to(device)
        rows: Dict[str, Any] = {}
        with torch.no_grad():
            ref = tuple(o.clone() for o in field(xyz, EVAL_TIME))
            offset = ref[0].abs()
            per_n: Dict[str, Any] = {
                "mean_abs_d_xyz": float(offset.mean()),
                "max_abs_d_xyz": float(offset.max()),
                "field_limit_ms": (
                    round(full_flops * n / (peaks["fp16"] * 1e12) * 1e3, 5) if peaks is not None else None
                ),
            }
            steps: Dict[str, Tuple[PathSpec, Step]] = {}
            for spec in specs:
                flops = float((cached_flops if spec.cached else full_flops) * n)
                sync(device)
                t0 = time.perf_counter()
                step, extra = spec.build(field, xyz, a)
                sync(device)
                prepare_ms = (time.perf_counter() - t0) * 1e3

                def eager(t: float, spec: PathSpec = spec, step: Step = step) -> Offsets:
                    with spec.context(device):
                        return step(t)

                rows[spec.name] = measure(spec.name, spec, eager, ref, flops, peaks, device, a)
                if spec.cached:
                    rows[spec.name].update(prepare_ms=round(prepare_ms, 3), **extra)
                steps[spec.name] = (spec, step)
                label = spec.name + "+graph"
                if not graphs_available(device):
                    rows[label] = {"skipped": "CUDA graphs need a CUDA device"}
                    continue
                rows[label] = measure(label, spec, graph_call(step, spec, device), ref, flops, peaks, device, a)
                torch.cuda.empty_cache()
            compile_rows(rows, steps, field, ref, n, full_flops, cached_flops, peaks, device, a, budget)
            if n in (a.layers or []):
                per_n["layers"] = layer_breakdown(field, xyz, a, peaks, bandwidth_for(name))
        for row in rows.values():
            if "ms" in row and "ms" in rows["fp32"]:
                row["speedup"] = round(rows["fp32"]["ms"] / row["ms"], 3)
        result["results"][str(n)] = {**per_n, "paths": rows}
        result["results"] = {k: result["results"][k] for k in sorted(result["results"], key=int)}
        if output is not None:
            output.parent.mkdir(parents=True, exist_ok=True)
            output.write_text(json.dumps(result, indent=1) + "\n")
        del xyz, ref, steps
        if device.type == "cuda":
            torch.cuda.empty_cache()
    print_table(result)
    return result


def layer_breakdown(
    field: DeformationField, xyz: Tensor, a: argparse.Namespace, peaks: Optional[Dict[str, float]], bw: Optional[float]
) -> Dict[str, Any]:
    """Where fp16_cached's time goes (the product's fp16 path, cached_forward's stages in its order), each
    stage timed alone (median, CUDA events): its FLOPs, the bytes it must move through memory (inputs read,
    outputs written, weights once), and the time each would take at the tensor-core peak and at the HBM
    bandwidth. A stage near its larger limit cannot get much faster alone; the gap between the stages' sum and
    the whole path's time is what fusing them or a graph can still take."""
    device = xyz.device
    n = xyz.shape[0]
    half = torch.float16
    w = FieldWeights.of(field, half)
    cache = PositionCache.build(field, xyz, half)
    width = cache.first.shape[1]
    tfeat = time_features(field, EVAL_TIME, device).to(half)
    h = (cache.first + F.linear(tfeat, w.first_time)).relu_()
    e16, e32 = 2, 4  # bytes per element
    stages: List[Tuple[str, Callable[[float], Any], float, float, str]] = [
        # (stage, call, FLOPs, bytes, precision of the FLOPs' peak)
        ("time features (one row)", lambda t: time_features(field, t, device), 0.0, 0.0, "fp32"),
        (
            "layer 0: cached part + time row",
            lambda t: cache.first + F.linear(tfeat, w.first_time),
            0.0,
            2 * n * width * e16,
            "fp16",
        ),
        # in place on the layer's output, as the product runs it (idempotent, so it may repeat)
        ("relu (in place)", lambda t: h.relu_(), 0.0, 2 * n * width * e16, "fp16"),
    ]
    for i in range(1, len(w.layers)):
        if i == w.skip + 1 and w.skip_hidden is not None and cache.skip is not None:
            skip_hidden, skip = w.skip_hidden, cache.skip
            base = skip + F.linear(tfeat, w.skip_time)
            stages.append(
                (
                    f"layer {i}: skip cached part + time row",
                    lambda t, c=skip: c + F.linear(tfeat, w.skip_time),
                    0.0,
                    2 * n * width * e16,
                    "fp16",
                )
            )
            stages.append(
                (
                    f"layer {i}: addmm (hidden columns)",
                    lambda t, b=base, m=skip_hidden: torch.addmm(b, h, m.t()),
                    2.0 * n * width * width,
                    (3 * n * width + width * width) * e16,
                    "fp16",
                )
            )
        else:
            weight, bias = w.layers[i]
            stages.append(
                (
                    f"layer {i}: linear",
                    lambda t, m=weight, b=bias: F.linear(h, m, b),
                    2.0 * n * width * width,
                    (2 * n * width + width * width) * e16,
                    "fp16",
                )
            )
    n_heads = w.head_w.shape[0]
    stages += [
        ("heads: activations to fp32", lambda t: h.to(w.head_w.dtype), 0.0, n * width * (e16 + e32), "fp32"),
        (
            "heads: linear in fp32",
            lambda t, h32=h.float(): F.linear(h32, w.head_w, w.head_b),
            2.0 * n * width * n_heads,
            (n * width + n * n_heads) * e32,
            "fp32",
        ),
    ]
    relus = len(w.layers) - 1  # every layer has one; the first's is the stage timed, the others count with it
    rows = []
    with fp32_accumulation():
        for name, call, flops, nbytes, mode in stages:
            ms = median_ms(call, device, a.warmup, a.repeats)
            count = relus + 1 if name.startswith("relu") else 1
            row: Dict[str, Any] = {"stage": name, "ms": round(ms, 5), "count": count, "flops": flops, "bytes": nbytes}
            if peaks is not None and flops:
                row["compute_limit_ms"] = round(flops / (peaks[mode] * 1e12) * 1e3, 5)
            if bw is not None and nbytes:
                row["memory_limit_ms"] = round(nbytes / (bw * 1e12) * 1e3, 5)
            limits = [row[k] for k in ("compute_limit_ms", "memory_limit_ms") if k in row]
            if limits:
                row["bound"] = (
                    "compute" if row.get("compute_limit_ms", 0) >= row.get("memory_limit_ms", 0) else "memory"
                )
                row["fraction_of_limit"] = round(max(limits) / ms, 3)
            rows.append(row)
    total = sum(r["ms"] * r["count"] for r in rows)
    limit = sum(max(r.get("compute_limit_ms", 0), r.get("memory_limit_ms", 0)) * r["count"] for r in rows)
    return {
        "path": "fp16_cached (eager, each stage alone; the relu timed once and counted for every layer)",
        "stages": rows,
        "sum_ms": round(total, 5),
        "sum_of_limits_ms": round(limit, 5),
        "bandwidth_tbs": bw,
        "note": "bytes count activations read and written once per stage and the weights once; the limits "
        "assume the stage alone at the datasheet peak",
    }


def compile_rows(
    rows: Dict[str, Any],
    steps: Dict[str, Tuple[PathSpec, Step]],
    field: DeformationField,
    ref: Offsets,
    n: int,
    full_flops: int,
    cached_flops: int,
    peaks: Optional[Dict[str, float]],
    device: torch.device,
    a: argparse.Namespace,
    budget: Dict[str, float],
) -> None:
    """torch.compile of the fastest eager path within the error bound, alone and in a CUDA graph, guarded;
    `budget` counts the seconds spent compiling: no compile starts that the last one's duration would take past
    --compile-budget-s."""
    reason = compile_skip_reason(device)
    if reason is None and a.no_compile:
        reason = "--no-compile"
    if reason is None and budget["spent"] + budget["last"] > a.compile_budget_s:
        reason = (
            f"compile budget: {budget['spent']:.0f} s spent, the last compile took {budget['last']:.0f} s, "
            f"--compile-budget-s {a.compile_budget_s:.0f}"
        )
    # Not the product's path (render_fp16): it checks parameter versions in Python on every call, which is
    # no graph to compile.
    eligible = [
        k for k in steps if k != "render_fp16" and rows[k].get("relative_error", math.inf) <= a.compile_max_error
    ]
    if a.compile_from is not None:
        eligible = [k for k in steps if k == a.compile_from]
    if reason is None and not eligible:
        reason = (
            f"--compile-from {a.compile_from} did not run"
            if a.compile_from is not None
            else f"no eager path within --compile-max-error {a.compile_max_error:g}"
        )
    if reason is not None:
        rows["compile"] = rows["compile+graph"] = {"skipped": reason}
        return
    best = min(eligible, key=lambda k: rows[k]["ms"])
    spec, step = steps[best]
    flops = float((cached_flops if spec.cached else full_flops) * n)
    t0 = time.perf_counter()
    try:
        import torch._dynamo

        torch._dynamo.reset()
        compiled = torch.compile(step, mode="max-autotune-no-cudagraphs", dynamic=False)
        t_buf = torch.zeros((), device=device)

        def call(t: float) -> Offsets:
            t_buf.fill_(t)  # a tensor time: a Python float would be specialised (one compile per value)
            with spec.context(device):
                return compiled(t_buf)

        call(EVAL_TIME)  # compiles (and autotunes) here, outside the timing
        compile_s = time.perf_counter() - t0
        rows["compile"] = measure("compile", spec, call, ref, flops, peaks, device, a)
        rows["compile"].update(compiled_from=best, compile_s=round(compile_s, 1))
        rows["compile+graph"] = measure(
            "compile+graph", spec, graph_call(compiled, spec, device), ref, flops, peaks, device, a
        )
        rows["compile+graph"]["compiled_from"] = best
    except Exception as e:  # any compiler failure is a result, not a crash
        msg = f"{type(e).__name__}: {str(e).strip().splitlines()[0][:300] if str(e).strip() else ''}"
        for label in ("compile", "compile+graph"):
            rows.setdefault(label, {"skipped": f"torch.compile failed on {best}: {msg}"})
        print(f"  compile failed: {msg}", flush=True)
    budget["last"] = time.perf_counter() - t0
    budget["spent"] += budget["last"]


def print_table(result: Dict[str, Any]) -> None:
    print(f"\ndeformation field on {result['device']} (torch {result['torch']}); error: max |d_xyz| diff / extent")
    print(f"{'N':>8} {'path':<22} {'ms':>9} {'speedup':>8} {'TFLOP/s':>8} {'of peak':>8} {'rel err':>9}")
    for n, entry in result["results"].items():
        for label, row in entry["paths"].items():
            if "skipped" in row:
                print(f"{n:>8} {label:<22} skipped: {row['skipped']}")
                continue
            frac = f"{100 * row['peak_fraction']:.1f}%" if "peak_fraction" in row else "-"
            print(
                f"{n:>8} {label:<22} {row['ms']:9.4f} {row.get('speedup', 1.0):8.2f} {row['tflops']:8.2f} "
                f"{frac:>8} {row['relative_error']:9.2e}"
            )
        if entry.get("field_limit_ms") is not None:
            print(f"{n:>8} {'(limit at 16-bit peak)':<22} {entry['field_limit_ms']:9.4f}")
        layers = entry.get("layers")
        if layers:
            print(f"\n{n:>8} stage by stage ({layers['path']}):")
            for r in layers["stages"]:
                lim = max(r.get("compute_limit_ms", 0.0), r.get("memory_limit_ms", 0.0))
                bound = r.get("bound", "-")
                print(f"{'':>8} {r['stage']:<38} x{r['count']} {r['ms']:9.4f} ms  limit {lim:8.4f} ({bound})")
            print(f"{'':>8} {'sum':<38}    {layers['sum_ms']:9.4f} ms  limit {layers['sum_of_limits_ms']:8.4f}")


def git_commit() -> Optional[str]:
    marker = Path(".git-commit")
    if marker.exists():
        return marker.read_text().strip()
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--n", type=int, nargs="+", default=list(NS), help="numbers of moving Gaussians")
    p.add_argument("--paths", nargs="+", default=None, help="only these paths (fp32 always runs)")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-compile", action="store_true")
    p.add_argument(
        "--layers",
        type=int,
        nargs="*",
        default=[50_000],
        help="the N at which fp16_cached is broken down stage by stage against the tensor-core and\n"
        "memory-bandwidth limits (none: no breakdown)",
    )
    p.add_argument(
        "--compile-budget-s",
        type=float,
        default=120.0,
        help="seconds of compiling: no compile starts that the last one's duration would take past this",
    )
    p.add_argument(
        "--compile-max-error",
        type=float,
        default=5e-4,
        help="the largest relative_error of a path that may be compiled (1e-3 of the extent is\n"
        "some 0.8 px of an 800 px view across the extent; fp16 is about 1e-4)",
    )
    p.add_argument("--compile-from", default=None, help="compile this path instead of the fastest eligible one")
    p.add_argument("--output", default="benchmarks/results", help="a .json file, or a folder for deform_mlp_<GPU>.json")
    return p.parse_args(argv)


def output_path(arg: str, device: torch.device) -> Path:
    out = Path(arg)
    if out.suffix == ".json":
        return out
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    return out / f"deform_mlp_{gpu_tag(name)}.json"


def main(argv: Optional[Sequence[str]] = None) -> None:
    a = parse_args(argv)
    device = torch.device(a.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        sys.exit("CUDA is not available here: use --device cpu")
    field = trained_looking(recipe_field(), seed=a.seed)
    output = output_path(a.output, device)
    construction = "GaroModelConfig().make_deformation()"
    run(field, device, a.n, a, output=output, paths=a.paths, construction=construction)
    print(f"wrote {output}")


if __name__ == "__main__":
    main()
