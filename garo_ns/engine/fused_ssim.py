"""SSIM's forward and backward in four Triton kernels (CUDA; Triton's interpreter runs them on the CPU in the tests).

The definition is `garo_ns.engine.ssim.SSIM`'s (pytorch_msssim's: an 11-tap Gaussian window along height then width,
valid borders, the mean of the map). There, grouped convolutions write the five blurred maps, then some twenty
elementwise kernels read and write whole maps, and the backward does it all again in reverse: about 1.2 ms of device
time for one 800x800 loss on an H100 (benchmarks/results/loss_speed_H100.json).

Forward, two kernels: the first blurs x, y, x^2, y^2 and xy along the height from the inputs (the five products
formed on the fly); the second blurs those along the width, forms the SSIM map (torch takes its mean) and writes
the map's partial derivatives with respect to the five blurred values, all the backward needs. With
S = (a1 / b1)(a2 / b2), a1 = 2 mx my + C1, b1 = mx^2 + my^2 + C1, a2 = 2 (Exy - mx my) + C2,
b2 = (Exx - mx^2) + (Eyy - my^2) + C2,

    dS/dmy = 2 mx (a2 - a1) / (b1 b2) - 2 my S (1/b1 - 1/b2)        (mx's the same with x and y swapped)
    dS/dExx = dS/dEyy = -S / b2,    dS/dExy = 2 a1 / (b1 b2),

and the gradient of the mean at an input pixel q is the window's transpose applied to them:
dy(q) = (B^T dmy)(q) + 2 y(q) (B^T dE)(q) + x(q) (B^T dExy)(q), over the M values of the map. Backward, two
kernels: the transposed blur along the width, then along the height with the products by x and y.

A blur along one axis at a time takes 11 loads a value where the whole window would take 121 (a first version
that did so was slower than the convolutions: 1.52 against 1.22 ms graphed, loss_speed_window_H100.json). The
summation order differs from the convolutions', so values agree with `SSIM` to fp32 rounding
(tests/test_fused_ssim.py). Triton is imported when a kernel is first needed; without it (or off CUDA outside the
interpreter) `SSIM` blurs with its convolutions.
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.ops.triton_mode import has_triton, interpreting, per_mode

# A tile of 8 x 64 pixels, 4 warps: rows of 64 contiguous values for the loads along the width.
BLOCK_H = 8
BLOCK_W = 64


def available(x: Tensor) -> bool:
    """Whether the kernels can run on `x`'s device: CUDA with Triton, or the CPU under Triton's interpreter."""
    if not has_triton():
        return False
    return (not x.is_cuda) if interpreting() else x.is_cuda


@per_mode
def _kernels() -> Tuple[Any, Any, Any, Any]:
    """The four jitted kernels (built once per interpreter setting: Triton reads it when a kernel is decorated).

    They call Triton's builtins only (tl.full, not tl.zeros; no tl.sum): its interpreter cannot run the library's
    jitted helpers once Triton was imported without it."""
    import triton
    import triton.language as tl

    @triton.jit
    def blur_height(
        x_ptr, y_ptr, win_ptr, v_ptr, channels, sxb, sxc, sxh, sxw, syb, syc, syh, syw, planes, out_h, width,
        KH: tl.constexpr, BH: tl.constexpr, BW: tl.constexpr,
    ):  # fmt: skip
        # v[k, plane, h, w] = sum_i win[i] f_k(x, y)[h + i, w] for f = (x, y, x^2, y^2, xy); h < out_h.
        plane = tl.program_id(2)
        b = plane // channels
        c = plane % channels
        rows = tl.program_id(0) * BH + tl.arange(0, BH)
        cols = tl.program_id(1) * BW + tl.arange(0, BW)
        inside = (rows[:, None] < out_h) & (cols[None, :] < width)  # every tap of an inside pixel is in the image
        px = x_ptr + b * sxb + c * sxc + rows[:, None] * sxh + cols[None, :] * sxw
        py = y_ptr + b * syb + c * syc + rows[:, None] * syh + cols[None, :] * syw
        mx = tl.full((BH, BW), 0.0, tl.float32)
        my = tl.full((BH, BW), 0.0, tl.float32)
        exx = tl.full((BH, BW), 0.0, tl.float32)
        eyy = tl.full((BH, BW), 0.0, tl.float32)
        exy = tl.full((BH, BW), 0.0, tl.float32)
        for i in tl.static_range(KH):
            if KH > 1:
                wi = tl.load(win_ptr + i)
            else:
                wi = 1.0
            xv = tl.load(px + i * sxh, mask=inside, other=0.0).to(tl.float32)
            yv = tl.load(py + i * syh, mask=inside, other=0.0).to(tl.float32)
            mx += wi * xv
            my += wi * yv
            exx += wi * (xv * xv)
            eyy += wi * (yv * yv)
            exy += wi * (xv * yv)
        n = planes * out_h * width
        at = plane * out_h * width + rows[:, None] * width + cols[None, :]
        tl.store(v_ptr + at, mx, mask=inside)
        tl.store(v_ptr + n + at, my, mask=inside)
        tl.store(v_ptr + 2 * n + at, exx, mask=inside)
        tl.store(v_ptr + 3 * n + at, eyy, mask=inside)
        tl.store(v_ptr + 4 * n + at, exy, mask=inside)

    @triton.jit
    def blur_width_ssim(
        v_ptr, win_ptr, map_ptr, dmx_ptr, dmy_ptr, de_ptr, dexy_ptr, planes, out_h, width, out_w, c1, c2,
        KW: tl.constexpr, WANT_DMX: tl.constexpr, BH: tl.constexpr, BW: tl.constexpr,
    ):  # fmt: skip
        plane = tl.program_id(2)
        rows = tl.program_id(0) * BH + tl.arange(0, BH)
        cols = tl.program_id(1) * BW + tl.arange(0, BW)
        inside = (rows[:, None] < out_h) & (cols[None, :] < out_w)
        n = planes * out_h * width
        pv = v_ptr + plane * out_h * width + rows[:, None] * width + cols[None, :]
        mx = tl.full((BH, BW), 0.0, tl.float32)
        my = tl.full((BH, BW), 0.0, tl.float32)
        exx = tl.full((BH, BW), 0.0, tl.float32)
        eyy = tl.full((BH, BW), 0.0, tl.float32)
        exy = tl.full((BH, BW), 0.0, tl.float32)
        for j in tl.static_range(KW):
            if KW > 1:
                wj = tl.load(win_ptr + j)
            else:
                wj = 1.0
            mx += wj * tl.load(pv + j, mask=inside, other=0.0)
            my += wj * tl.load(pv + n + j, mask=inside, other=0.0)
            exx += wj * tl.load(pv + 2 * n + j, mask=inside, other=0.0)
            eyy += wj * tl.load(pv + 3 * n + j, mask=inside, other=0.0)
            exy += wj * tl.load(pv + 4 * n + j, mask=inside, other=0.0)
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
        at = plane * out_h * out_w + rows[:, None] * out_w + cols[None, :]
        tl.store(map_ptr + at, s, mask=inside)
        tl.store(dmy_ptr + at, 2.0 * mx * (a2 - a1) * inv - 2.0 * my * s * spread, mask=inside)
        if WANT_DMX:
            tl.store(dmx_ptr + at, 2.0 * my * (a2 - a1) * inv - 2.0 * mx * s * spread, mask=inside)
        tl.store(de_ptr + at, -s / b2, mask=inside)
        tl.store(dexy_ptr + at, 2.0 * a1 * inv, mask=inside)

    @triton.jit
    def unblur_width(
        dmx_ptr, dmy_ptr, de_ptr, dexy_ptr, win_ptr, u_ptr, planes, out_h, out_w, width,
        KW: tl.constexpr, WANT_GX: tl.constexpr, WANT_GY: tl.constexpr, MX_SLOT: tl.constexpr, BH: tl.constexpr,
        BW: tl.constexpr,
    ):  # fmt: skip
        # u[k, plane, h, w] = sum_j win[j] d_k[h, w - j] over the map's columns; slots e, exy, my (if wanted), mx.
        plane = tl.program_id(2)
        rows = tl.program_id(0) * BH + tl.arange(0, BH)
        cols = tl.program_id(1) * BW + tl.arange(0, BW)
        inside = (rows[:, None] < out_h) & (cols[None, :] < width)
        base = plane * out_h * out_w + rows[:, None] * out_w + cols[None, :]
        g_e = tl.full((BH, BW), 0.0, tl.float32)
        g_exy = tl.full((BH, BW), 0.0, tl.float32)
        g_my = tl.full((BH, BW), 0.0, tl.float32)
        g_mx = tl.full((BH, BW), 0.0, tl.float32)
        for j in tl.static_range(KW):
            if KW > 1:
                wj = tl.load(win_ptr + j)
            else:
                wj = 1.0
            hit = inside & (cols[None, :] >= j) & (cols[None, :] - j < out_w)
            g_e += wj * tl.load(de_ptr + base - j, mask=hit, other=0.0)
            g_exy += wj * tl.load(dexy_ptr + base - j, mask=hit, other=0.0)
            if WANT_GY:
                g_my += wj * tl.load(dmy_ptr + base - j, mask=hit, other=0.0)
            if WANT_GX:
                g_mx += wj * tl.load(dmx_ptr + base - j, mask=hit, other=0.0)
        n = planes * out_h * width
        at = plane * out_h * width + rows[:, None] * width + cols[None, :]
        tl.store(u_ptr + at, g_e, mask=inside)
        tl.store(u_ptr + n + at, g_exy, mask=inside)
        if WANT_GY:
            tl.store(u_ptr + 2 * n + at, g_my, mask=inside)
        if WANT_GX:
            tl.store(u_ptr + MX_SLOT * n + at, g_mx, mask=inside)

    @triton.jit
    def unblur_height_grad(
        u_ptr, x_ptr, y_ptr, win_ptr, gx_ptr, gy_ptr, scale_ptr, channels, sxb, sxc, sxh, sxw, syb, syc, syh, syw,
        planes, height, width, out_h,
        KH: tl.constexpr, WANT_GX: tl.constexpr, WANT_GY: tl.constexpr, MX_SLOT: tl.constexpr, BH: tl.constexpr,
        BW: tl.constexpr,
    ):  # fmt: skip
        plane = tl.program_id(2)
        b = plane // channels
        c = plane % channels
        rows = tl.program_id(0) * BH + tl.arange(0, BH)
        cols = tl.program_id(1) * BW + tl.arange(0, BW)
        inside = (rows[:, None] < height) & (cols[None, :] < width)
        n = planes * out_h * width
        base = plane * out_h * width + rows[:, None] * width + cols[None, :]
        g_e = tl.full((BH, BW), 0.0, tl.float32)
        g_exy = tl.full((BH, BW), 0.0, tl.float32)
        g_my = tl.full((BH, BW), 0.0, tl.float32)
        g_mx = tl.full((BH, BW), 0.0, tl.float32)
        for i in tl.static_range(KH):
            if KH > 1:
                wi = tl.load(win_ptr + i)
            else:
                wi = 1.0
            hit = inside & (rows[:, None] >= i) & (rows[:, None] - i < out_h)
            at = base - i * width
            g_e += wi * tl.load(u_ptr + at, mask=hit, other=0.0)
            g_exy += wi * tl.load(u_ptr + n + at, mask=hit, other=0.0)
            if WANT_GY:
                g_my += wi * tl.load(u_ptr + 2 * n + at, mask=hit, other=0.0)
            if WANT_GX:
                g_mx += wi * tl.load(u_ptr + MX_SLOT * n + at, mask=hit, other=0.0)
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

    return blur_height, blur_width_ssim, unblur_width, unblur_height_grad


def _taps(size: int, length: int) -> int:
    """The window's taps along an axis of `length` pixels: none (1) where the image is shorter than the window."""
    return size if length >= size else 1


