"""What the model returns for one rendered camera (nerfstudio's outputs): the image on its background, the
depth where something was drawn, the accumulated opacity and the background."""

from __future__ import annotations

from typing import Dict, Optional

import torch
from torch import Tensor


def camera_outputs(
    render: Tensor, alpha: Tensor, background: Tensor, with_depth: bool, training: bool
) -> Dict[str, Optional[Tensor]]:
    """nerfstudio's outputs of one render: `render` [1, H, W, C] (colour, then the expected depth as a fourth
    channel `with_depth`), `alpha` [1, H, W, 1], `background` [3] on the render's device.

    Training: the colour stays unclamped, as D-3DGS's loss sees it (a clamp would stop the gradient of every
    over-bright pixel, and with it part of the densification signal), and the background stays [3]. Otherwise
    the colour is clamped to [0, 1] and the background expanded to [H, W, 3]. Where nothing was drawn, the depth
    is the frame's farthest."""
    rgb = render[..., :3] + (1 - alpha) * background
    rgb = rgb if training else torch.clamp(rgb, 0.0, 1.0)
    depth = None
    if with_depth:
        depth = render[..., 3:4]
        depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
    if not training:
        background = background.expand(alpha.shape[1], alpha.shape[2], 3)
    return {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}
