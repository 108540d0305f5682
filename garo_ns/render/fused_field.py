"""The deformation field at render time as one fused Triton kernel (CUDA; `render_precision=fp16-fused`).

Same arithmetic as `garo_ns.render.half_field.HalfField` (half weights and activations, fp32 accumulation,
the position parts of the first and the skip layer cached per Gaussian, the time parts one row a frame), but
a program takes a block of `block_m` Gaussians through every layer and the heads without writing an
activation to memory. Library GEMMs, one per layer, move every N x width activation to device memory and
back, which is what bounds HalfField.

How the layers are fused: layers are taken in pairs, like attention's two products. The first layer of a
pair is produced `block_n` output columns at a time from the pair's resident input h [block_m, width]
(h @ W_a[chunk].T, plus bias, ReLU, rounded to half); each chunk is at once multiplied into the second
layer's accumulator [block_m, width] (chunk @ W_b.T[chunk]), which holds the second layer's complete
pre-activation after the last chunk and becomes the next pair's input. So no activation is ever sliced
(Triton cannot index a register tile), only the weights are streamed, in [block_n, width] slices that the
compiler pipelines through shared memory (`num_stages`), and on-chip state is one input tile, one
accumulator and one chunk. The heads (3 + 4 + 3 outputs, zero-padded to 16 columns) are the second layer
of the last pair. Layer 0 has no product at all (cached position part plus the frame's time row): it is
the whole input of the first pair when the number of remaining layers plus heads is even, otherwise the
first layer of the first pair, produced chunk by chunk from the cache. The skip layer's hidden columns
are an ordinary product whose bias is replaced by the cached position part plus its time row.

Each layer's weights are stored in the layout its role reads contiguously: a pair's first layer as
[out, in] (its chunk is a block of rows, used transposed), its second as [in, out] (its chunk is a block
of rows of the transpose). The weight slices are the only global reads in the loop besides the caches;
all 7 x 128 KB of the recipe's weights stay in L2.

Budget of one program at the default config (block_m 64, block_n 64, width 256, 8 warps): registers hold
the fp32 accumulator (64 KB), the half input tile (32 KB, or shared memory if the compiler stages it
there) and one fp32 chunk (16 KB); shared memory holds `num_stages` x 2 weight slices of 32 KB each.
Compiled for sm_90 that is 172 KB of shared memory and 242 registers a thread, no spills, the products as
wgmma (benchmarks/fused_kernel_resources.py); see DEFAULT_CONFIG and TUNE_CONFIGS.

Triton is imported only when a kernel is first built (CUDA, or Triton's interpreter in the tests with
TRITON_INTERPRET=1); the CPU renders with the plain field. A frame is a handful of small torch ops (the
time row) and one launch with fixed shapes and no host synchronisation, so it is captured by the frame
path's CUDA graph like any other kernel.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

from garo_ns.deformation import DeformationField
from garo_ns.render.half_field import (
    HalfField,
    Offsets,
    PositionCache,
    has_skip,
    position_dims,
    split_heads,
    time_features,
)


@dataclass(frozen=True)
class FusedConfig:
    """Launch shape of the fused kernel: `block_m` Gaussians a program, weight slices of `block_n` rows
    (a multiple of 16 dividing the width), `num_warps` warps, `num_stages` weight slices in flight."""

    block_m: int = 64
    block_n: int = 64
    num_warps: int = 8
    num_stages: int = 2

    def for_width(self, width: int) -> "FusedConfig":
        """This config with `block_n` no wider than the layers (small test fields)."""
        return replace(self, block_n=min(self.block_n, width))


# The default launch shape, chosen from the static resources of the recipe's kernel compiled for sm_90
# (benchmarks/fused_kernel_resources.py; not yet timed on a GPU): 172 KB of shared memory (2 stages of two
# 64-row weight slices, 128 KB, plus the half input tile), 242 registers a thread and no spills, the products as
# wgmma. With 4 warps every config spills (the 64 x 256 fp32 accumulator alone is 128 registers a thread);
# 8 warps split its columns over two warpgroups. `autotune` (benchmarks/deform_mlp.py, row fused_tuned) times
# the alternatives below.
DEFAULT_CONFIG = FusedConfig(block_m=64, block_n=64, num_warps=8, num_stages=2)

# The alternatives `autotune` times, those that fit in an H100/H200's 227 KB of shared memory at the recipe's
# width (static compile for sm_90, KB of shared memory / registers / spilled bytes):
#   m64-n32-w4-s2   98 / 255 / 184     m64-n32-w8-s2  103 / 208 / 0     m128-n32-w8-s2  131 / 255 / 0
#   m64-n32-w4-s3  131 / 255 / 204     m64-n32-w8-s3  140 / 213 / 0     m128-n32-w8-s3  164 / 255 / 0
#   m64-n64-w4-s2  164 / 255 / 56      m64-n64-w8-s2  172 / 242 / 0     m128-n64-w8-s2  197 / 255 / 156
#   m64-n64-w4-s3  230 / 255 / 28
# (m64-n64-w8-s3 needs 246 KB, m128-n64-w8-s3 263 KB: they do not launch.) A block of 128 halves the weight
# traffic from L2 per Gaussian (every program streams all 7 x 128 KB of weights), which may matter more than
# its register pressure.
TUNE_CONFIGS: Tuple[FusedConfig, ...] = (
    FusedConfig(64, 32, 4, 2),
    FusedConfig(64, 32, 4, 3),
    FusedConfig(64, 64, 4, 2),
    FusedConfig(64, 64, 4, 3),
    FusedConfig(64, 32, 8, 2),
    FusedConfig(64, 32, 8, 3),
    DEFAULT_CONFIG,
    FusedConfig(128, 32, 8, 2),
    FusedConfig(128, 32, 8, 3),
    FusedConfig(128, 64, 8, 2),
)


def is_pow2(x: int) -> bool:
    """Whether `x` is a positive power of two."""
    return x > 0 and x & (x - 1) == 0


def supports(field: DeformationField) -> bool:
    """Whether the kernel takes this field: a power-of-two width of at least 16 (Triton's tiles have
    power-of-two sides; tensor-core products need 16)."""
    width = field.layers[0].out_features
    return is_pow2(width) and width >= 16


def heads_out(field: DeformationField) -> int:
    """Outputs of the three heads together (3 + 4 + 3)."""
    return field.d_xyz.out_features + field.d_rot.out_features + field.d_scale.out_features


def first_pair_layer(depth: int) -> int:
    """The first layer of the first pair: 1 when layers 1 .. depth-1 and the heads pair up exactly (depth
    even; layer 0 is then the first pair's whole input), else 0 (layer 0 produced chunk by chunk)."""
    return 1 - depth % 2


def is_pair_first(layer: int, depth: int) -> bool:
    """Whether `layer` (>= 1) is produced chunk by chunk (a pair's first layer) rather than accumulated."""
    return (layer - first_pair_layer(depth)) % 2 == 0


@dataclass
class FusedWeights:
    """The field's weights as the kernel reads them.

    `weights` [max(depth - 1, 1), width, width] half: layer i at index i - 1, as [out, in] when it is a
    pair's first layer, [in, out] when its second (the skip layer: its hidden columns only); `biases`
    [depth, width] fp32 (zero rows for layer 0 and the skip layer, whose biases are in the cache);
    `head_w` [width, heads_p] half and `head_b` [heads_p] fp32, the stacked heads zero-padded; `time_w`
    [2, width, T] fp32, the time columns of the first and the skip layer (zero without a skip layer)."""

    weights: Tensor
    biases: Tensor
    head_w: Tensor
    head_b: Tensor
    time_w: Tensor
    depth: int
    width: int
    skip_layer: int  # the layer reading the re-injected input; -1: none
    heads: int

    @classmethod
    @torch.no_grad()
    def of(cls, field: DeformationField) -> "FusedWeights":
        """The kernel's copies of `field`'s weights (on the field's device)."""
        layers = field.layers
        depth, width = len(layers), layers[0].out_features
        p, t = position_dims(field), layers[0].in_features
        device = layers[0].weight.device
        skip_layer = field.skip + 1 if has_skip(field) else -1
        mats = []
        for i in range(1, depth):
            w = layers[i].weight.detach().float()
            w = w[:, t:] if i == skip_layer else w  # the skip layer's hidden columns (after [pos, time])
            mats.append(w if is_pair_first(i, depth) else w.t())
        weights = torch.stack(mats) if mats else torch.zeros(1, width, width, device=device)
        biases = torch.zeros(depth, width, device=device)
        for i in range(1, depth):
            if i != skip_layer:
                biases[i] = layers[i].bias.detach().float()
        heads = (field.d_xyz, field.d_rot, field.d_scale)
        n_out = heads_out(field)
        heads_p = max(16, 1 << (n_out - 1).bit_length())
        head_w = torch.zeros(width, heads_p, device=device)
        head_w[:, :n_out] = torch.cat([h.weight.detach().float() for h in heads]).t()
        head_b = torch.zeros(heads_p, device=device)
        head_b[:n_out] = torch.cat([h.bias.detach().float() for h in heads])
        time_w = torch.zeros(2, width, t - p, device=device)
        time_w[0] = layers[0].weight.detach().float()[:, p:t]
        if skip_layer > 0:
            time_w[1] = layers[skip_layer].weight.detach().float()[:, p:t]
        return cls(
            weights=weights.half().contiguous(),
            biases=biases.contiguous(),
            head_w=head_w.half().contiguous(),
            head_b=head_b,
            time_w=time_w.contiguous(),
            depth=depth,
            width=width,
            skip_layer=skip_layer,
            heads=n_out,
        )

    def time_rows(self, tfeat: Tensor) -> Tensor:
        """The time parts [2, width] (fp32) of the first and the skip layer for time features `tfeat` [1, T]:
        an elementwise product and a sum, not a matrix product, so no TF32 setting can round it."""
        return (self.time_w * tfeat.reshape(1, 1, -1)).sum(-1)


def _interpret() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def triton_available() -> bool:
    """Whether Triton can be imported (it ships with torch's CUDA builds on Linux)."""
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


@functools.lru_cache(maxsize=None)
def build_kernel(interpret: bool) -> Any:
    """The Triton kernel, built on first use. `interpret`: for Triton's CPU interpreter. `triton.jit` reads
    TRITON_INTERPRET when a function is defined, and the interpreter runs a kernel's source in its module's
    namespace (adding names to it), so each setting loads its own copy of `fused_kernel.py`."""
    name = f"garo_ns.render._fused_kernel_{'interpreted' if interpret else 'compiled'}"
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name("fused_kernel.py"))
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    previous = os.environ.get("TRITON_INTERPRET")
    os.environ["TRITON_INTERPRET"] = "1" if interpret else "0"
    try:
        spec.loader.exec_module(module)  # type: ignore[union-attr]
    finally:
        if previous is None:
            del os.environ["TRITON_INTERPRET"]
        else:
            os.environ["TRITON_INTERPRET"] = previous
    return module.fused_field


