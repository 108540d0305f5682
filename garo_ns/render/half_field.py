"""The deformation field at render time: half-precision weights, the per-Gaussian part cached.

The field's first layer and its skip layer read [position encoding, time features]. Their products
split into a position part, fixed per Gaussian until the means or the weights change, and a time
part, one row per frame. `HalfField` computes the position parts once (in fp32, stored in half) and
then runs every frame as half-precision matrix products with fp32 accumulation: the two split
layers become an addition of one row, the three heads one product, kept in fp32 (`head_dtype`). The
heads write the offsets themselves: in half, their weights' and outputs' rounding (11 bits) lands on
every position unattenuated, while in fp32 they cost 10 of the field's ~1M FLOPs per Gaussian. Issue
#31 measured fp16 with half heads at 0.030 dB from the plain render on standup's worst test view, over
the 0.02 dB bound. With the fp32 heads, at 40k steps on an H100 (`+half` rows, worst test view against
the plain render; benchmarks/results/): mutant 0.0108 dB (baseline) and 0.0116 (GARO)
(mutant40k_switches_H100.json), jumpingjacks 0.0202 and 0.0124 (table1_jumpingjacks_run2_H100.json),
standup's GARO arm 0.045 (standup40k_garo_switches_H100.json). Within the 0.02 dB bound on mutant and
jumpingjacks' GARO arm, over it on standup and by 0.0002 dB on jumpingjacks' baseline: `render_precision`
fp16 is an explicit opt-in, never chosen by default (garo_ns.render.switches).

Chosen by a micro-benchmark of the field alone (`benchmarks/results/deform_mlp_H100.json`, its script
retired: benchmarks/HISTORY.md; the recipe's field, 50k / 200k moving Gaussians, ms per frame): fp32
1.93 / 6.98; tf32 (since deleted) + CUDA graph 0.94 / 3.50; half weights + graph 0.51 / 2.26; half
weights with the position part cached + graph (this) 0.44 / 1.68, largest position-offset error 1.6e-4
of the scene extent (bf16: 1.3e-3). torch.compile + graph is a little faster (0.40 / 1.33) but autotunes
for minutes at the first frame (and, compiled for fixed shapes as measured, for every new number of
Gaussians): too costly for a viewer. The cache takes 2 x N x width half values (49 MB at 50k Gaussians).
Its bound on real scenes: a rendered PSNR within 0.02 dB of the fp32 field on every view (the
benchmark's `+half` rows, `psnr_vs_plain`), met on the scenes above except standup and jumpingjacks'
baseline.

Training never comes here: it keeps the fp32 field and its gradients (`garo_ns.render.frame.compose`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any, Iterator, List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor

from garo_ns.deformation import DeformationField, positional_encoding
from garo_ns.render.graphs import versions

Offsets = Tuple[Tensor, Tensor, Tensor]  # d_xyz [N, 3], d_rot [N, 4], d_log_scale [N, 3]


def position_dims(field: DeformationField) -> int:
    """Width of the position encoding, the first columns of the first and the skip layer's input."""
    return 3 * (1 + 2 * field.pos_freqs)


def has_skip(field: DeformationField) -> bool:
    """Whether the input is re-injected (a skip after the last layer re-injects nothing)."""
    return field.skip + 1 < len(field.layers)


