"""One entry point for rasterization: gsplat's CUDA kernels when they can run, else the reference."""

from __future__ import annotations

import functools
from typing import Any, Dict, Literal, Optional, Tuple

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
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Render with classic (non-antialiased) 3DGS rasterization, unpacked, plain gradients.

    Same arguments and outputs on both backends; `info` always carries means2d (with grad after
    backward), radii, width, height and n_cameras for the densification strategies.
    """
    if resolve_backend(backend, means.device) == "cuda":
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