def launch(
    w: FusedWeights, cache: PositionCache, tvec: Tensor, config: FusedConfig, out: Optional[Tensor] = None
) -> Tensor:
    """The heads' outputs [N, heads] (fp32) of the Gaussians in `cache`, with time rows `tvec` [2, width]."""
    n = cache.first.shape[0]
    out = torch.empty(n, w.heads, device=cache.first.device, dtype=torch.float32) if out is None else out
    if n == 0:
        return out
    c = config.for_width(w.width)
    kernel = build_kernel(_interpret())
    skip = cache.skip if cache.skip is not None else cache.first  # never read without a skip layer
    kernel[(triton_cdiv(n, c.block_m),)](
        cache.first,
        skip,
        tvec,
        w.weights,
        w.biases,
        w.head_w,
        w.head_b,
        out,
        n,
        WIDTH=w.width,
        DEPTH=w.depth,
        SKIP_LAYER=w.skip_layer,
        HEADS=w.heads,
        HEADS_P=w.head_w.shape[1],
        BLOCK_M=c.block_m,
        BLOCK_N=c.block_n,
        STAGES=c.num_stages,
        num_warps=c.num_warps,
        num_stages=c.num_stages,
    )
    return out


def triton_cdiv(a: int, b: int) -> int:
    return -(-a // b)


class FusedField(HalfField):
    """Render-time offsets of a `DeformationField` through the fused kernel: `HalfField`'s position cache
    (half, rebuilt on the same keys: the field's parameter versions and the caller's `points_key`), the
    kernel's own weight copies, and `config`'s launch shape. A field the kernel does not take (a width that
    is not a power of two) runs as HalfField does.

    `devices`: where it runs (CUDA by default, where Triton is installed); on the CPU only under Triton's
    interpreter (TRITON_INTERPRET=1, for tests), elsewhere the frame path keeps the plain fp32 field.
    """

    def __init__(self, config: Optional[FusedConfig] = None, devices: Sequence[str] = ("cuda",)):
        super().__init__(torch.float16, devices)
        self.config = DEFAULT_CONFIG if config is None else config

    def runs_on(self, device: torch.device) -> bool:
        """Whether this path is used on `device`: one of `devices`, Triton importable, and on a CPU only
        under the interpreter."""
        kind = torch.device(device).type
        return kind in self.devices and (kind == "cuda" or _interpret()) and triton_available()

    def copy_weights(self, field: DeformationField) -> Any:
        return FusedWeights.of(field) if supports(field) else super().copy_weights(field)

    def forward(
        self,
        field: DeformationField,
        weights: Any,
        cache: PositionCache,
        time: Union[float, Tensor],
        device: torch.device,
    ) -> Offsets:
        if not isinstance(weights, FusedWeights):
            return super().forward(field, weights, cache, time, device)
        tvec = weights.time_rows(time_features(field, time, device))
        return split_heads(launch(weights, cache, tvec, self.config))


@torch.no_grad()
def autotune(
    field: DeformationField,
    xyz: Tensor,
    configs: Sequence[FusedConfig] = TUNE_CONFIGS,
    repeats: int = 20,
    time: float = 0.5,
) -> Tuple[FusedConfig, Dict[str, Union[float, str]]]:
    """The fastest of `configs` for `field` on the Gaussians at `xyz` (CUDA), and every config's time: ms per
    launch (the median of 5 CUDA-event timings of `repeats` back-to-back launches, after a launch that
    compiles it), or the error for one that does not compile or run (e.g. out of shared memory)."""
    if xyz.device.type != "cuda":
        raise ValueError("autotune times CUDA kernels; the Gaussians must be on a CUDA device")
    w = FusedWeights.of(field)
    cache = PositionCache.build(field, xyz, torch.float16)
    tvec = w.time_rows(time_features(field, time, xyz.device))
    out = torch.empty(xyz.shape[0], w.heads, device=xyz.device)
    table: Dict[str, Union[float, str]] = {}
    best: Optional[Tuple[float, FusedConfig]] = None
    for config in configs:
        name = config_name(config)
        try:
            launch(w, cache, tvec, config, out)
            torch.cuda.synchronize(xyz.device)
            samples: List[float] = []
            for _ in range(5):
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                for _ in range(repeats):
                    launch(w, cache, tvec, config, out)
                end.record()
                end.synchronize()
                samples.append(start.elapsed_time(end) / repeats)
        except Exception as e:  # a config that does not compile (resources) is a result of the search
            table[name] = f"{type(e).__name__}: {str(e).strip().splitlines()[0][:200] if str(e).strip() else ''}"
            continue
        ms = sorted(samples)[len(samples) // 2]
        table[name] = round(ms, 5)
        if best is None or ms < best[0]:
            best = (ms, config)
    if best is None:
        raise RuntimeError(f"no fused kernel config ran: {table}")
    return best[1], table


def config_name(config: FusedConfig) -> str:
    """`m64-n64-w8-s2`: block_m, block_n, num_warps, num_stages."""
    return f"m{config.block_m}-n{config.block_n}-w{config.num_warps}-s{config.num_stages}"


def parse_config(name: str) -> FusedConfig:
    """The inverse of `config_name`."""
    parts = dict((p[0], int(p[1:])) for p in name.split("-"))
    return FusedConfig(parts["m"], parts["n"], parts["w"], parts["s"])
