"""How far a splat's alpha reaches before the rasterizer skips it.

gsplat's compositing (and the reference rasterizer's) skips a Gaussian at a pixel where its alpha,
opacity * exp(-sigma), is below 1/255. So a splat only ever shows inside the ellipse
sigma <= log(opacity * 255), which for a faint or small splat is far inside the 3-sigma square that
projection gives it. Tile lists built from that square hold (tile, Gaussian) pairs that sorting orders
and compositing walks only to skip; the box of the ellipse drops them and changes no pixel.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0
# Widening against rounding: the kernels evaluate exp() approximately and in fp32.
_REL_MARGIN, _ABS_MARGIN_PX = 1e-4, 1e-3


def reach_half_widths(conics: Tensor, opacities: Tensor, alpha_min: float = ALPHA_MIN) -> Tuple[Tensor, Tensor]:
    """Half-widths in x and y (pixels) of the box around the ellipse where a splat's alpha can reach `alpha_min`.

    Args:
        conics: [..., 3] the inverse 2D covariance (a, b, c) as projection returns it.
        opacities: [...] opacities in [0, 1], broadcastable to conics' leading shape.
        alpha_min: the skip threshold; at or below 0 nothing is skipped (infinite reach).

    Returns: (half_x, half_y), NaN where the splat can reach no pixel (opacity below `alpha_min`).
    """
    a, b, c = conics.unbind(-1)
    if alpha_min > 0:
        reach = 2.0 * torch.log(opacities / alpha_min)  # twice the largest sigma that passes; < 0: none
    else:
        reach = torch.full_like(a, math.inf)
    det = a * c - b * b
    # The ellipse d^T conic d <= reach spans sqrt(reach * cov_xx) in x; cov is the conic's inverse.
    half_x = torch.sqrt(reach * c / det) * (1 + _REL_MARGIN) + _ABS_MARGIN_PX
    half_y = torch.sqrt(reach * a / det) * (1 + _REL_MARGIN) + _ABS_MARGIN_PX
    return half_x, half_y


def reach_radii(radii: Tensor, conics: Tensor, opacities: Tensor, alpha_min: float = ALPHA_MIN) -> Tensor:
    """Radii for tile intersection: each splat's square shrunk to the box its alpha can reach, never grown.

    Args:
        radii: [C, N] integer radii from projection (0: culled).
        conics: [C, N, 3]; opacities: [N] or [C, N].

    Returns: [C, N] radii of `radii`'s dtype: 0 for a splat too faint to reach any pixel, the original radius
    where the box is not finite (a degenerate conic), else the smaller of the two.
    """
    half_x, half_y = reach_half_widths(conics, opacities.expand(radii.shape), alpha_min)
    snug = torch.ceil(torch.maximum(half_x, half_y))
    # A NaN box means no reach when the opacity is under the threshold, else a conic not to be trusted.
    faint = ~(opacities.expand(radii.shape) >= alpha_min) if alpha_min > 0 else torch.zeros_like(radii, dtype=bool)
    snug = torch.where(torch.isfinite(snug), snug, radii.to(snug.dtype))
    snug = torch.minimum(snug, radii.to(snug.dtype)).to(radii.dtype)
    return torch.where(faint, torch.zeros_like(radii), snug)
