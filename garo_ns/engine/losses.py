"""The training loss and metric of one step, computed without waiting for the GPU.

Splatfacto's loss (L1 and SSIM, optionally its scale regulariser) and its training PSNR, written so that a step
on CUDA never copies to or from the host: splatfacto builds host tensors for the zero regulariser and torchmetrics
counts pixels in a host-built tensor, and each of these waits for the GPU to finish its queue. A non-finite loss
still stops training before a checkpoint can keep it (`NonFiniteWatch`).
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.engine.ssim import SSIM
from garo_ns.errors import GaroTrainingError
from garo_ns.ops.collector import collector_paused


def image_loss(gt: Tensor, pred: Tensor, ssim: SSIM, ssim_lambda: float) -> Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of two [H, W, 3] images, splatfacto's `main_loss`."""
    l1 = torch.abs(gt - pred).mean()
    similarity = ssim(gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None])
    return (1 - ssim_lambda) * l1 + ssim_lambda * (1 - similarity)


def scale_regularisation(log_scales: Tensor, max_ratio: float) -> Tensor:
    """Splatfacto's scale regulariser: 0.1 x the mean excess of each Gaussian's largest-to-smallest scale ratio
    over `max_ratio`."""
    scales = torch.exp(log_scales)
    return 0.1 * torch.clamp_min(scales.amax(dim=-1) / scales.amin(dim=-1) - max_ratio, 0.0).mean()


def psnr(pred: Tensor, gt: Tensor) -> Tensor:
    """PSNR in dB of `pred` against `gt` for values in [0, 1] (a tensor on their device)."""
    return -10.0 * torch.log10(torch.mean((pred - gt) ** 2))


class ImageLoss:
    """`image_loss` of a training step. With `graphed`, on CUDA and with gradients, it replays a CUDA graph of its
    forward and backward captured for each image shape (torch.cuda.make_graphed_callables): the same kernels, one
    launch. Anywhere else it runs eagerly."""

    def __init__(self, ssim: SSIM, ssim_lambda: float, graphed: bool = False) -> None:
        self.ssim, self.ssim_lambda, self.graphed = ssim, float(ssim_lambda), bool(graphed)
        self.graphs: Dict[Tuple[Any, ...], Callable[..., Tensor]] = {}

    def eager(self, gt: Tensor, pred: Tensor) -> Tensor:
        return image_loss(gt, pred, self.ssim, self.ssim_lambda)

    def __call__(self, gt: Tensor, pred: Tensor) -> Tensor:
        if not (self.graphed and pred.is_cuda and pred.requires_grad and torch.is_grad_enabled()):
            return self.eager(gt, pred)
        key = (tuple(pred.shape), pred.dtype, pred.device, tuple(gt.shape), gt.dtype)
        if key not in self.graphs:
            samples = (gt.detach().clone(), pred.detach().clone().requires_grad_(True))
            with collector_paused():
                self.graphs[key] = torch.cuda.make_graphed_callables(self.eager, samples)
        return self.graphs[key](gt.detach(), pred)


class NonFiniteWatch:
    """Stops training on a non-finite loss: on the CPU at the step itself; on CUDA the first such step is kept on the
    device and read every `every` steps and before every checkpoint (`check`), so that no step waits for the GPU.
    Steps after it train on NaN, but nothing of them is saved: the error names the step where it began."""

    def __init__(self, every: int = 50, defer: Optional[bool] = None) -> None:
        self.every = max(int(every), 1)
        self.defer = defer  # None: on CUDA only (a read on the CPU waits for nothing)
        self.first_bad: Optional[Tensor] = None

    def observe(self, loss: Tensor, step: int) -> None:
        bad = ~torch.isfinite(loss.detach())
        if not (loss.is_cuda if self.defer is None else self.defer):
            if bool(bad):
                raise self.error(step)
            return
        if self.first_bad is None:
            self.first_bad = torch.full((), -1, dtype=torch.int64, device=loss.device)
        self.first_bad = torch.where(bad & (self.first_bad < 0), step, self.first_bad)
        if step % self.every == 0:
            self.check()

    def check(self) -> None:
        """Raise if a step since the last check had a non-finite loss (one read of the device)."""
        if self.first_bad is not None:
            first = int(self.first_bad)
            self.first_bad = None
            if first >= 0:
                raise self.error(first)

    @staticmethod
    def error(step: int) -> GaroTrainingError:
        return GaroTrainingError(f"non-finite loss at step {step}; training stopped, earlier checkpoints are kept")


def step_losses(
    gt: Tensor,
    pred: Tensor,
    loss: Callable[[Tensor, Tensor], Tensor],
    mask: Optional[Tensor] = None,
    log_scales: Optional[Tensor] = None,
    max_ratio: float = 10.0,
) -> Dict[str, Tensor]:
    """`main_loss` (`loss(gt, pred)`, e.g. an `ImageLoss`) and `scale_reg` of one view as splatfacto defines them;
    `mask` [H, W, 1] blacks out both images where it is 0; `log_scales` given: the scale regulariser is added (else
    a zero on the images' device)."""
    if mask is not None:
        gt, pred = gt * mask, pred * mask
    reg = torch.zeros((), device=pred.device) if log_scales is None else scale_regularisation(log_scales, max_ratio)
    return {"main_loss": loss(gt, pred), "scale_reg": reg}
