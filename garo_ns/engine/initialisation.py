"""The Gaussians a training starts from, as 3DGS and D-3DGS initialise them.

Seed points (with their colours) or, for synthetic scenes, random points in a cube; each Gaussian
isotropic with the RMS distance to its 3 nearest neighbours as scale, identity rotation, opacity
0.1. Random points start nearly grey, with a fixed seed, so two runs start from the same points.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np
import torch
from torch import Tensor

from garo_ns.render.sh import num_sh_bases, rgb_to_dc


def nearest_distances(points: Tensor, k: int) -> np.ndarray:
    """Distances [N, k] (float32) from every point to its `k` nearest other points (sklearn, exact)."""
    from sklearn.neighbors import NearestNeighbors

    x = points.cpu().numpy()
    distances, _ = NearestNeighbors(n_neighbors=k + 1, algorithm="auto", metric="euclidean").fit(x).kneighbors(x)
    return distances[:, 1:].astype(np.float32)  # the first neighbour is the point itself


def initial_gaussians(
    seed_points: Optional[Tuple[Tensor, Tensor]],
    random_init: bool,
    num_random: int,
    random_scale: float,
    sh_degree: int,
) -> Dict[str, Tensor]:
    """The starting Gaussians, keyed as splatfacto's `gauss_params`.

    Args:
        seed_points: the dataparser's (positions [N, 3], colours [N, 3] in 0..255, possibly empty), or None.
        random_init: use random points even when there are seed points.
        num_random: number of random points, uniform in a cube of edge `random_scale` centred at the origin.
        random_scale: edge of that cube.
        sh_degree: SH degree of the colours (the higher coefficients start at zero).

    Raises ValueError with fewer than 4 points (3 neighbours each are needed for the scale).
    """
    if seed_points is not None and not random_init and len(seed_points[0]) > 0:
        means = seed_points[0].float()
        colors = seed_points[1].float() / 255.0 if seed_points[1].shape[0] > 0 else None
    else:
        means = (torch.rand((num_random, 3), generator=torch.Generator().manual_seed(0)) - 0.5) * random_scale
        colors = None
    n = means.shape[0]
    if n < 4:
        raise ValueError(f"need at least 4 initial Gaussians, got {n}")
    rms = torch.from_numpy(nearest_distances(means, 3)).float().pow(2).mean(-1, keepdim=True).sqrt()
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    if colors is not None:
        features_dc = rgb_to_dc(colors)
    else:
        features_dc = torch.rand(n, 3, generator=torch.Generator().manual_seed(1)) / 255.0
    return {
        "means": means,
        "scales": torch.log(rms.clamp_min(1e-7)).repeat(1, 3),
        "quats": quats,
        "features_dc": features_dc,
        "features_rest": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3),
        "opacities": torch.logit(torch.full((n, 1), 0.1)),
    }
