"""Quaternions as rotations: shared by the normals of GARO and the reference rasterizer."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of (w, x, y, z) quaternions; normalised here, a zero quaternion gives I."""
    q = F.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    w = w + (q.abs().sum(-1) == 0).to(q.dtype)  # the zero quaternion reads as the identity rotation
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rot.reshape(q.shape[:-1] + (3, 3))