@dataclass
class FieldWeights:
    """The field's weights in one dtype: every layer, the first and skip layers also split into
    position / time / hidden columns, and the three heads stacked into one matrix (in `head_dtype`)."""

    layers: List[Tuple[Tensor, Tensor]]
    first_pos: Tensor
    first_time: Tensor
    skip_pos: Optional[Tensor]
    skip_time: Optional[Tensor]
    skip_hidden: Optional[Tensor]
    head_w: Tensor
    head_b: Tensor
    skip: int  # -1: no skip layer

    @classmethod
    @torch.no_grad()
    def of(cls, field: DeformationField, dtype: torch.dtype, head_dtype: torch.dtype = torch.float32) -> "FieldWeights":
        """Copies of `field`'s weights in `dtype`, the heads in `head_dtype` (detached; in fp32 they may
        share the parameters' storage)."""
        p = position_dims(field)
        t = field.layers[0].in_features  # position + time columns, the skip layer's first t columns too
        layers = [(m.weight.detach().to(dtype), m.bias.detach().to(dtype)) for m in field.layers]
        skip_w = layers[field.skip + 1][0] if has_skip(field) else None
        head_layers = (field.d_xyz, field.d_rot, field.d_scale)
        return cls(
            layers=layers,
            first_pos=layers[0][0][:, :p],
            first_time=layers[0][0][:, p:t],
            skip_pos=skip_w[:, :p] if skip_w is not None else None,
            skip_time=skip_w[:, p:t] if skip_w is not None else None,
            skip_hidden=skip_w[:, t:].contiguous() if skip_w is not None else None,
            head_w=torch.cat([h.weight.detach() for h in head_layers]).to(head_dtype),
            head_b=torch.cat([h.bias.detach() for h in head_layers]).to(head_dtype),
            skip=field.skip if skip_w is not None else -1,
        )


@dataclass
class PositionCache:
    """Per Gaussian, the position parts of the first and the skip layer's pre-activations, biases
    folded in: [N, width] each (`skip` None when the field has no skip layer)."""

    first: Tensor
    skip: Optional[Tensor]

    @classmethod
    @torch.no_grad()
    def build(cls, field: DeformationField, xyz: Tensor, dtype: torch.dtype) -> "PositionCache":
        """The position parts for canonical positions `xyz` [N, 3], computed in fp32 and stored in `dtype`."""
        w = FieldWeights.of(field, torch.float32)
        pe = positional_encoding(xyz.detach().float(), field.pos_freqs, field.pos_bands.float())
        first = F.linear(pe, w.first_pos, w.layers[0][1]).to(dtype)
        skip = F.linear(pe, w.skip_pos, w.layers[w.skip + 1][1]).to(dtype) if w.skip_pos is not None else None
        return cls(first, skip)

    def megabytes(self) -> float:
        """Memory held by the cache."""
        return sum(t.numel() * t.element_size() for t in (self.first, self.skip) if t is not None) / 2**20


def time_features(field: DeformationField, time: Union[float, Tensor], device: torch.device) -> Tensor:
    """The time part of the field's input [1, T], in fp32: the time encoding, through the time network
    when there is one (one row a frame, so it stays in fp32)."""
    t = torch.as_tensor(time, dtype=torch.float32, device=device).reshape(1, 1)
    t_enc = positional_encoding(t, field.time_freqs, field.time_bands.float())
    return field.time_net(t_enc).float() if field.time_net is not None else t_enc


def split_heads(out: Tensor) -> Offsets:
    """The stacked heads' output [N, 10] as (d_xyz, d_rot, d_log_scale)."""
    return out[:, :3], out[:, 3:7], out[:, 7:]


def heads(w: FieldWeights, h: Tensor) -> Offsets:
    """The three heads on the last hidden layer `h`, in the heads' dtype (the activations cast up to it)."""
    return split_heads(F.linear(h.to(w.head_w.dtype), w.head_w, w.head_b))


def cached_forward(w: FieldWeights, cache: PositionCache, tfeat: Tensor) -> Offsets:
    """The field's offsets from the cached position parts and the time features `tfeat` [1, T]: the
    first and the skip layer add one per-frame row to the cached per-Gaussian part (the same sums as
    the full products, reassociated), every other layer runs as the field does, in `w`'s dtype, the
    heads in theirs."""
    tfeat = tfeat.to(w.first_time.dtype)
    h = (cache.first + F.linear(tfeat, w.first_time)).relu_()
    for i in range(1, len(w.layers)):
        if i == w.skip + 1:
            base = cache.skip + F.linear(tfeat, w.skip_time)  # type: ignore[operator]
            h = torch.addmm(base.to(h.dtype), h, w.skip_hidden.t()).relu_()  # type: ignore[union-attr]
        else:
            h = F.linear(h, *w.layers[i]).relu_()
    return heads(w, h)


