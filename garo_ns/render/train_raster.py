"""A lean training rasterization: gsplat's kernels behind two autograd nodes instead of its wrapper.

gsplat's `rasterization` builds a dozen autograd nodes per call (projection, a 4x4 inverse, view
directions, SH, the +0.5 and clamp, the opacity repeat, the depth concatenation, compositing, the
expected-depth division) and spends as much host time in its Python as the kernels take on the GPU
at training sizes. Here the same kernels run behind two `torch.autograd.Function`s:

- `_Front`: projection, and for SH colours the view directions and SH evaluation with gsplat's
  +0.5 / clamp_min(0). Its backward runs the clamp's mask, the SH backward (into the coefficients,
  and through the directions into the means) and the projection backward.
- `_Composite`: compositing, with the depth channel and the expected-depth division of RGB+ED
  folded in. Its backward is gsplat's compositing backward plus those two steps by hand.

The tile intersection runs between them, outside autograd. Values and gradients are gsplat's for
`packed=False, absgrad=False, rasterize_mode="classic"` and one camera, up to the camera centre
(closed form -R^T t here, a 4x4 inverse in gsplat: the view directions differ in the last bits).
"""

from __future__ import annotations

import math
from typing import Any, Dict, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.ops.alpha_reach import reach_radii
from garo_ns.render.kernels import EPS2D, TILE_SIZE, gsplat_kernels, lean_front

ALPHA_FLOOR = 1e-10  # gsplat's clamp on the alpha that divides the accumulated depth (RGB+ED)


class _Front(torch.autograd.Function):
    """Projection and SH colours: (means, quats, scales, SH coefficients or None) -> means2d [1, N, 2],
    conics [1, N, 3], rgb [1, N, 3] (None without SH), depths [1, N], radii [1, N] (int32, no gradient)."""

    @staticmethod
    def forward(
        ctx: Any,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        coeffs: Optional[Tensor],
        viewmats: Tensor,
        Ks: Tensor,
        width: int,
        height: int,
        sh_degree: Optional[int],
        near_plane: float,
        far_plane: float,
    ) -> Tuple[Tensor, Tensor, Optional[Tensor], Tensor, Tensor]:
        kernels = gsplat_kernels()
        # Unused outputs (depths in RGB mode, radii) get None in backward rather than zero tensors.
        ctx.set_materialize_grads(False)
        means, quats, scales = means.contiguous(), quats.contiguous(), scales.contiguous()
        viewmats, Ks = viewmats.contiguous(), Ks.contiguous()
        # The inference path's projection and view directions (camera centre in closed form, -R^T t).
        radii, means2d, depths, conics, dirs, visible, _ = lean_front(
            means, quats, scales, viewmats, Ks, width, height, coeffs is not None, near_plane, far_plane
        )
        ctx.mark_non_differentiable(radii)
        rgb = shifted = None
        if coeffs is not None:
            # [N, K, 3] coefficients are shared by the camera: a leading axis of one, no copy.
            ctx.shared = coeffs.dim() == 3
            coeffs = (coeffs[None] if ctx.shared else coeffs).contiguous()
            # The kernel leaves culled Gaussians' colours unwritten: they reach no tile, and their
            # gradient is zero, as in gsplat.
            shifted = kernels.compute_sh_fwd(sh_degree, dirs, coeffs, visible).add_(0.5)
            rgb = shifted.clamp_min(0.0)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii, conics, coeffs, dirs, visible, shifted)
        ctx.width, ctx.height, ctx.sh_degree = width, height, sh_degree
        return means2d, conics, rgb, depths, radii

    @staticmethod
    def backward(
        ctx: Any,
        v_means2d: Optional[Tensor],
        v_conics: Optional[Tensor],
        v_rgb: Optional[Tensor],
        v_depths: Optional[Tensor],
        v_radii: Optional[Tensor],
    ) -> Tuple[Optional[Tensor], ...]:
        kernels = gsplat_kernels()
        means, quats, scales, viewmats, Ks, radii, conics, coeffs, dirs, visible, shifted = ctx.saved_tensors
        # The projection kernel needs every incoming gradient; a missing one is zero.
        if v_means2d is None:
            v_means2d = conics.new_zeros((*conics.shape[:-1], 2))
        if v_conics is None:
            v_conics = torch.zeros_like(conics)
        if v_depths is None:
            v_depths = conics.new_zeros(conics.shape[:-1])
        v_means, _, v_quats, v_scales, _ = kernels.fully_fused_projection_bwd(
            means,
            None,
            quats,
            scales,
            viewmats,
            Ks,
            ctx.width,
            ctx.height,
            EPS2D,
            kernels.CameraModelType.PINHOLE,
            radii,
            conics,
            None,  # no compensations
            v_means2d.contiguous(),
            v_depths.contiguous(),
            v_conics.contiguous(),
            None,
            False,  # no viewmat gradient: the cameras are not optimised
        )
        v_coeffs = None
        if shifted is not None and v_rgb is not None:
            # clamp_min's gradient passes where its input (SH + 0.5) is >= 0, as torch's does.
            v_sh = torch.where(shifted >= 0.0, v_rgb, 0.0).contiguous()
            want_dirs = ctx.needs_input_grad[0]
            v_coeffs, v_dirs = kernels.compute_sh_bwd(
                coeffs.shape[-2], ctx.sh_degree, dirs, coeffs, visible, v_sh, want_dirs
            )
            if ctx.shared:
                v_coeffs = v_coeffs[0]
            if want_dirs:  # dirs = means - campos
                v_means = v_means + v_dirs[0]
        needs = ctx.needs_input_grad
        return (
            v_means if needs[0] else None,
            v_quats if needs[1] else None,
            v_scales if needs[2] else None,
            v_coeffs if needs[3] else None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
        )


