"""Cameras: gsplat's world-to-camera convention, one view prepared for the rasterizer (from a nerfstudio
camera), and the scene extent that a set of cameras implies."""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, Optional, Union

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras


def viewmat_from_c2w(c2w: Tensor) -> Tensor:
    """World-to-camera [C, 4, 4] in gsplat's convention (OpenCV axes) from nerfstudio's c2w [C, 3, 4]."""
    # Flip the y and z axes (OpenGL to OpenCV) without a host-to-device copy of a sign vector.
    rot = torch.cat([c2w[:, :3, :1], -c2w[:, :3, 1:3]], dim=-1)
    rot_inv = rot.transpose(1, 2)
    view = torch.zeros(c2w.shape[0], 4, 4, device=c2w.device, dtype=c2w.dtype)
    view[:, :3, :3] = rot_inv
    view[:, :3, 3:4] = -rot_inv @ c2w[:, :3, 3:4]
    view[:, 3, 3] = 1.0
    return view


class RenderView(NamedTuple):
    """One camera as the rasterizer takes it, prepared once: world-to-camera [1, 4, 4] and
    intrinsics [1, 3, 3] on the render device, image size, and the time to deform to."""

    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    time: float


def camera_time(camera: "Cameras") -> Optional[float]:
    """The time in [0, 1] that `camera` (one) carries, or None when it carries none."""
    return None if camera.times is None else float(camera.times.reshape(-1)[0])


def camera_view(
    camera: "Cameras", c2w: Tensor, downscale: float, device: Union[str, torch.device], time: float
) -> RenderView:
    """`camera` (one) as the rasterizer takes it: posed by `c2w` [1, 3, 4] (its own pose, or one the
    camera optimizer corrected), its image `downscale`d, on `device`, at `time`."""
    camera.rescale_output_resolution(1 / downscale)
    K = camera.get_intrinsics_matrices().to(device)
    width, height = int(camera.width.item()), int(camera.height.item())
    camera.rescale_output_resolution(downscale)  # the camera is the caller's: leave it as it was
    return RenderView(viewmat_from_c2w(c2w.to(device)), K, width, height, time)


def camera_extent(c2w: np.ndarray) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their mean."""
    centres = c2w[:, :3, 3]
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=-1).max()) if len(centres) else 1.0
