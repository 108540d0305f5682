"""One entry point for rasterization: gsplat's CUDA kernels when they can run, else the reference."""

from __future__ import annotations

import contextlib
import functools
import math
from typing import Any, Callable, ContextManager, Dict, Literal, Optional, Tuple

import torch
from torch import Tensor

from garo_ns import rasterizer

Backend = Literal["auto", "cuda", "reference"]


@functools.lru_cache(maxsize=1)
def gsplat_cuda_available() -> bool:
    """True when a CUDA device exists and gsplat's CUDA extension loads (it may JIT-compile once)."""
    if not torch.cuda.is_available():
        return False
    try:
        from gsplat.cuda._backend import _C  # noqa: F401  (importing builds or loads the extension)
    except Exception:  # any build or load failure means: use the reference
        return False
    return _C is not None


def resolve_backend(backend: Backend, device: torch.device) -> Literal["cuda", "reference"]:
    """Which rasterizer a call on `device` uses."""
    if backend == "reference":
        return "reference"
    on_cuda = torch.device(device).type == "cuda"
    if backend == "cuda":
        if not on_cuda or not gsplat_cuda_available():
            raise RuntimeError("backend 'cuda' was asked for, but gsplat's CUDA rasterizer cannot run here")
        return "cuda"
    return "cuda" if on_cuda and gsplat_cuda_available() else "reference"


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    sh_degree: Optional[int] = None,
    backgrounds: Optional[Tensor] = None,
    render_mode: rasterizer.RenderMode = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backend: Backend = "auto",
    lean: bool = False,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Render with classic (non-antialiased) 3DGS rasterization, unpacked, plain gradients.

    Same arguments and outputs on both backends; `info` always carries means2d (with grad after
    backward), radii, width, height and n_cameras for the densification strategies. `lean`: on
    CUDA without autograd, call the kernels directly (`rasterize_lean`); ignored otherwise.
    """
    on_cuda = resolve_backend(backend, means.device) == "cuda"
    if on_cuda and lean and not torch.is_grad_enabled() and render_mode in ("RGB", "RGB+ED"):
        return rasterize_lean(
            means,
            quats,
            scales,
            opacities,
            colors,
            viewmats,
            Ks,
            width,
            height,
            sh_degree,
            backgrounds,
            with_depth=render_mode == "RGB+ED",
            near_plane=near_plane,
            far_plane=far_plane,
        )
    if on_cuda:
        from gsplat import rasterization

        return rasterization(
            means=means,
            quats=quats,
            scales=scales,
            opacities=opacities,
            colors=colors,
            viewmats=viewmats,
            Ks=Ks,
            width=width,
            height=height,
            near_plane=near_plane,
            far_plane=far_plane,
            sh_degree=sh_degree,
            backgrounds=backgrounds,
            render_mode=render_mode,
            packed=False,
            absgrad=False,
            rasterize_mode="classic",
        )
    return rasterizer.rasterize(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode=render_mode,
    )


TILE_SIZE = 16


def _no_stage(name: str) -> ContextManager[Any]:
    return contextlib.nullcontext()


def rasterize_lean(
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
    stage: Callable[[str], ContextManager[Any]] = _no_stage,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Inference-only CUDA rasterization: gsplat's five kernels (projection, SH colours, tile
    intersection, tile offsets, compositing) with the arguments `rasterize` gives them, without
    the general wrapper's per-call Python (argument checks, packing, distributed and
    antialiasing branches, a 4x4 inverse for the camera centre). Same pixels as `rasterize`.
    `stage(name)` wraps each step (projection, color, sorting, compositing): the frame profile
    times them there.
    """
    from gsplat.cuda._wrapper import (
        fully_fused_projection,
        isect_offset_encode,
        isect_tiles,
        rasterize_to_pixels,
        spherical_harmonics,
    )

    n_cams = viewmats.shape[0]
    with stage("projection"):
        radii, means2d, depths, conics, _ = fully_fused_projection(
            means,
            None,
            quats,
            scales,
            viewmats,
            Ks,
            width,
            height,
            packed=False,
            near_plane=near_plane,
            far_plane=far_plane,
        )
    with stage("color"):
        if sh_degree is None:
            rgb = colors.expand(n_cams, *colors.shape) if colors.dim() == 2 else colors
        else:
            # Camera centre in closed form (-R^T t): the world-to-camera matrices are rigid.
            rot, trans = viewmats[:, :3, :3], viewmats[:, :3, 3:4]
            campos = -(rot.transpose(1, 2) @ trans).squeeze(-1)
            dirs = means[None] - campos[:, None]
            rgb = spherical_harmonics(sh_degree, dirs, colors.expand(n_cams, *colors.shape), masks=radii > 0)
            rgb = torch.clamp_min(rgb + 0.5, 0.0)
        if with_depth:
            rgb = torch.cat([rgb, depths[..., None]], dim=-1)
            if backgrounds is not None:
                backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cams, 1)], dim=-1)
    with stage("sorting"):
        tiles_w, tiles_h = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
        _, isect_ids, flatten_ids = isect_tiles(
            means2d, radii, depths, TILE_SIZE, tiles_w, tiles_h, packed=False, n_cameras=n_cams
        )
        offsets = isect_offset_encode(isect_ids, n_cams, tiles_w, tiles_h)
    with stage("compositing"):
        render, alpha = rasterize_to_pixels(
            means2d,
            conics,
            rgb,
            opacities.expand(n_cams, -1),
            width,
            height,
            TILE_SIZE,
            offsets,
            flatten_ids,
            backgrounds=backgrounds,
        )
    if with_depth:  # expected depth, as gsplat's RGB+ED
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
    info = {"radii": radii, "means2d": means2d, "depths": depths, "width": width, "height": height, "n_cameras": n_cams}
    return render, alpha, info
