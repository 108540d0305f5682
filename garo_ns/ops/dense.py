"""The deformation MLP's layers as products shaped for tensor cores.

Profiled in training (bf16, an H100 and an H200), `nn.Linear` left a third of the field's GPU time outside its
matrix products: the bias gradient as a column reduction over every Gaussian (`grad.sum(0)`, the costliest event
after the rasterizer's backward), the ReLU as kernels of its own each way, and the odd input widths of two layers
(93 and 349 with the time network) and the three narrow heads (3, 4, 3 outputs) on slow unaligned kernels. `dense`
keeps each layer's sums and moves that work into the products: the bias and the ReLU into the product's epilogue,
the bias gradient into a matrix-vector product. `aligned` gives the zero padding that makes a width a multiple of 8.
The same code runs on the CPU in fp32 (tests/test_dense.py).
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

import torch
from torch import Tensor

ALIGN = 8
"""Widths that are a multiple of this (16 bytes of bf16) get cuBLAS's aligned tensor-core kernels."""


def aligned(width: int, multiple: int = ALIGN) -> int:
    """The zero columns that bring `width` to a multiple of `multiple`."""
    return -width % multiple


def _product_dtype(x: Tensor) -> Optional[torch.dtype]:
    """The autocast dtype for `x`'s device where autocast is on there, else None (the inputs' own dtype)."""
    kind = x.device.type
    return torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else None


def _addmm_relu(bias: Tensor, x: Tensor, weight_t: Tensor) -> Tensor:
    """relu(bias + x @ weight_t), the ReLU in the product's epilogue where torch offers it (cuBLASLt on CUDA)."""
    fused = getattr(torch, "_addmm_activation", None)  # a private op: a torch without it gets the two steps
    return fused(bias, x, weight_t) if fused is not None else torch.relu(torch.addmm(bias, x, weight_t))


class _Dense(torch.autograd.Function):
    """x @ W^T + b, optionally through a ReLU, with the bias gradient as a matrix-vector product."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, weight: Tensor, bias: Tensor, relu: bool) -> Tensor:  # type: ignore[override]
        dtype = _product_dtype(x)
        ctx.dtypes = (x.dtype, weight.dtype, bias.dtype)
        if dtype is not None:  # autocast's cast, done here because autocast does not reach into a Function
            x, weight, bias = x.to(dtype), weight.to(dtype), bias.to(dtype)
        with torch.autocast(x.device.type, enabled=False):
            y = _addmm_relu(bias, x, weight.t()) if relu else torch.addmm(bias, x, weight.t())
        ctx.relu = relu
        ctx.save_for_backward(x, weight, y if relu else None)
        return y

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> Tuple[Optional[Tensor], ...]:  # type: ignore[override]
        x, weight, y = ctx.saved_tensors
        grad = grad.to(x.dtype)
        if ctx.relu:  # ReLU's gradient: through where the output is positive, as torch's own ReLU
            grad = torch.ops.aten.threshold_backward(grad, y, 0)
        x_dtype, w_dtype, b_dtype = ctx.dtypes
        need_x, need_w, need_b, _ = ctx.needs_input_grad
        grad_x = (grad @ weight).to(x_dtype) if need_x else None
        grad_w = (grad.t() @ x).to(w_dtype) if need_w else None
        # A column sum over every Gaussian as a product with ones: tensor cores at memory speed, where torch's
        # reduction kernel for this shape ran at a fifth of it.
        grad_b = (grad.t() @ grad.new_ones(grad.shape[0])).to(b_dtype) if need_b else None
        return grad_x, grad_w, grad_b, None


def dense(x: Tensor, weight: Tensor, bias: Tensor, relu: bool = False) -> Tensor:
    """`F.linear(x, weight, bias)` (then `relu` if asked) for `x` [N, in], `weight` [out, in], `bias` [out], under
    autocast as `F.linear` is (its dtype on its device) and fp32 elsewhere; the same sums up to their order."""
    return _Dense.apply(x, weight, bias, relu)
