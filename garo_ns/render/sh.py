"""Real spherical harmonics up to degree 3, in the sign convention of 3DGS and gsplat."""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from garo_ns.ops.triton_mode import per_mode, runs_on

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


def rendered_colors(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """The colours a rasterizer composites: SH `coeffs` [N, K, 3] seen along `dirs` [C, N, 3], plus 0.5, clamped at
    0 (gsplat's `compute_sh_fwd` and offset) -> [C, N, 3]. One Triton kernel on a CUDA device (a CUDA graph can hold
    it, where gsplat's kernel launches on the legacy stream), or with Triton's interpreter; torch elsewhere."""
    if not runs_on(dirs.device):
        return (eval_sh(degree, dirs, coeffs.expand(dirs.shape[0], *coeffs.shape)) + 0.5).clamp_min(0.0)
    if coeffs.shape[-2] < num_sh_bases(degree):
        raise ValueError(f"coeffs has {coeffs.shape[-2]} bases, degree {degree} needs {num_sh_bases(degree)}")
    c, n = dirs.shape[:2]
    out = torch.empty(c, n, 3, dtype=torch.float32, device=dirs.device)
    _kernel()[(-(-n // _BLOCK), c)](  # the splats on axis x (y stops at 65,535 blocks)
        dirs.float().contiguous(), coeffs.float().contiguous(), out, n, coeffs.shape[-2], DEGREE=degree, BLOCK=_BLOCK
    )
    return out


_BLOCK = 256


@per_mode
def _kernel() -> Any:
    """The Triton kernel, made once per interpreter setting (garo_ns.ops.triton_mode)."""
    import triton
    import triton.language as tl

    @triton.jit
    def colors(dirs_ptr, coeffs_ptr, out_ptr, n, k, DEGREE: tl.constexpr, BLOCK: tl.constexpr):
        cam = tl.program_id(1).to(tl.int64)
        g = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        m = g < n
        d = dirs_ptr + (cam * n + g) * 3
        x, y, z = tl.load(d, mask=m, other=1.0), tl.load(d + 1, mask=m, other=0.0), tl.load(d + 2, mask=m, other=0.0)
        inv = 1.0 / tl.maximum(tl.sqrt(x * x + y * y + z * z), 1e-12)
        x, y, z = x * inv, y * inv, z * inv
        base = coeffs_ptr + g * k * 3
        for ch in tl.static_range(3):
            acc = 0.28209479177387814 * tl.load(base + ch, mask=m, other=0.0)
            if DEGREE >= 1:
                acc += -0.4886025119029199 * y * tl.load(base + 3 + ch, mask=m, other=0.0)
                acc += 0.4886025119029199 * z * tl.load(base + 6 + ch, mask=m, other=0.0)
                acc += -0.4886025119029199 * x * tl.load(base + 9 + ch, mask=m, other=0.0)
            if DEGREE >= 2:
                xx, yy, zz = x * x, y * y, z * z
                acc += 1.0925484305920792 * x * y * tl.load(base + 12 + ch, mask=m, other=0.0)
                acc += -1.0925484305920792 * y * z * tl.load(base + 15 + ch, mask=m, other=0.0)
                acc += 0.31539156525252005 * (2.0 * zz - xx - yy) * tl.load(base + 18 + ch, mask=m, other=0.0)
                acc += -1.0925484305920792 * x * z * tl.load(base + 21 + ch, mask=m, other=0.0)
                acc += 0.5462742152960396 * (xx - yy) * tl.load(base + 24 + ch, mask=m, other=0.0)
            if DEGREE >= 3:
                acc += -0.5900435899266435 * y * (3.0 * xx - yy) * tl.load(base + 27 + ch, mask=m, other=0.0)
                acc += 2.890611442640554 * x * y * z * tl.load(base + 30 + ch, mask=m, other=0.0)
                acc += -0.4570457994644658 * y * (4.0 * zz - xx - yy) * tl.load(base + 33 + ch, mask=m, other=0.0)
                acc += (
                    0.3731763325901154
                    * z
                    * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                    * tl.load(base + 36 + ch, mask=m, other=0.0)
                )
                acc += -0.4570457994644658 * x * (4.0 * zz - xx - yy) * tl.load(base + 39 + ch, mask=m, other=0.0)
                acc += 1.445305721320277 * z * (xx - yy) * tl.load(base + 42 + ch, mask=m, other=0.0)
                acc += -0.5900435899266435 * x * (xx - 3.0 * yy) * tl.load(base + 45 + ch, mask=m, other=0.0)
            tl.store(out_ptr + (cam * n + g) * 3 + ch, tl.maximum(acc + 0.5, 0.0), mask=m)

    return colors
