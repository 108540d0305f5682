"""SSIM's forward and backward as two Triton kernels (CUDA; Triton's interpreter runs them on the CPU in the tests).

The definition is `garo_ns.ssim.SSIM`'s (pytorch_msssim's: an 11-tap Gaussian window along height then width, valid
borders, the mean of the map). The grouped convolutions there write each of the five blurred maps to memory, then
some twenty elementwise kernels read them back, and the backward does it all again in reverse: about 1.6 ms of a
training step on an H100 at 800x800 (benchmarks/results/train_profile_bf16_*), for what is a local stencil.

Forward: a program takes a tile of output pixels of one image plane, blurs x, y, x^2, y^2 and xy from the input
(every tap a load that the cache serves), forms the SSIM map and writes it (torch takes its mean) with the map's
partial derivatives with respect to the five blurred values. Those are all the backward needs: with
S = (a1 / b1)(a2 / b2), a1 = 2 mx my + C1, b1 = mx^2 + my^2 + C1, a2 = 2 (Exy - mx my) + C2,
b2 = (Exx - mx^2) + (Eyy - my^2) + C2,

    dS/dmy = 2 mx (a2 - a1) / (b1 b2) - 2 my S (1/b1 - 1/b2)        (mx's the same with x and y swapped)
    dS/dExx = dS/dEyy = -S / b2,    dS/dExy = 2 a1 / (b1 b2),

and the gradient of the mean at an input pixel q is the window's transpose applied to them:
dy(q) = (B^T dmy)(q) + 2 y(q) (B^T dE)(q) + x(q) (B^T dExy)(q), over the M values of the map. Backward: a program
takes a tile of input pixels and gathers the three (four, when x needs a gradient too) maps over the window.

Summation order differs from the convolutions', so values agree with `SSIM` to fp32 rounding (tests/test_fused_ssim.py).
Triton is imported when a kernel is first needed; without it (or off CUDA outside the interpreter) `SSIM` blurs
with its convolutions.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from typing import Any, Optional, Tuple

import torch
from torch import Tensor

# A tile of 16 x 32 output pixels, 4 warps: every tap of the window is one [16, 32] load per input map.
BLOCK_H = 16
BLOCK_W = 32


def interpreting() -> bool:
    """Whether Triton's interpreter is on (TRITON_INTERPRET=1): the kernels then run on CPU tensors."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


@functools.lru_cache(maxsize=None)
def _has_triton() -> bool:
    return importlib.util.find_spec("triton") is not None


def available(x: Tensor) -> bool:
    """Whether the kernels can run on `x`'s device: CUDA with Triton, or the CPU under Triton's interpreter."""
    if not _has_triton():
        return False
    return (not x.is_cuda) if interpreting() else x.is_cuda