@contextlib.contextmanager
def fp32_accumulation() -> Iterator[None]:
    """Half-precision matrix products that accumulate in fp32 on CUDA (cuBLAS may otherwise reduce
    partial sums in half); CPU kernels accumulate half products in fp32 anyway."""
    previous = torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction
    torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction = previous


class HalfField:
    """Render-time offsets of a `DeformationField`: weights in `dtype` (half by default) except the
    heads, in `head_dtype` (fp32 by default), the position parts cached per Gaussian. Holds the copies
    and the cache of one field and one set of Gaussians; both are rebuilt when the field's weights
    change (checked on every call) or when the caller's `points_key` does.

    `devices`: the device types it runs on; elsewhere the frame path keeps the plain fp32 field (a
    CPU gains nothing from half products). Tests ask for the CPU explicitly.
    """

    def __init__(
        self,
        dtype: torch.dtype = torch.float16,
        devices: Sequence[str] = ("cuda",),
        head_dtype: torch.dtype = torch.float32,
    ):
        self.dtype = dtype
        self.head_dtype = head_dtype
        self.devices = tuple(devices)
        self._weights: Optional[Tuple[Any, FieldWeights]] = None
        self._cache: Optional[Tuple[Any, PositionCache]] = None
        self.builds = 0  # position caches built so far (for tests and profiles)
        # Changes whenever the weight copies or the cache are rebuilt or released: a CUDA graph that read
        # them must be captured again then (its replay would read freed memory).
        self.generation = 0

    def runs_on(self, device: torch.device) -> bool:
        """Whether this path is used on `device` (otherwise the plain field is)."""
        return torch.device(device).type in self.devices

    def __call__(self, field: DeformationField, xyz: Tensor, time: Union[float, Tensor], points_key: Any) -> Offsets:
        """Offsets at `time` of the Gaussians at canonical positions `xyz` [N, 3], in `xyz`'s dtype.

        `points_key` must change whenever `xyz` does (values or which Gaussians): the frame path passes
        the versions of the parameters and whether it passes the dynamic Gaussians or all of them."""
        if torch.is_grad_enabled() and any(p.requires_grad for p in field.parameters()):
            raise RuntimeError("HalfField renders without gradients; training uses the fp32 field")
        weights_key = (versions(field.parameters()), xyz.device)
        if self._weights is None or self._weights[0] != weights_key:
            self._weights = None  # free the old copies first
            self._weights = (weights_key, self.copy_weights(field))
            self.generation += 1
        cache_key = (points_key, weights_key, tuple(xyz.shape))
        if self._cache is None or self._cache[0] != cache_key:
            self._cache = None  # free the old cache before building the new one
            self._cache = (cache_key, PositionCache.build(field, xyz, self.dtype))
            self.builds += 1
            self.generation += 1
        out = self.forward(field, self._weights[1], self._cache[1], time, xyz.device)
        return tuple(o.to(xyz.dtype) for o in out)  # type: ignore[return-value]

    def copy_weights(self, field: DeformationField) -> Any:
        """The weight copies `forward` runs with (rebuilt whenever a parameter of `field` changes)."""
        return FieldWeights.of(field, self.dtype, self.head_dtype)

    def forward(
        self,
        field: DeformationField,
        weights: Any,
        cache: PositionCache,
        time: Union[float, Tensor],
        device: torch.device,
    ) -> Offsets:
        """The offsets from the weight copies and the position cache at `time`."""
        with fp32_accumulation():
            return cached_forward(weights, cache, time_features(field, time, device))

    def cache_megabytes(self) -> float:
        """Memory held by the position cache (0 when there is none)."""
        return self._cache[1].megabytes() if self._cache is not None else 0.0

    def release(self) -> None:
        """Drop the weight copies and the cache (e.g. when rendering in another precision)."""
        if self._weights is not None or self._cache is not None:
            self.generation += 1
        self._weights, self._cache = None, None
