"""How much each Gaussian matters to the training views: the score compaction removes the lowest of.

LightGaussian's global significance: a Gaussian's summed blending weight over every pixel of every
training view (here each view at its own time, so a Gaussian that shows only in some frames counts
for those), times its normalised volume to a small power. The blending weight alone already grows
with the splat's screen area; the volume term keeps large, faint Gaussians (backgrounds, fills)
ahead of tiny ones of the same weight.
"""

from __future__ import annotations

import torch
from torch import Tensor


def importance(contribution: Tensor, log_scales: Tensor, volume_beta: float) -> Tensor:
    """Score [N] of each Gaussian: contribution [N] x (volume / largest volume) ** volume_beta.

    `log_scales` [N, 3] are the stored (log) scales; the volume is their exponentiated sum, taken in
    log space and relative to the largest so it neither overflows nor underflows. Only the order of
    the scores matters; a Gaussian that contributes nothing scores 0 whatever its size.
    """
    if contribution.shape[0] != log_scales.shape[0]:
        raise ValueError(f"{contribution.shape[0]} contributions for {log_scales.shape[0]} Gaussians")
    if volume_beta == 0 or contribution.numel() == 0:
        return contribution.clone()
    log_volume = log_scales.detach().float().sum(-1)
    weight = torch.exp(volume_beta * (log_volume - log_volume.max()))
    return contribution * weight
