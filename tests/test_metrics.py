"""Scores of one render: LPIPS is left out of images too small for its AlexNet instead of failing the score (a
24-pixel scene's training run scored on a machine with the LPIPS weights stopped with torch's "Output size is too
small")."""

from __future__ import annotations

import torch

from garo_ns.engine.metrics import LPIPS_MIN_SIDE, image_metrics, lpips_fits
from garo_ns.engine.ssim import SSIM


class _Recorder(torch.nn.Module):
    """A stand-in LPIPS that records the shapes it was given."""

    def __init__(self) -> None:
        super().__init__()
        self.shapes = []

    def forward(self, a, b):
        self.shapes.append(tuple(a.shape))
        return torch.tensor(0.25)


def _psnr(gt, pred):
    return -10.0 * torch.log10(torch.mean((gt - pred) ** 2))


def test_lpips_is_left_out_of_images_under_its_smallest_side():
    lpips = _Recorder()
    for h, w, scored in ((24, 40, False), (40, 31, False), (LPIPS_MIN_SIDE, LPIPS_MIN_SIDE, True), (48, 64, True)):
        gt = torch.rand(h, w, 3)
        pred = (gt + 0.05).clamp(0, 1)
        assert lpips_fits(pred) is scored
        metrics = image_metrics(gt, pred, _psnr, SSIM(), lpips)
        assert ("lpips" in metrics) is scored
        assert metrics["psnr"] > 20 and 0 < metrics["ssim"] <= 1
    assert lpips.shapes == [(1, 3, 32, 32), (1, 3, 48, 64)]