class _Composite(torch.autograd.Function):
    """Compositing: (means2d, conics, colours [1, N, 3] or [N, 3], depths or None, opacities [N],
    backgrounds [1, 3] or None) -> render [1, H, W, 3 (+1 expected depth)], alpha [1, H, W, 1]."""

    @staticmethod
    def forward(
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        colors: Tensor,
        depths: Optional[Tensor],
        opacities: Tensor,
        backgrounds: Optional[Tensor],
        width: int,
        height: int,
        offsets: Tensor,
        flatten_ids: Tensor,
    ) -> Tuple[Tensor, Tensor]:
        ctx.shared = colors.dim() == 2
        feats = colors[None] if ctx.shared else colors
        if depths is not None:
            # RGB+ED composites the depth as a fourth channel, with a zero background.
            feats = torch.cat([feats, depths[..., None]], dim=-1)
            if backgrounds is not None:
                backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(backgrounds.shape[0], 1)], dim=-1)
        feats = feats.contiguous()
        opacities = opacities[None].contiguous()
        backgrounds = None if backgrounds is None else backgrounds.contiguous()
        raw, alpha, last_ids = gsplat_kernels().rasterize_to_pixels_fwd(
            means2d.contiguous(),
            conics.contiguous(),
            feats,
            opacities,
            backgrounds,
            None,  # no tile mask
            width,
            height,
            TILE_SIZE,
            offsets,
            flatten_ids,
        )
        render, depth_sum = raw, None
        if depths is not None:  # expected depth: the accumulated depth over the alpha
            depth_sum = raw[..., -1:]
            render = torch.cat([raw[..., :-1], depth_sum / alpha.clamp_min(ALPHA_FLOOR)], dim=-1)
        ctx.save_for_backward(
            means2d, conics, feats, opacities, backgrounds, offsets, flatten_ids, alpha, last_ids, depth_sum
        )
        ctx.width, ctx.height = width, height
        return render, alpha

    @staticmethod
    def backward(ctx: Any, v_render: Tensor, v_alpha: Tensor) -> Tuple[Optional[Tensor], ...]:
        means2d, conics, feats, opacities, backgrounds, offsets, flatten_ids, alpha, last_ids, depth_sum = (
            ctx.saved_tensors
        )
        v_raw = v_render
        if depth_sum is not None:
            # The division's gradients, as torch's autograd forms them for x / clamp_min(alpha): into
            # the accumulated depth, and into alpha where the clamp passes it.
            floor = alpha.clamp_min(ALPHA_FLOOR)
            v_expected = v_render[..., -1:]
            v_raw = torch.cat([v_render[..., :-1], v_expected / floor], dim=-1)
            v_alpha = v_alpha + torch.where(alpha >= ALPHA_FLOOR, -v_expected * ((depth_sum / floor) / floor), 0.0)
        _, v_means2d, v_conics, v_feats, v_opacities = gsplat_kernels().rasterize_to_pixels_bwd(
            means2d.contiguous(),
            conics.contiguous(),
            feats,
            opacities,
            backgrounds,
            None,
            ctx.width,
            ctx.height,
            TILE_SIZE,
            offsets,
            flatten_ids,
            alpha,
            last_ids,
            v_raw.contiguous(),
            v_alpha.contiguous(),
            False,  # no absgrad
        )
        v_backgrounds = None
        if ctx.needs_input_grad[5]:  # what shows through: the background times the transmittance
            v_backgrounds = (v_raw * (1.0 - alpha)).sum(dim=(1, 2))
            if depth_sum is not None:
                v_backgrounds = v_backgrounds[..., :-1]
        v_colors, v_depths = v_feats, None
        if depth_sum is not None:
            v_colors, v_depths = v_feats[..., :-1], v_feats[..., -1]
        if ctx.shared:
            v_colors = v_colors[0]
        return v_means2d, v_conics, v_colors, v_depths, v_opacities[0], v_backgrounds, None, None, None, None