@functools.lru_cache(maxsize=None)
def _kernels(interpret: bool) -> Tuple[Any, Any]:
    """The two jitted kernels (built once per interpreter setting: Triton reads it when a kernel is decorated)."""
    del interpret  # the cache key
    import triton
    import triton.language as tl

    @triton.jit
    def forward_kernel(
        x_ptr,
        y_ptr,
        win_ptr,
        map_ptr,
        dmx_ptr,
        dmy_ptr,
        de_ptr,
        dexy_ptr,
        channels,
        sxb,
        sxc,
        sxh,
        sxw,
        syb,
        syc,
        syh,
        syw,
        out_h,
        out_w,
        c1,
        c2,
        KH: tl.constexpr,
        KW: tl.constexpr,
        WANT_DMX: tl.constexpr,
        BH: tl.constexpr,
        BW: tl.constexpr,
    ):
        tile_h = tl.program_id(0)
        tile_w = tl.program_id(1)
        plane = tl.program_id(2)
        b = plane // channels
        c = plane % channels
        rows = tile_h * BH + tl.arange(0, BH)
        cols = tile_w * BW + tl.arange(0, BW)
        inside = (rows[:, None] < out_h) & (cols[None, :] < out_w)
        x_base = x_ptr + b * sxb + c * sxc
        y_base = y_ptr + b * syb + c * syc
        mx = tl.full((BH, BW), 0.0, tl.float32)
        my = tl.full((BH, BW), 0.0, tl.float32)
        exx = tl.full((BH, BW), 0.0, tl.float32)
        eyy = tl.full((BH, BW), 0.0, tl.float32)
        exy = tl.full((BH, BW), 0.0, tl.float32)
        # Height inside, width outside: the convolutions' order (height first, then width).
        for j in tl.static_range(KW):
            if KW > 1:
                wj = tl.load(win_ptr + j)
            else:
                wj = 1.0
            hx = tl.full((BH, BW), 0.0, tl.float32)
            hy = tl.full((BH, BW), 0.0, tl.float32)
            hxx = tl.full((BH, BW), 0.0, tl.float32)
            hyy = tl.full((BH, BW), 0.0, tl.float32)
            hxy = tl.full((BH, BW), 0.0, tl.float32)
            for i in tl.static_range(KH):
                if KH > 1:
                    wi = tl.load(win_ptr + i)
                else:
                    wi = 1.0
                r = rows[:, None] + i
                q = cols[None, :] + j
                xv = tl.load(x_base + r * sxh + q * sxw, mask=inside, other=0.0).to(tl.float32)
                yv = tl.load(y_base + r * syh + q * syw, mask=inside, other=0.0).to(tl.float32)
                hx += wi * xv
                hy += wi * yv
                hxx += wi * (xv * xv)
                hyy += wi * (yv * yv)
                hxy += wi * (xv * yv)
            mx += wj * hx
            my += wj * hy
            exx += wj * hxx
            eyy += wj * hyy
            exy += wj * hxy
        mxx = mx * mx
        myy = my * my
        mxy = mx * my
        a1 = 2.0 * mxy + c1
        b1 = mxx + myy + c1
        a2 = 2.0 * (exy - mxy) + c2
        b2 = (exx - mxx) + (eyy - myy) + c2
        s = (a1 / b1) * (a2 / b2)
        inv = 1.0 / (b1 * b2)
        spread = 1.0 / b1 - 1.0 / b2
        out = plane * out_h * out_w + rows[:, None] * out_w + cols[None, :]
        # The map itself, summed by torch (a few MB): the kernels call Triton's builtins only, as its interpreter
        # cannot run the library's jitted helpers (tl.sum, tl.zeros) once Triton was imported without it.
        tl.store(map_ptr + out, s, mask=inside)
        tl.store(dmy_ptr + out, 2.0 * mx * (a2 - a1) * inv - 2.0 * my * s * spread, mask=inside)
        if WANT_DMX:
            tl.store(dmx_ptr + out, 2.0 * my * (a2 - a1) * inv - 2.0 * mx * s * spread, mask=inside)
        tl.store(de_ptr + out, -s / b2, mask=inside)
        tl.store(dexy_ptr + out, 2.0 * a1 * inv, mask=inside)

    @triton.jit
    def backward_kernel(
        x_ptr,
        y_ptr,
        win_ptr,
        dmx_ptr,
        dmy_ptr,
        de_ptr,
        dexy_ptr,
        gx_ptr,
        gy_ptr,
        scale_ptr,
        channels,
        sxb,
        sxc,
        sxh,
        sxw,
        syb,
        syc,
        syh,
        syw,
        height,
        width,
        out_h,
        out_w,
        KH: tl.constexpr,
        KW: tl.constexpr,
        WANT_GX: tl.constexpr,
        WANT_GY: tl.constexpr,
        BH: tl.constexpr,
        BW: tl.constexpr,
    ):
        tile_h = tl.program_id(0)
        tile_w = tl.program_id(1)
        plane = tl.program_id(2)
        b = plane // channels
        c = plane % channels
        rows = tile_h * BH + tl.arange(0, BH)
        cols = tile_w * BW + tl.arange(0, BW)
        inside = (rows[:, None] < height) & (cols[None, :] < width)
        base = plane * out_h * out_w
        g_mx = tl.full((BH, BW), 0.0, tl.float32)
        g_my = tl.full((BH, BW), 0.0, tl.float32)
        g_e = tl.full((BH, BW), 0.0, tl.float32)
        g_exy = tl.full((BH, BW), 0.0, tl.float32)
        for j in tl.static_range(KW):
            if KW > 1:
                wj = tl.load(win_ptr + j)
            else:
                wj = 1.0
            q = cols[None, :] - j
            for i in tl.static_range(KH):
                if KH > 1:
                    wi = tl.load(win_ptr + i)
                else:
                    wi = 1.0
                r = rows[:, None] - i
                # Output pixel (r, q) took this input pixel at tap (i, j).
                hit = inside & (r >= 0) & (r < out_h) & (q >= 0) & (q < out_w)
                at = base + r * out_w + q
                w = wi * wj
                if WANT_GY:
                    g_my += w * tl.load(dmy_ptr + at, mask=hit, other=0.0)
                if WANT_GX:
                    g_mx += w * tl.load(dmx_ptr + at, mask=hit, other=0.0)
                g_e += w * tl.load(de_ptr + at, mask=hit, other=0.0)
                g_exy += w * tl.load(dexy_ptr + at, mask=hit, other=0.0)
        scale = tl.load(scale_ptr)
        xv = tl.load(x_ptr + b * sxb + c * sxc + rows[:, None] * sxh + cols[None, :] * sxw, mask=inside, other=0.0)
        yv = tl.load(y_ptr + b * syb + c * syc + rows[:, None] * syh + cols[None, :] * syw, mask=inside, other=0.0)
        xv = xv.to(tl.float32)
        yv = yv.to(tl.float32)
        at_in = plane * height * width + rows[:, None] * width + cols[None, :]
        if WANT_GY:
            tl.store(gy_ptr + at_in, scale * (g_my + 2.0 * yv * g_e + xv * g_exy), mask=inside)
        if WANT_GX:
            tl.store(gx_ptr + at_in, scale * (g_mx + 2.0 * xv * g_e + yv * g_exy), mask=inside)

    return forward_kernel, backward_kernel


