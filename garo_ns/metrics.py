"""Image metrics that must work offline."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Optional

import torch

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
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
