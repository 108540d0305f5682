"""Image metrics that must work offline."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Dict, Optional, Tuple

import torch
from torch import Tensor

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
# AlexNet's strided first layer and two poolings leave nothing of an image under 31 pixels a side (torch raises
# "Output size is too small"): LPIPS is left out below this, as where its weights are missing.
LPIPS_MIN_SIDE = 32
_warned = False


def lpips_backbone_path() -> Path:
    """Where torchvision looks for the AlexNet weights LPIPS needs ($TORCH_HOME/hub/checkpoints)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def make_lpips() -> Optional[torch.nn.Module]:
    """torchmetrics' LPIPS (AlexNet) when its backbone is on disk, else None with one warning.

    Never downloads: without the file, LPIPS is left out instead of hanging on the network.
    """
    global _warned
    if not lpips_backbone_path().exists() and os.environ.get("GARO_LPIPS_DOWNLOAD") != "1":
        if not _warned:
            warnings.warn(
                f"LPIPS disabled: backbone weights not found at {lpips_backbone_path()} "
                "(place them there, or set TORCH_HOME); PSNR and SSIM are still computed",
                stacklevel=2,
            )
            _warned = True
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    return LearnedPerceptualImagePatchSimilarity(net_type="alex", normalize=True)


def lpips_fits(image: Tensor) -> bool:
    """Whether LPIPS's AlexNet can take an image [..., H, W, 3] (each side at least `LPIPS_MIN_SIDE` pixels)."""
    return min(int(image.shape[-3]), int(image.shape[-2])) >= LPIPS_MIN_SIDE


def metric_modules() -> Tuple[torch.nn.Module, torch.nn.Module, Optional[torch.nn.Module]]:
    """PSNR and SSIM as splatfacto scores them (data range 1), and LPIPS where `make_lpips` can."""
    from torchmetrics.image import PeakSignalNoiseRatio

    from garo_ns.engine.ssim import SSIM  # splatfacto's SSIM (pytorch_msssim's definition) in fewer kernels

    return PeakSignalNoiseRatio(data_range=1.0), SSIM(data_range=1.0), make_lpips()


def image_metrics(
    gt: Tensor, pred: Tensor, psnr: torch.nn.Module, ssim: torch.nn.Module, lpips: Optional[torch.nn.Module]
) -> Dict[str, float]:
    """PSNR, SSIM and (where available) LPIPS of one render `pred` against `gt`, both [H, W, 3]."""
    gt_b, pred_b = torch.moveaxis(gt, -1, 0)[None], torch.moveaxis(pred, -1, 0)[None]
    metrics = {"psnr": float(psnr(gt_b, pred_b).item()), "ssim": float(ssim(gt_b, pred_b))}
    if lpips is not None and lpips_fits(pred):
        metrics["lpips"] = float(lpips.to(pred.device)(gt_b.clamp(0, 1), pred_b.clamp(0, 1)))
    return metrics
