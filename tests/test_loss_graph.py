"""CUDA only: the image loss replayed from a CUDA graph gives the eager loss's value and gradient, call after call,
for new images each time and for each image size (benchmarks/device_run.sh gputests runs it)."""

from __future__ import annotations

import pytest
import torch

from garo_ns.losses import ImageLoss
from garo_ns.ssim import SSIM

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")


def _images(shape, seed):
    g = torch.Generator(device="cuda").manual_seed(seed)
    gt = torch.rand(shape, generator=g, device="cuda")
    pred = (gt + 0.1 * torch.randn(shape, generator=g, device="cuda")).clamp(0, 1).requires_grad_(True)
    return gt, pred


@pytest.mark.parametrize("shape", [(64, 80, 3), (800, 800, 3)])
def test_the_graphed_loss_is_the_eager_loss(shape):
    graphed = ImageLoss(SSIM().cuda(), 0.2, graphed=True)
    for seed in range(4):
        gt, pred = _images(shape, seed)
        loss = graphed(gt, pred)
        (grad,) = torch.autograd.grad(loss, pred)
        gt2, pred2 = _images(shape, seed)
        want = graphed.eager(gt2, pred2)
        (want_grad,) = torch.autograd.grad(want, pred2)
        assert torch.allclose(loss, want, rtol=1e-6, atol=1e-7)
        assert torch.allclose(grad, want_grad, rtol=1e-5, atol=1e-9)
    assert len(graphed.graphs) == 1  # captured once for this size


def test_a_second_size_gets_its_own_graph_and_evaluation_stays_eager():
    graphed = ImageLoss(SSIM().cuda(), 0.2, graphed=True)
    for shape in ((32, 48, 3), (48, 32, 3)):
        gt, pred = _images(shape, 0)
        graphed(gt, pred).backward()
        assert pred.grad is not None and pred.grad.abs().sum() > 0
    with torch.no_grad():
        gt, pred = _images((16, 16, 3), 1)
        graphed(gt, pred)
    assert len(graphed.graphs) == 2