def _grid(rows: int, cols: int, planes: int) -> Tuple[int, int, int]:
    return (-(-rows // BLOCK_H), -(-cols // BLOCK_W), planes)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, y: Tensor, window: Tensor, c1: float, c2: float) -> Tensor:
        blur_height, blur_width_ssim, _, _ = _kernels()
        bsz, channels, height, width = x.shape
        kh, kw = _taps(window.numel(), height), _taps(window.numel(), width)
        out_h, out_w = height - kh + 1, width - kw + 1
        planes = bsz * channels
        f32 = dict(device=x.device, dtype=torch.float32)
        win = window.to(**f32).contiguous()
        blurred = torch.empty(5, planes, out_h, width, **f32)
        blur_height[_grid(out_h, width, planes)](
            x, y, win, blurred, channels, *x.stride(), *y.stride(), planes, out_h, width,
            KH=kh, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        want_dmx = bool(ctx.needs_input_grad[0])
        ssim_map, dmy, de, dexy = (torch.empty(planes, out_h, out_w, **f32) for _ in range(4))
        dmx = torch.empty(planes, out_h, out_w, **f32) if want_dmx else dmy  # a placeholder pointer when unused
        blur_width_ssim[_grid(out_h, out_w, planes)](
            blurred, win, ssim_map, dmx, dmy, de, dexy, planes, out_h, width, out_w, c1, c2,
            KW=kw, WANT_DMX=want_dmx, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        ctx.save_for_backward(x, y, win, dmx, dmy, de, dexy)
        ctx.taps = (kh, kw)
        ctx.count = ssim_map.numel()
        return ssim_map.mean().to(x.dtype)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tuple[Optional[Tensor], ...]:
        _, _, unblur_width, unblur_height_grad = _kernels()
        x, y, win, dmx, dmy, de, dexy = ctx.saved_tensors
        want_gx, want_gy = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        if not (want_gx or want_gy):
            return None, None, None, None, None
        bsz, channels, height, width = x.shape
        kh, kw = ctx.taps
        out_h, out_w = height - kh + 1, width - kw + 1
        planes = bsz * channels
        f32 = dict(device=x.device, dtype=torch.float32)
        spread = torch.empty(2 + want_gx + want_gy, planes, out_h, width, **f32)
        unblur_width[_grid(out_h, width, planes)](
            dmx, dmy, de, dexy, win, spread, planes, out_h, out_w, width,
            KW=kw, WANT_GX=want_gx, WANT_GY=want_gy, MX_SLOT=2 + want_gy, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        gx = torch.empty(bsz, channels, height, width, **f32) if want_gx else spread
        gy = torch.empty(bsz, channels, height, width, **f32) if want_gy else spread
        # The incoming gradient stays on the device (no host read): the kernel loads it.
        scale = (grad.to(torch.float32) / ctx.count).reshape(1)
        unblur_height_grad[_grid(height, width, planes)](
            spread, x, y, win, gx, gy, scale, channels, *x.stride(), *y.stride(), planes, height, width, out_h,
            KH=kh, WANT_GX=want_gx, WANT_GY=want_gy, MX_SLOT=2 + want_gy, BH=BLOCK_H, BW=BLOCK_W,
        )  # fmt: skip
        return (
            gx.to(x.dtype) if want_gx else None,
            gy.to(y.dtype) if want_gy else None,
            None,
            None,
            None,
        )


def fused_ssim(x: Tensor, y: Tensor, window: Tensor, data_range: float = 1.0) -> Tensor:
    """Mean SSIM of two [B, C, H, W] batches of one shape with the 1-D `window`, through the four kernels
    (`available(x)` must hold). Gradients flow to whichever of x and y requires them."""
    if x.shape != y.shape or x.dim() != 4:
        raise ValueError(f"SSIM takes two [B, C, H, W] batches of one shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    c1 = (0.01 * float(data_range)) ** 2
    c2 = (0.03 * float(data_range)) ** 2
    return _FusedSSIM.apply(x, y, window, c1, c2)
