"""SSIM as splatfacto's loss and score define it, in fewer kernels.

The definition is pytorch_msssim's (11-tap Gaussian window of sigma 1.5 applied along height then width, valid
borders, K = (0.01, 0.03), the mean of the map over channels and pixels). pytorch_msssim blurs each of its five
maps (x, y, x^2, y^2, xy) with two convolutions of their own and copies its window to the device on every call, a
host wait in every training step; here the five maps are stacked and blurred by two grouped convolutions with the
window kept on the device. With `fused`, on CUDA (Triton), forward and backward are four kernels instead
(garo_ns.engine.fused_ssim): the same values to fp32 rounding.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from garo_ns.engine import fused_ssim


def gaussian_window(size: int = 11, sigma: float = 1.5) -> Tensor:
    """The normalised 1-D Gaussian window [size] (float32), as pytorch_msssim builds it."""
    coords = torch.arange(size, dtype=torch.float32) - size // 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    return g / g.sum()


class SSIM(nn.Module):
    """Mean SSIM of two image batches [B, C, H, W] with values in [0, `data_range`] (a scalar tensor).

    Images smaller than the window along an axis are not blurred along it (pytorch_msssim warns and does the same).
    `fused`: where `garo_ns.engine.fused_ssim` can run (CUDA with Triton), through its four kernels.
    """

    def __init__(
        self, data_range: float = 1.0, win_size: int = 11, win_sigma: float = 1.5, fused: bool = False
    ) -> None:
        super().__init__()
        self.data_range = float(data_range)
        self.fused = bool(fused)
        # Not saved with the model: fixed by the two numbers, and older checkpoints have no such entry.
        self.register_buffer("window", gaussian_window(win_size, win_sigma), persistent=False)

    def blur(self, maps: Tensor) -> Tensor:
        """`maps` [B, M, H, W] blurred by the window along height, then width (valid borders)."""
        m, size = maps.shape[1], self.window.numel()
        w = self.window.to(maps.dtype)
        out = maps
        if maps.shape[2] >= size:
            out = F.conv2d(out, w.view(1, 1, size, 1).expand(m, 1, size, 1), groups=m)
        if maps.shape[3] >= size:
            out = F.conv2d(out, w.view(1, 1, 1, size).expand(m, 1, 1, size), groups=m)
        return out

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        if x.shape != y.shape or x.dim() != 4:
            shapes = f"{tuple(x.shape)} and {tuple(y.shape)}"
            raise ValueError(f"SSIM takes two [B, C, H, W] batches of one shape, got {shapes}")
        if self.fused and fused_ssim.available(x):
            return fused_ssim.fused_ssim(x, y, self.window, self.data_range)
        c = x.shape[1]
        c1 = (0.01 * self.data_range) ** 2
        c2 = (0.03 * self.data_range) ** 2
        mu_x, mu_y, xx, yy, xy = self.blur(torch.cat([x, y, x * x, y * y, x * y], dim=1)).split(c, dim=1)
        mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
        contrast = (2 * (xy - mu_xy) + c2) / ((xx - mu_xx) + (yy - mu_yy) + c2)
        return (((2 * mu_xy + c1) / (mu_xx + mu_yy + c1)) * contrast).mean()
