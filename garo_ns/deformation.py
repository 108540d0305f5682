"""Time-conditioned deformation field of D-3DGS (Yang et al., CVPR 2024).

An MLP of positional encodings of a Gaussian's canonical position and of time predicts offsets
of its position, rotation (quaternion) and log-scale at that time.
"""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor, nn


def positional_encoding(x: Tensor, n_freqs: int) -> Tensor:
    """[x, sin(2^k x), cos(2^k x) for k < n_freqs] along the last axis: D * (1 + 2 n_freqs) features."""
    if n_freqs == 0:
        return x
    freqs = 2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)
    angles = (x[..., None, :] * freqs[:, None]).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class DeformationField(nn.Module):
    """D-3DGS's deformation MLP: `depth` ReLU layers of `width` with the input re-injected after
    layer `skip`, and three linear heads for position, rotation and scale offsets.

    The heads start at zero, so the deformation starts as the identity when it is switched on
    after the static warm-up, and training continues smoothly from the canonical Gaussians.
    """

    def __init__(self, pos_freqs: int = 10, time_freqs: int = 6, depth: int = 8, width: int = 256, skip: int = 4):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"depth and width must be >= 1, got depth={depth}, width={width}")
        self.pos_freqs, self.time_freqs, self.skip = pos_freqs, time_freqs, skip
        in_dim = 3 * (1 + 2 * pos_freqs) + (1 + 2 * time_freqs)
        layers = [nn.Linear(in_dim, width)]
        for i in range(depth - 1):
            layers.append(nn.Linear(width + (in_dim if i == skip else 0), width))
        self.layers = nn.ModuleList(layers)
        self.d_xyz = nn.Linear(width, 3)
        self.d_rot = nn.Linear(width, 4)
        self.d_scale = nn.Linear(width, 3)
        for head in (self.d_xyz, self.d_rot, self.d_scale):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, xyz: Tensor, time: Tensor | float) -> Tuple[Tensor, Tensor, Tensor]:
        """Offsets at `time` for canonical positions `xyz` [N, 3].

        Args:
            xyz: canonical positions (the caller detaches them, as D-3DGS does).
            time: a scalar or an [N, 1] tensor in [0, 1].

        Returns:
            d_xyz [N, 3], d_rot [N, 4], d_log_scale [N, 3].
        """
        t = torch.as_tensor(time, dtype=xyz.dtype, device=xyz.device)
        t = t.reshape(-1, 1).expand(xyz.shape[0], 1)
        x = torch.cat([positional_encoding(xyz, self.pos_freqs), positional_encoding(t, self.time_freqs)], dim=-1)
        h = x
        for i, layer in enumerate(self.layers):
            h = torch.relu(layer(h))
            if i == self.skip and i + 1 < len(self.layers):
                h = torch.cat([x, h], dim=-1)
        return self.d_xyz(h), self.d_rot(h), self.d_scale(h)