def _taps(size: int, length: int) -> int:
    """The window's taps along an axis of `length` pixels: none (1) where the image is shorter than the window."""
    return size if length >= size else 1


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, y: Tensor, window: Tensor, c1: float, c2: float) -> Tensor:
        forward_kernel, _ = _kernels(interpreting())
        bsz, channels, height, width = x.shape
        kh, kw = _taps(window.numel(), height), _taps(window.numel(), width)
        out_h, out_w = height - kh + 1, width - kw + 1
        planes = bsz * channels
        grid = (-(-out_h // BLOCK_H), -(-out_w // BLOCK_W), planes)
        f32 = dict(device=x.device, dtype=torch.float32)
        want_dmx = bool(ctx.needs_input_grad[0])
        ssim_map, dmy, de, dexy = (torch.empty(planes, out_h, out_w, **f32) for _ in range(4))
        dmx = torch.empty(planes, out_h, out_w, **f32) if want_dmx else dmy  # a placeholder pointer when unused
        win = window.to(**f32).contiguous()
        forward_kernel[grid](
            x, y, win, ssim_map, dmx, dmy, de, dexy, channels, *x.stride(), *y.stride(), out_h, out_w, c1, c2,
            KH=kh, KW=kw, WANT_DMX=want_dmx, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        ctx.save_for_backward(x, y, win, dmx, dmy, de, dexy)
        ctx.taps = (kh, kw)
        count = planes * out_h * out_w
        ctx.count = count
        return ssim_map.mean().to(x.dtype)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tuple[Optional[Tensor], ...]:
        _, backward_kernel = _kernels(interpreting())
        x, y, win, dmx, dmy, de, dexy = ctx.saved_tensors
        want_gx, want_gy = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        if not (want_gx or want_gy):
            return None, None, None, None, None
        bsz, channels, height, width = x.shape
        kh, kw = ctx.taps
        out_h, out_w = height - kh + 1, width - kw + 1
        f32 = dict(device=x.device, dtype=torch.float32)
        gx = torch.empty(bsz, channels, height, width, **f32) if want_gx else dmy
        gy = torch.empty(bsz, channels, height, width, **f32) if want_gy else dmy
        # The incoming gradient stays on the device (no host read): the kernel loads it.
        scale = (grad.to(torch.float32) / ctx.count).reshape(1)
        grid = (-(-height // BLOCK_H), -(-width // BLOCK_W), bsz * channels)
        backward_kernel[grid](
            x, y, win, dmx, dmy, de, dexy, gx, gy, scale, channels, *x.stride(), *y.stride(),
            height, width, out_h, out_w,
            KH=kh, KW=kw, WANT_GX=want_gx, WANT_GY=want_gy, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        return (
            gx.to(x.dtype) if want_gx else None,
            gy.to(y.dtype) if want_gy else None,
            None,
            None,
            None,
        )


def fused_ssim(x: Tensor, y: Tensor, window: Tensor, data_range: float = 1.0) -> Tensor:
    """Mean SSIM of two [B, C, H, W] batches of one shape with the 1-D `window`, through the two kernels
    (`available(x)` must hold). Gradients flow to whichever of x and y requires them."""
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"SSIM takes two [B, C, H, W] batches of one shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    c1 = (0.01 * float(data_range)) ** 2
    c2 = (0.03 * float(data_range)) ** 2
    return _FusedSSIM.apply(x, y, window, c1, c2)
