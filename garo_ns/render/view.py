"""Cameras: gsplat's world-to-camera convention, one view prepared for the rasterizer (from a nerfstudio
camera), and the scene extent that a set of cameras implies."""

from __future__ import annotations

from typing import TYPE_CHECKING, Dict, NamedTuple, Optional, Tuple, Union

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
    # -R^T c as a sum of products, not a matrix product: a training step allows cuBLAS TF32 (`deform_train_tf32`),
    # whose 10-bit inputs would move a camera 4 units from the origin by about 2e-3, half a pixel of its image.
    view[:, :3, 3] = -(rot_inv * c2w[:, None, :3, 3]).sum(-1)
    view[:, 3, 3] = 1.0
    return view


def camera_centres(viewmats: Tensor) -> Tensor:
    """Camera centres [C, 3] (-R^T t) of rigid world-to-camera matrices [C, 4, 4]; a sum of products, exact fp32
    whatever cuBLAS's TF32 setting (see viewmat_from_c2w)."""
    return -(viewmats[:, :3, :3] * viewmats[:, :3, 3:4]).sum(1)


class RenderView(NamedTuple):
    """One camera as the rasterizer takes it, prepared once: world-to-camera [1, 4, 4] and
    intrinsics [1, 3, 3] on the render device, image size, and the time to deform to."""

    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    time: float


def camera_numbers(
    camera: "Cameras", downscale: float = 1.0
) -> Tuple[Tuple[float, float, float, float], int, int, Optional[float]]:
    """(fx, fy, cx, cy), width, height of `camera` (one) with its image `downscale`d, and its time (None when
    it carries none), read in one device-to-host copy: each `.item()` or host-built tensor of a camera on the
    GPU would wait for the GPU (a training step read six). Same float32 arithmetic as nerfstudio's
    `rescale_output_resolution`, without changing the camera."""
    parts = [camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height]
    if camera.times is not None:
        parts.append(camera.times)
    host = torch.cat([p.reshape(-1)[:1].to(torch.float64) for p in parts]).cpu()
    s = torch.tensor(1.0 / downscale, dtype=torch.float32)
    scaled = host[:6].to(torch.float32) * s
    fx, fy, cx, cy = (float(v) for v in scaled[:4])
    width, height = int(torch.floor(scaled[4])), int(torch.floor(scaled[5]))
    time = float(host[6].to(torch.float32)) if camera.times is not None else None
    return (fx, fy, cx, cy), width, height, time


CameraNumbers = Tuple[Tuple[float, float, float, float], int, int, Optional[float]]


class HostCameras:
    """Cameras kept on the host (a dataset's) and their `camera_numbers`, read once per camera and downscale: a
    training step's camera is a device copy of one of them, whose numbers read there would wait for the GPU."""

    def __init__(self, cameras: "Cameras") -> None:
        self.cameras = cameras
        self._numbers: Dict[Tuple[int, float], CameraNumbers] = {}

    def numbers(self, index: int, downscale: float) -> Optional[CameraNumbers]:
        """`camera_numbers` of camera `index` (None when there is no such camera)."""
        if not 0 <= index < self.cameras.shape[0]:
            return None
        key = (index, float(downscale))
        if key not in self._numbers:
            self._numbers[key] = camera_numbers(self.cameras[index : index + 1], key[1])
        return self._numbers[key]


def camera_view(
    camera: "Cameras",
    c2w: Tensor,
    downscale: float,
    device: Union[str, torch.device],
    time: Optional[float],
    numbers: Optional[Tuple[Tuple[float, float, float, float], int, int, Optional[float]]] = None,
) -> RenderView:
    """`camera` (one) as the rasterizer takes it: posed by `c2w` [1, 3, 4] (its own pose, or one the
    camera optimizer corrected), its image `downscale`d, on `device`, at `time`. `numbers`: its
    `camera_numbers` at this downscale, when the caller has read them already."""
    (fx, fy, cx, cy), width, height, _ = camera_numbers(camera, downscale) if numbers is None else numbers
    K = torch.tensor([[[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]], dtype=torch.float32)
    K = K.pin_memory().to(device, non_blocking=True) if torch.device(device).type == "cuda" else K.to(device)
    return RenderView(viewmat_from_c2w(c2w.to(device)), K, width, height, float(time) if time is not None else 0.0)


def camera_extent(c2w: np.ndarray) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their mean."""
    centres = c2w[:, :3, 3]
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=-1).max()) if len(centres) else 1.0
