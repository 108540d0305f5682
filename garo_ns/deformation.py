"""Time-conditioned deformation field of D-3DGS (Yang et al., CVPR 2024).

An MLP of positional encodings of a Gaussian's canonical position and of time predicts offsets
of its position, rotation (quaternion) and log-scale at that time. For synthetic scenes D-3DGS
first passes the time encoding through a small network of its own (one hidden layer of 256, out
`time_net` features); real captures feed the encoding directly (`time_net=0`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Literal, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from garo_ns.errors import check_ranges
from garo_ns.ops.dense import aligned, dense

HeadInit = Literal["zero", "default"]
HEAD_INITS = ("zero", "default")
ScaleOffset = Literal["log", "linear"]
SCALE_OFFSETS = ("log", "linear")
SCALE_FLOOR = 1e-8
"""Smallest scale a `linear` scale offset leaves (scene units): an offset may cancel a scale."""


def log_scale_offset(log_scales: Tensor, d_scale: Tensor, mode: ScaleOffset) -> Tensor:
    """The field's scale offset as an offset of the log-scales, so that every reader composes `log_scales +`
    this. `log`: the offset itself (this project's composition: scales stay positive). `linear`: the official
    D-3DGS code's, the offset added to the activated scale, exp(log_scales) + d_scale, taken by magnitude (the
    rasterizer's covariance squares each scale, so a negative one acts as its magnitude there too) and floored
    at SCALE_FLOOR."""
    if mode == "log":
        return d_scale
    check_scale_offset(mode)
    return torch.log(linear_scales(torch.exp(log_scales) + d_scale)) - log_scales


def linear_scales(scales: Tensor) -> Tensor:
    """Activated scales with their `linear` offsets added, as the rasterizer takes them: by magnitude and floored
    at SCALE_FLOOR (see `log_scale_offset`)."""
    return scales.abs().clamp_min(SCALE_FLOOR)


def check_scale_offset(mode: str) -> None:
    """Raise ValueError unless `mode` is one of SCALE_OFFSETS."""
    if mode not in SCALE_OFFSETS:
        raise ValueError(f"scale offset must be one of {SCALE_OFFSETS}, got {mode!r}")


def as_log_offsets(offsets: Tensor, log_scales: Optional[Tensor], mode: ScaleOffset) -> Tensor:
    """Concatenated offsets [..., N, 10] (position, rotation, scale) with their scale part made offsets of the
    log-scales [N, 3] (`log_scale_offset`), in place; unchanged under `log`. For the readers that sample the field
    apart from a frame: the time table, the static classification."""
    if mode == "log":
        return offsets
    if log_scales is None:
        raise ValueError(f"a {mode!r} scale offset needs the Gaussians' log-scales")
    offsets[..., 7:] = log_scale_offset(log_scales.detach().to(offsets.dtype), offsets[..., 7:], mode)
    return offsets


def frequency_bands(n_freqs: int, device: torch.device | None = None) -> Tensor:
    """2^k for k < n_freqs (exact in floating point)."""
    return 2.0 ** torch.arange(n_freqs, device=device, dtype=torch.float32)


def positional_encoding(x: Tensor, n_freqs: int, freqs: Tensor | None = None) -> Tensor:
    """[x, sin(2^k x), cos(2^k x) for k < n_freqs] along the last axis: D * (1 + 2 n_freqs) features.
    `freqs`: `frequency_bands(n_freqs)` made beforehand (saves two kernels a call)."""
    if n_freqs == 0:
        return x
    freqs = frequency_bands(n_freqs, x.device) if freqs is None else freqs
    freqs = freqs.to(x.dtype)
    angles = (x[..., None, :] * freqs[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class DeformationField(nn.Module):
    """D-3DGS's deformation MLP: `depth` ReLU layers of `width` with the input re-injected after
    layer `skip`, and three linear heads for position, rotation and scale offsets.

    `head_init`: "default" keeps PyTorch's random initialisation, as the official D-3DGS code does
    (the field starts with small offsets, mostly a common shift); "zero" starts the heads at zero,
    the identity at the switch-on, but then every unit of the last hidden layer receives the same
    first updates, and that layer can die as a whole (see GaroModelConfig.deform_head_init).
    """

    times_per_row = True
    """`forward` takes one time per position ([N, 1]): a caller may sample several times in one call."""

    def __init__(
        self,
        pos_freqs: int = 10,
        time_freqs: int = 6,
        depth: int = 8,
        width: int = 256,
        skip: int = 4,
        head_init: HeadInit = "default",
        time_net: int = 0,
        fused_layers: bool = False,
        fp32_heads: bool = False,
    ):
        super().__init__()
        # Not parameters: how the products run (garo_ns.ops.dense; the heads' precision under autocast), not what they
        # compute.
        self.fused_layers = fused_layers
        self.fp32_heads = fp32_heads
        if depth < 1 or width < 1:
            raise ValueError(f"depth and width must be >= 1, got depth={depth}, width={width}")
        if time_net < 0:
            raise ValueError(f"time_net must be >= 0 (0: no time network), got {time_net}")
        if head_init not in HEAD_INITS:
            raise ValueError(f"head_init must be one of {HEAD_INITS}, got {head_init!r}")
        self.pos_freqs, self.time_freqs, self.skip = pos_freqs, time_freqs, skip
        # Not saved: fixed by the two counts, and checkpoints from before them load unchanged.
        self.register_buffer("pos_bands", frequency_bands(pos_freqs), persistent=False)
        self.register_buffer("time_bands", frequency_bands(time_freqs), persistent=False)
        time_dim = 1 + 2 * time_freqs
        # D-3DGS's time network for synthetic scenes: encoding -> 256 -> ReLU -> `time_net` features.
        self.time_net = (
            nn.Sequential(nn.Linear(time_dim, 256), nn.ReLU(), nn.Linear(256, time_net)) if time_net > 0 else None
        )
        in_dim = 3 * (1 + 2 * pos_freqs) + (time_net if time_net > 0 else time_dim)
        layers = [nn.Linear(in_dim, width)]
        for i in range(depth - 1):
            layers.append(nn.Linear(width + (in_dim if i == skip else 0), width))
        self.layers = nn.ModuleList(layers)
        self.d_xyz = nn.Linear(width, 3)
        self.d_rot = nn.Linear(width, 4)
        self.d_scale = nn.Linear(width, 3)
        if head_init == "zero":
            for head in (self.d_xyz, self.d_rot, self.d_scale):
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)

    def encode(self, xyz: Tensor, time: Tensor | float, pad: int = 0) -> Tensor:
        """The MLP's input [N, F]: positional encodings of `xyz` [N, 3] and of `time` (a scalar, or one
        per point [N, 1]), the latter through the time network when there is one; then `pad` zero columns."""
        # A number is filled in on the device: a tensor made from it on the host is a copy that waits for the GPU.
        if isinstance(time, Tensor):
            t = time.to(dtype=xyz.dtype, device=xyz.device)
        else:
            t = torch.full((1, 1), float(time), dtype=xyz.dtype, device=xyz.device)
        t_enc = positional_encoding(t.reshape(-1, 1), self.time_freqs, self.time_bands)
        if self.time_net is not None:
            t_enc = self.time_net(t_enc)
        # One time (a scalar) is encoded once and broadcast: the time network runs on one row.
        t_enc = t_enc.expand(xyz.shape[0], -1) if t_enc.shape[0] == 1 else t_enc
        parts = [positional_encoding(xyz, self.pos_freqs, self.pos_bands), t_enc.to(xyz.dtype)]
        if pad:  # in the concatenation that happens anyway: no copy of its own
            parts.append(xyz.new_zeros(1, pad).expand(xyz.shape[0], -1))
        return torch.cat(parts, dim=-1)

    def time_sampler(self, xyz: Tensor) -> Callable[[Tensor], Tuple[Tensor, Tensor, Tensor]]:
        """For fixed canonical positions `xyz` [N, 3], a function of times [T] that returns the offsets at every
        time ([T * N, 3], [T * N, 4], [T * N, 3], time-major): `forward(xyz.repeat(T, 1), times.repeat_interleave(N))`
        up to the order of its sums. The positions' share of the two layers that read the encoding (the first and the
        one after the skip) is computed once here, so sampling a time costs the hidden products alone, without the
        position encoding, the time network per row or the concatenations. For time tables (thousands of times)."""
        pos_dim = 3 * (1 + 2 * self.pos_freqs)
        x_enc = positional_encoding(xyz, self.pos_freqs, self.pos_bands)
        first = self.layers[0]
        skip = self.layers[self.skip + 1] if self.skip + 1 < len(self.layers) else None
        in_dim = first.in_features

        def position_share(layer: nn.Linear) -> Tensor:
            return torch.addmm(layer.bias, x_enc, layer.weight[:, :pos_dim].t())

        fixed_first = position_share(first)
        fixed_skip = position_share(skip) if skip is not None else None

        def sample(times: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
            t = times.to(dtype=xyz.dtype, device=xyz.device).reshape(-1, 1)
            t_enc = positional_encoding(t, self.time_freqs, self.time_bands)
            if self.time_net is not None:
                t_enc = self.time_net(t_enc)

            def layer_in(fixed: Tensor, weight: Tensor) -> Tensor:  # [T * N, width]: position share + time share
                return (fixed[None] + (t_enc @ weight.t())[:, None]).flatten(0, 1)

            h = torch.relu(layer_in(fixed_first, first.weight[:, pos_dim:]))
            for i, layer in enumerate(self.layers[1:], start=1):
                if layer is skip:
                    assert fixed_skip is not None
                    timed = layer_in(fixed_skip, layer.weight[:, pos_dim:in_dim])
                    h = torch.relu(torch.addmm(timed, h, layer.weight[:, in_dim:].t()))
                else:
                    h = torch.relu(layer(h))
            return self.d_xyz(h), self.d_rot(h), self.d_scale(h)

        return sample

    def hidden(self, xyz: Tensor, time: Tensor | float) -> List[Tensor]:
        """The ReLU output of every hidden layer [N, width] (before the skip concatenation). With `fused_layers` the
        layers run through garo_ns.ops.dense, the input padded with zero columns to a multiple of 8 (after the skip, the
        input and a hidden layer together) and the weights given zero columns to match."""
        in_dim = self.layers[0].in_features
        pad = aligned(in_dim) if self.fused_layers else 0
        x = self.encode(xyz, time, pad)
        h, out = x, []
        for i, layer in enumerate(self.layers):
            if self.fused_layers:
                weight = layer.weight
                if pad and i == 0:
                    weight = F.pad(weight, (0, pad))
                elif pad and i == self.skip + 1:  # [input, hidden]: the zeros sit between them
                    zeros = weight.new_zeros(weight.shape[0], pad)
                    weight = torch.cat([weight[:, :in_dim], zeros, weight[:, in_dim:]], dim=1)
                h = dense(h, weight, layer.bias, relu=True)
            else:
                h = torch.relu(layer(h))
            out.append(h)
            if i == self.skip and i + 1 < len(self.layers):
                h = torch.cat([x, h], dim=-1)
        return out

    def _heads_fused(self, h: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """The three heads as one product, its outputs padded to a multiple of 8 rows."""
        heads = (self.d_xyz, self.d_rot, self.d_scale)
        sizes = [head.out_features for head in heads]
        pad = aligned(sum(sizes))
        weight = torch.cat([head.weight for head in heads] + [heads[0].weight.new_zeros(pad, h.shape[1])])
        bias = torch.cat([head.bias for head in heads] + [heads[0].bias.new_zeros(pad)])
        d_xyz, d_rot, d_scale, _ = dense(h, weight, bias).split(sizes + [pad], dim=-1)
        return d_xyz, d_rot, d_scale

    def forward(self, xyz: Tensor, time: Tensor | float) -> Tuple[Tensor, Tensor, Tensor]:
        """Offsets at `time` for canonical positions `xyz` [N, 3].

        Args:
            xyz: canonical positions (the caller detaches them, as D-3DGS does).
            time: a scalar or an [N, 1] tensor in [0, 1].

        Returns:
            d_xyz [N, 3], d_rot [N, 4], d_log_scale [N, 3].
        """
        h = self.hidden(xyz, time)[-1]
        if self.fp32_heads and torch.is_autocast_enabled(h.device.type):
            # The offsets' last product in fp32, outside autocast: a bf16 result keeps 8 bits of an offset, too few
            # where the scale offset nearly cancels a small scale (`deform_fp32_heads`).
            with torch.autocast(h.device.type, enabled=False):
                return self.heads(h.float(), xyz.dtype)
        return self.heads(h, xyz.dtype)

    def heads(self, h: Tensor, dtype: torch.dtype) -> Tuple[Tensor, Tensor, Tensor]:
        """The three offsets of the last hidden layer `h` [N, width], in `dtype`."""
        if self.fused_layers:
            return tuple(o.to(dtype) for o in self._heads_fused(h))  # type: ignore[return-value]
        return self.d_xyz(h).to(dtype), self.d_rot(h).to(dtype), self.d_scale(h).to(dtype)


@torch.no_grad()
def field_health(field: DeformationField, xyz: Tensor, times: Tensor) -> Dict[str, object]:
    """Whether the field still models motion, on sample positions `xyz` [N, 3] at `times` [T].

    Returns `time_sensitivity` (mean over points of the RMS deviation of the position offset from
    its mean over the times, world units), `mean_offset` (mean |d_xyz|), and `dead_fraction` per
    hidden layer (units that are zero for every sample). A layer that is all dead, or a time
    sensitivity of zero, means the field has collapsed to one motion for every time: its ReLUs
    get no gradient and it never recovers.
    """
    offsets, alive = [], None
    for t in times.tolist():
        hidden = field.hidden(xyz, t)
        used = torch.stack([(h > 0).any(0) for h in hidden])  # [layers, width]
        alive = used if alive is None else alive | used
        offsets.append(field.d_xyz(hidden[-1]))
    d = torch.stack(offsets)  # [T, N, 3]
    spread = (d - d.mean(0, keepdim=True)).pow(2).sum(-1).mean(0).sqrt()
    return {
        "time_sensitivity": float(spread.mean()),
        "mean_offset": float(d.norm(dim=-1).mean()),
        "dead_fraction": [round(float(1 - a.float().mean()), 4) for a in alive],
    }


@torch.no_grad()
def health_check(field: DeformationField, means: Tensor, times: Tensor, extent: float, step: int) -> Dict[str, object]:
    """`field_health` on up to 4096 of the Gaussians (a sample seeded by `step`) at `times`, with the
    step and whether the field has `collapsed`: a hidden layer all dead, or offsets that no longer
    change with time (relative to the scene `extent`)."""
    pick = torch.randperm(means.shape[0], generator=torch.Generator().manual_seed(step))[:4096]
    health = field_health(field, means.detach()[pick.to(means.device)], times)
    health["step"] = int(step)
    health["collapsed"] = bool(
        max(health["dead_fraction"]) >= 1.0 or health["time_sensitivity"] <= 1e-6 * extent  # type: ignore[operator]
    )
    return health


def health_due(step: int, warmup: int, every: int) -> bool:
    """Whether `step` is a health-check step: every `every` steps after the field switches on at
    `warmup`, not at the switch-on itself (zero heads give no motion there by design); never when
    `every` <= 0."""
    return every > 0 and step > warmup and (step - warmup) % every == 0


def collapse_warning(health: Dict[str, object], head_init: HeadInit) -> str:
    """What to tell the user once a `health_check` found the field `collapsed` (no later step can undo it)."""
    return (
        f"[bold red]Step {health['step']}: the deformation field has collapsed (time sensitivity "
        f"{health['time_sensitivity']:.2e}, dead units per layer {health['dead_fraction']}); "
        "the scene will render as static. Retrain with another seed"
        + (" or --pipeline.model.deform-head-init default" if head_init == "zero" else "")
        + ".[/bold red]"
    )


def time_noise(strength: float, steps: int, step: int, frames: int, training: bool) -> float:
    """D-3DGS's noise on the field's time input while training (its `ast_noise`): one draw from torch's
    global generator, shared by all Gaussians, with a standard deviation of `strength` frame intervals
    (`frames` frames over [0, 1]) that decays linearly to 0 at step `steps`. 0 outside training, from
    step `steps` on, and when `strength` <= 0 (no draw then)."""
    if not training or strength <= 0 or step >= steps:
        return 0.0
    std = strength * (1.0 - step / steps) / max(frames, 1)
    return float(torch.randn(()) * std)


@dataclass
class DeformationSettings:
    """The deformation field's settings (D-3DGS's), part of the model config."""

    deform_pos_freqs: int = 10
    """Positional-encoding frequencies of the canonical position."""
    deform_time_freqs: int = 6
    """Positional-encoding frequencies of time: 6 for synthetic scenes, 10 for real captures."""
    deform_depth: int = 8
    """Hidden layers of the deformation MLP."""
    deform_width: int = 256
    """Width of the deformation MLP."""
    deform_skip: int = 4
    """The input is concatenated again after this hidden layer."""
    deform_time_net: int = 30
    """D-3DGS's time network for synthetic scenes (`--is_blender`): the time encoding passes through
    a 256-unit hidden layer to this many features before the MLP. 0: the encoding goes in directly,
    as D-3DGS does for real captures (the `-real` presets)."""
    deform_warmup: int = 3000
    """Static warm-up: the deformation field is used from this step on (D-3DGS warm_up)."""
    deform_head_init: HeadInit = "default"
    """Initial output heads of the MLP: PyTorch's default (as D-3DGS) or zero (identity at the
    switch-on). Zero heads give every unit of the last hidden layer the same first updates; on lego
    their last layer died wholesale in 1 of 5 runs, the field then modelled no motion
    (benchmarks/results/deform_health_H200.json, benchmarks/HISTORY.md; 0 of 5 with the default)."""
    health_every: int = 500
    """Check every this many steps after the warm-up that the deformation field still models
    motion (garo_ns.deformation.field_health): logged, with a warning when it has collapsed. 0: off."""
    time_noise: float = 0.0
    """Training only: the MLP's time input gets Gaussian noise of this many frame intervals (one
    draw per step, shared by all Gaussians), decaying linearly to 0 at `time_noise_steps`. D-3DGS
    uses 0.1 on real captures (its `ast_noise`) to smooth motion between sparse frames; 0: off."""
    time_noise_steps: int = 20_000
    """Step at which the time-input noise reaches 0."""
    default_time: float = 0.0
    """Time used for cameras that carry none (e.g. some viewer and render paths); warned once."""
    deform_scale_offset: ScaleOffset = "log"
    """How the field's scale offset composes with a Gaussian's scale: `log` adds it to the log-scale (scales stay
    positive), `linear` to the scale itself, as the official D-3DGS code does (its magnitude, floored at 1e-8:
    garo_ns.deformation.log_scale_offset). Every reader follows it: training, rendering and the time table, the
    static classification, export. At 40k on the three shared scenes (deform-splatfacto, two rounds) `linear`
    changed test PSNR by -0.25, +0.16 and +0.07 dB (jumpingjacks, mutant, standup; -0.01 on average) with worse LPIPS
    on all three in both rounds (benchmarks/results/ab_scale_term_H200.json), but those runs took bf16 products; with
    fp32 products it gained on all three (+0.08, +0.23, +0.09 dB, two rounds; ab_scale_term_fp32_H200.json), so
    `deform-splatfacto` trains with `linear` in fp32, as the official code does; `garo-deform` with `linear` in bf16
    with its heads in fp32 (`deform_fp32_heads`: +0.17 dB on average, ab_fp32_heads_H200.json). `log` stays the
    default elsewhere. A checkpoint records the composition it was trained with, and loading it adopts that one
    (garo_ns.state.checkpoints.scale_offset_for), so a run trained before a method's default changed renders as
    trained."""
    deform_cuda_graph: bool = True
    """Training on CUDA: the step's Gaussians, from the canonical parameters to the rasterizer's inputs (the field,
    the composition, the activations), replay a CUDA graph captured for the current count of Gaussians (captured
    anew when it changes; garo_ns.engine.train_graphs.GraphedSplats): one autograd node instead of a few dozen each way,
    the same kernels and numbers (tests/test_training_graphs.py). 40k jumpingjacks steps alone on an H100 took 394 s
    with it and 403 s with the field alone in the graph (benchmarks/results/train_profile_splats*). See
    `loss_cuda_graph` for what the two graphs save."""
    deform_graph_grads: bool = True
    """With `deform_cuda_graph`: the graph is our own capture (garo_ns.engine.train_graphs.StepGraph), whose backward
    adds the field's gradients into each parameter's `.grad` itself instead of returning them for autograd to accumulate
    (one node, allocation and copy per parameter, 26, every step); the same sums (tests/test_training_graphs.py). On
    because its captures, one every refinement while densifying, reuse each other's memory on one stream. Off, torch's
    make_graphed_callables captures, and newer torch (2.14) captures it on a new stream each call: a freed block is
    reused only on its own stream, so the pool keeps the memory of up to 32 dropped graphs (StepGraph on a new
    stream each time held 43,697 MiB on an H200 where the run beside it held 6,175). In 40k A/B pairs on one H200
    host it scored +0.10 dB on average and ran 1.03x faster, within the two GPUs' own difference (1.06x on the
    field-free warm-up steps; benchmarks/results/ab_graph_grads_H200.json)."""
    deform_train_tf32: bool = True
    """Training on CUDA: the step's fp32 matrix products (the deformation MLP's, forward and backward, where
    `deform_train_bf16` is off) take TF32 inputs (10-bit mantissa, fp32 sums) on tensor cores; rendering, evaluation
    and the CPU stay exact fp32. The camera's view matrix and centre are sums, not products, so they stay exact fp32
    either way (TF32 would move a camera 4 units out by about 2e-3)."""
    deform_train_bf16: bool = False
    """Training on CUDA: the deformation MLP's forward (and so its backward) under bf16 autocast, its weights kept
    in fp32 and its offsets returned in fp32 (garo_ns.engine.train_graphs.Bf16Field); the CPU stays fp32. On a fresh
    field the offsets differ from fp32 by about 0.3% of their norm (tests/test_training_step.py). `garo-deform` turns it
    on after a 40k A/B on jumpingjacks, mutant and standup against fp32 runs (test PSNR -0.03 dB on average;
    benchmarks/results/train_profile_bf16_*). `deform-splatfacto` had it on too (+0.02 dB, train_profile_hx2_*) until it
    took the official scale composition, which gains in fp32 only (`deform_scale_offset`). Off elsewhere until their own
    A/B."""

    deform_fused_layers: bool = False
    """The deformation MLP's layers through garo_ns.ops.dense (training and rendering, CUDA and CPU): the bias and the
    ReLU in each product's epilogue, the bias gradient as a matrix-vector product instead of a column sum over every
    Gaussian, the two odd input widths (93 and 349) zero-padded to multiples of 8 and the three heads as one product.
    The same sums up to their order, the same parameters and checkpoints. The field alone in bf16, graphed, ran
    1.8x faster (benchmarks/field_layers.py at 7997206, benchmarks/results/field_layers_H200.json); 40k steps on mutant
    took 252 s instead of 278 (one pair, docs/benchmarks.md). `garo-deform` turns it on after its 40k A/B on the three
    scenes (+0.14 dB on average; benchmarks/results/ab_fused_layers_H200.json); off elsewhere until their own A/B, as
    bf16 rounds the reordered sums differently."""

    deform_fp32_heads: bool = False
    """With `deform_train_bf16`: the three heads' product (the offsets) in fp32, from the last hidden layer's bf16
    output, instead of rounding each offset to bf16's 8 bits. Where the scale offset composes `linear`ly it can nearly
    cancel a small scale, and the rounding of the offset becomes the rounding of the scale; the heads are about 0.5% of
    the field's products. The same parameters and checkpoints; it changes nothing outside bf16 autocast. On in
    `garo-deform`, with `linear` (its 40k A/B on the three scenes: benchmarks/results/ab_fp32_heads_H200.json)."""

    def validate_deformation(self) -> None:
        """Raise GaroConfigError, naming the flag, for a field size that cannot be built."""

        def count(value: Any, low: int) -> bool:
            return isinstance(value, int) and not isinstance(value, bool) and value >= low

        check_ranges(
            self,
            {
                "deform-width": (count(self.deform_width, 1), "an int >= 1"),
                "deform-depth": (count(self.deform_depth, 1), "an int >= 1"),
                "deform-skip": (count(self.deform_skip, 0), "an int >= 0"),
                "deform-pos-freqs": (count(self.deform_pos_freqs, 0), "an int >= 0"),
                "deform-time-freqs": (count(self.deform_time_freqs, 0), "an int >= 0"),
            },
        )

    def make_deformation(self) -> DeformationField:
        """The deformation field these settings describe (untrained)."""
        if self.deform_scale_offset not in SCALE_OFFSETS:
            raise ValueError(f"deform_scale_offset must be one of {SCALE_OFFSETS}, got {self.deform_scale_offset!r}")
        return DeformationField(
            self.deform_pos_freqs,
            self.deform_time_freqs,
            self.deform_depth,
            self.deform_width,
            self.deform_skip,
            head_init=self.deform_head_init,
            time_net=self.deform_time_net,
            fused_layers=self.deform_fused_layers,
            fp32_heads=self.deform_fp32_heads,
        )
