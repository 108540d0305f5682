"""A tabled frame's Gaussians in one GPU kernel.

A linear time table's frame (garo_ns.render.time_table.TimeTable.rows_at, then the rasterizer's means, quaternions
and scales) is some twenty small kernels: the segment found from the time on the device, two anchors and two keys
gathered, two interpolations, the scales put back, the rows split into the rasterizer's tensors. Each moves well
under a megabyte at 50k Gaussians, so the frame pays their launches, not their bytes. `table_splats` does all of it
in one Triton kernel where `fused_available` says it can (a CUDA device, Triton importable, every Gaussian moving);
the frame path takes the torch path otherwise. Both give the same numbers to float rounding, which
tests/test_table_lookup.py checks on a CPU with Triton's interpreter.
"""

from __future__ import annotations

from typing import Any, Tuple

import torch
from torch import Tensor

from garo_ns.deformation import SCALE_FLOOR
from garo_ns.ops.triton_mode import per_mode, runs_on
from garo_ns.render.time_table import CHANNELS, PAD, TimeTable

BLOCK = 1024  # table entries (Gaussian x channel) per program


def fused_available(table: TimeTable, rows: Tensor) -> bool:
    """Whether `table_splats` takes the one-kernel path for these rows: Triton on the rows' device (a CUDA GPU,
    or its interpreter when TRITON_INTERPRET=1), and every Gaussian moving (a table with still Gaussians scatters
    its moving ones, which the torch path does)."""
    if table.moving.numel() != rows.shape[0] or not table.graphable:
        return False
    return runs_on(rows.device)


def table_splats(table: TimeTable, rows: Tensor, time: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
    """Means [N, 3], quaternions [N, 4] and scales [N, 3] at `time` (a device scalar, so a CUDA graph can replay
    the frame) of a table `fused_available` accepts, `rows` being the canonical rows plus the table's base
    (frame.table_rows): what frame.rows_splats makes of `TimeTable.rows_at`, in one kernel."""
    key_anchor, anchor_at = table.anchor_index(rows.device)
    spec, n = table.spec, rows.shape[0]
    means = torch.empty(n, 3, device=rows.device)
    quats = torch.empty(n, 4, device=rows.device)
    scales = torch.empty(n, 3, device=rows.device)
    scale = table.codec.scale
    _kernel()[(-(-n * CHANNELS // BLOCK),)](
        time.reshape(1).float(),
        key_anchor,
        anchor_at,
        table.anchors,
        table.residual,
        scale if scale is not None else rows,  # not read without a scale
        rows,
        means,
        quats,
        scales,
        n * CHANNELS,
        float(spec.t_lo),
        float(spec.t_hi),
        float(spec.spacing),
        float(PAD - 1),
        float(spec.intervals + PAD - 1),
        SCALE_FLOOR,
        HAS_SCALE=scale is not None,
        LOG=table.scale_offset == "log",
        PAD_HALF=PAD - 0.5,
        CH=CHANNELS,
        BLOCK=BLOCK,
    )
    return means, quats, scales


@per_mode
def _kernel() -> Any:
    """The Triton kernel, made once per interpreter setting (garo_ns.ops.triton_mode)."""
    import triton
    import triton.language as tl

    @triton.jit
    def lookup(
        time_ptr,
        key_anchor_ptr,
        anchor_at_ptr,
        anchors_ptr,
        residual_ptr,
        scale_ptr,
        rows_ptr,
        means_ptr,
        quats_ptr,
        scales_ptr,
        size,
        t_lo,
        t_hi,
        spacing,
        i_lo,
        i_hi,
        floor,
        HAS_SCALE: tl.constexpr,
        LOG: tl.constexpr,
        PAD_HALF: tl.constexpr,
        CH: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        # The segment, as TimeTable.rows_at finds it (every program finds the same one).
        t = tl.minimum(tl.maximum(tl.load(time_ptr), t_lo), t_hi)
        u = (t - t_lo) / spacing + PAD_HALF
        i = tl.minimum(tl.maximum(tl.floor(u), i_lo), i_hi)
        f = u - i
        key = i.to(tl.int64)
        j = tl.load(key_anchor_ptr + key)
        at0 = tl.load(anchor_at_ptr + j)
        at1 = tl.load(anchor_at_ptr + j + 1)
        w = (i + f - at0) / (at1 - at0)
        offs = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        inside = offs < size
        # Both interpolations in torch.lerp's two-sided form, so that the two paths round alike.
        a0 = tl.load(anchors_ptr + j * size + offs, mask=inside, other=0.0)
        a1 = tl.load(anchors_ptr + (j + 1) * size + offs, mask=inside, other=0.0)
        line = tl.where(w < 0.5, a0 + w * (a1 - a0), a1 - (a1 - a0) * (1.0 - w))
        r0 = tl.load(residual_ptr + key * size + offs, mask=inside, other=0).to(tl.float32)
        r1 = tl.load(residual_ptr + (key + 1) * size + offs, mask=inside, other=0).to(tl.float32)
        fine = tl.where(f < 0.5, r0 + f * (r1 - r0), r1 - (r1 - r0) * (1.0 - f))
        if HAS_SCALE:
            out = line + fine * tl.load(scale_ptr + offs, mask=inside, other=0.0)
        else:
            out = line + fine
        out = out + tl.load(rows_ptr + offs, mask=inside, other=0.0)
        g = offs // CH  # the Gaussian; its channels are means 0-2, quaternion 3-6, scale rows 7-9
        c = offs % CH
        tl.store(means_ptr + g * 3 + c, out, mask=inside & (c < 3))
        tl.store(quats_ptr + g * 4 + (c - 3), out, mask=inside & (c >= 3) & (c < 7))
        if LOG:
            s = tl.exp(out)
        else:
            s = tl.maximum(tl.abs(out), floor)
        tl.store(scales_ptr + g * 3 + (c - 7), s, mask=inside & (c >= 7))

    return lookup