# Arguments as `backend.rasterize_lean` on purpose: the same call, with gradients.
def rasterize_train_lean(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: Optional[int],
    backgrounds: Optional[Tensor] = None,
    with_depth: bool = False,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Differentiable CUDA rasterization of one camera with gsplat's kernels behind two autograd
    nodes: render [1, H, W, 3 (+1 expected depth with `with_depth`)], alpha [1, H, W, 1] and an
    `info` with gsplat's keys for unpacked rendering, less its per-view opacities. `colors`: SH
    coefficients [N, K, 3] with `sh_degree`, else RGB [N, 3]. `info["means2d"]` is a non-leaf
    that compositing consumes: `retain_grad()` on it before backward gives gsplat's 2D gradient.
    """
    if viewmats.shape[0] != 1:
        raise ValueError(f"the lean training path renders one camera, got {viewmats.shape[0]}")
    if sh_degree is None and colors.shape[-1] != 3:
        raise ValueError(f"the lean path composites RGB colours, got {colors.shape[-1]} channels")
    kernels = gsplat_kernels()
    coeffs = None if sh_degree is None else colors
    means2d, conics, rgb, depths, radii = _Front.apply(
        means, quats, scales, coeffs, viewmats, Ks, width, height, sh_degree, near_plane, far_plane
    )
    # Tile lists: integer bookkeeping that autograd does not see.
    tiles_w, tiles_h = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    # From the box each splat's alpha can reach (garo_ns.ops.alpha_reach): the same pixels and gradients, fewer
    # pairs. `info["radii"]` stays projection's: the strategy counts a splat seen by its 3-sigma square.
    isect_radii = reach_radii(radii, conics.detach(), opacities.detach())
    tiles_per_gauss, isect_ids, flatten_ids = kernels.isect_tiles(
        means2d, isect_radii, depths, None, None, 1, TILE_SIZE, tiles_w, tiles_h, True, True
    )
    offsets = kernels.isect_offset_encode(isect_ids, 1, tiles_w, tiles_h)
    render, alpha = _Composite.apply(
        means2d,
        conics,
        colors if rgb is None else rgb,
        depths if with_depth else None,
        opacities,
        backgrounds,
        width,
        height,
        offsets,
        flatten_ids,
    )
    info = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "tiles_per_gauss": tiles_per_gauss,
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids,
        "isect_offsets": offsets,
        "tile_width": tiles_w,
        "tile_height": tiles_h,
        "tile_size": TILE_SIZE,
        "width": width,
        "height": height,
        "n_cameras": 1,
    }
    return render, alpha, info
