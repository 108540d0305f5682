"""The fused SSIM kernels (garo_ns.engine.fused_ssim) against the convolutions' SSIM in float64: on the CPU through
Triton's interpreter, on CUDA compiled (the training image size, and inside the loss's CUDA graph)."""

from __future__ import annotations

import importlib.util

import pytest
import torch

from garo_ns.engine import fused_ssim
from garo_ns.engine.losses import ImageLoss, image_loss
from garo_ns.engine.ssim import SSIM

needs_triton = pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="Triton is not installed")


def _pair(shape, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g)
    y = (x + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1)
    return x.to(device), y.to(device)


def _reference(x, y):
    """Value and both gradients of the convolutions' SSIM in float64."""
    xd = x.detach().double().cpu().requires_grad_(True)
    yd = y.detach().double().cpu().requires_grad_(True)
    value = SSIM().double()(xd, yd)
    gx, gy = torch.autograd.grad(value, (xd, yd))
    return float(value.detach()), gx, gy


def _error(got, want):
    """Largest difference relative to the largest entry of `want`."""
    return float((got.detach().double().cpu() - want).abs().max() / want.abs().max())


@pytest.fixture
def interpreter(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "1")


# Both axes blurred (two tiles along the width), the height under the window (blurred along the width only, as
# pytorch_msssim does), and neither axis blurred. fp32 with sums in another order: the convolutions' own fp32
# error against float64 here is up to 5e-7 (value) and 3.5e-5 (gradient, unblurred tiny images: cancellations).
@needs_triton
@pytest.mark.parametrize(
    "shape, grad_tol", [((1, 3, 20, 45), 4e-6), ((2, 2, 9, 21), 4e-6), ((1, 1, 6, 7), 2e-4)], ids=str
)
def test_fused_ssim_is_the_convolutions_value_and_gradients(interpreter, shape, grad_tol):
    x, y = _pair(shape)
    x.requires_grad_(True)
    y.requires_grad_(True)
    want, gx_want, gy_want = _reference(x, y)
    assert fused_ssim.available(x)
    got = fused_ssim.fused_ssim(x, y, SSIM().window)
    assert got.grad_fn is not None and "Fused" in type(got.grad_fn).__name__
    gx, gy = torch.autograd.grad(got, (x, y))
    assert abs(float(got) - want) < 1e-6
    assert _error(gx, gx_want) < grad_tol
    assert _error(gy, gy_want) < grad_tol


@needs_triton
def test_fused_ssim_takes_the_loss_layout_and_one_gradient(interpreter):
    """The loss passes [H, W, 3] images permuted to [1, 3, H, W] (strided), the ground truth without a gradient."""
    gt_hw, pred_hw = (t[0].permute(1, 2, 0).contiguous() for t in _pair((1, 3, 17, 40), seed=3))
    pred_hw.requires_grad_(True)
    gt, pred = gt_hw.permute(2, 0, 1)[None], pred_hw.permute(2, 0, 1)[None]
    assert not pred.is_contiguous()
    want, _, gy_want = _reference(gt, pred)
    loss = SSIM(fused=True)
    got = loss(gt, pred)
    assert "Fused" in type(got.grad_fn).__name__  # the module took the kernels
    (g,) = torch.autograd.grad(got, pred_hw)
    assert abs(float(got) - want) < 1e-6
    assert _error(g.permute(2, 0, 1)[None], gy_want) < 4e-6
    # The whole loss term through ImageLoss: the same as with the convolutions.
    lam = 0.2
    ref = image_loss(gt_hw, pred_hw, SSIM(), lam)
    assert abs(float(ImageLoss(loss, lam)(gt_hw, pred_hw)) - float(ref)) < 1e-6


def test_without_the_kernels_the_fused_setting_uses_the_convolutions(monkeypatch):
    """On the CPU outside the interpreter (as in training without CUDA) `fused=True` blurs with the convolutions."""
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    x, y = _pair((1, 3, 20, 20))
    y.requires_grad_(True)
    assert not fused_ssim.available(x)
    got = SSIM(fused=True)(x, y)
    assert "Fused" not in type(got.grad_fn).__name__
    assert abs(float(got) - float(SSIM()(x, y))) == 0.0


def test_fused_ssim_refuses_images_of_two_shapes():
    with pytest.raises(ValueError, match="one shape"):
        fused_ssim.fused_ssim(torch.rand(1, 3, 20, 20), torch.rand(1, 3, 20, 21), SSIM().window)


cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@cuda
@needs_triton
def test_fused_ssim_on_cuda_at_the_training_size():
    """800 x 800 x 3 compiled on the GPU: value within 1e-6 of float64, gradient within 4e-6 of its largest entry."""
    gt, pred = _pair((1, 3, 800, 800), seed=5, device="cuda")
    pred.requires_grad_(True)
    want, _, gy_want = _reference(gt, pred)
    got = SSIM(fused=True).cuda()(gt, pred)
    assert "Fused" in type(got.grad_fn).__name__
    (g,) = torch.autograd.grad(got, pred)
    assert abs(float(got) - want) < 1e-6
    assert _error(g, gy_want) < 4e-6


@cuda
@needs_triton
def test_fused_ssim_inside_the_loss_cuda_graph():
    """The graphed loss (captured and replayed) gives the eager convolutions' loss and gradient on new images."""
    fused_loss = ImageLoss(SSIM(fused=True).cuda(), 0.2, graphed=True)
    plain = SSIM().cuda()
    for seed in range(3):  # capture, then replays with other images
        gt, pred = (t[0].permute(1, 2, 0).contiguous() for t in _pair((1, 3, 120, 160), seed=seed, device="cuda"))
        pred.requires_grad_(True)
        got = fused_loss(gt, pred)
        (g,) = torch.autograd.grad(got, pred)
        p2 = pred.detach().clone().requires_grad_(True)
        want = image_loss(gt, p2, plain, 0.2)
        (g_want,) = torch.autograd.grad(want, p2)
        assert abs(float(got) - float(want)) < 1e-6
        assert float((g - g_want).abs().max()) <= 4e-6 * float(g_want.abs().max())
    assert len(fused_loss.graphs) == 1
