"""Real spherical harmonics up to degree 3, in the sign convention of 3DGS and gsplat."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients of a degree-`degree` expansion."""
    return (degree + 1) ** 2


def rgb_to_dc(rgb: Tensor) -> Tensor:
    """The degree-0 coefficient that renders colour `rgb` (in [0, 1]) from every direction."""
    return (rgb - 0.5) / _C0


def dc_to_rgb(dc: Tensor) -> Tensor:
    """The colour (unclamped) that the degree-0 coefficient `dc` renders: `rgb_to_dc`'s inverse."""
    return dc * _C0 + 0.5


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the basis functions at unit directions.

    Args:
        degree: 0 to 3.
        dirs: [..., 3] unit vectors.

    Returns:
        [..., (degree + 1) ** 2] basis values.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _C2[0] * x * y,
            _C2[1] * y * z,
            _C2[2] * (2.0 * zz - xx - yy),
            _C2[3] * x * z,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3.0 * xx - yy),
            _C3[1] * x * y * z,
            _C3[2] * y * (4.0 * zz - xx - yy),
            _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            _C3[4] * x * (4.0 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Colour of SH coefficients seen along `dirs` (not normalised; not offset).

    Args:
        degree: degree to evaluate; coefficients beyond it are ignored.
        dirs: [..., 3] view directions (any length; normalised here, zero stays finite).
        coeffs: [..., K, 3] with K >= (degree + 1) ** 2.

    Returns:
        [..., 3].
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"coeffs has {coeffs.shape[-2]} bases, degree {degree} needs {k}")
    bases = sh_bases(degree, F.normalize(dirs, dim=-1))
    return (bases[..., None] * coeffs[..., :k, :]).sum(dim=-2)
