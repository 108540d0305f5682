"""One entry point for rasterization: gsplat's CUDA kernels when they can run, else the reference."""

from __future__ import annotations

import contextlib
import functools
import math
import sys
from typing import Any, Callable, ContextManager, Dict, Literal, Optional, Tuple

import torch
from torch import Tensor

from garo_ns.render import reference
from garo_ns.render.kernels import TILE_SIZE, Front, gsplat_kernels, lean_front
from garo_ns.render.train_raster import rasterize_train_lean

Backend = Literal["auto", "cuda", "reference"]


# Why gsplat's CUDA rasterizer is not used on a machine that has CUDA (None: it is, or there is no CUDA).
_cuda_failure: Dict[str, Optional[str]] = {"reason": None}


@functools.lru_cache(maxsize=1)
def gsplat_cuda_available() -> bool:
    """True when a CUDA device exists and gsplat's CUDA extension loads (it may JIT-compile once). Where CUDA exists
    but the extension does not load, says so once on stderr: everything then renders through the reference, correct
    but some hundred times slower, and a timing would otherwise not show why."""
    if not torch.cuda.is_available():
        return False
    try:
        from gsplat.cuda._backend import _C  # noqa: F401  (importing builds or loads the extension)
    except Exception as err:  # any build or load failure means: use the reference
        reason = f"{type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}"
    else:
        if _C is not None:
            return True
        reason = "its CUDA extension did not build or load"
    _cuda_failure["reason"] = reason
    print(
        f"warning: gsplat's CUDA rasterizer cannot run ({reason}); rendering with the pure-torch reference",
        file=sys.stderr,
    )
    return False


def rasterizer_in_use(device: str) -> str:
    """Which rasterizer renders on `device` ("cuda" or "cpu"), in words, for result files: gsplat's CUDA kernels,
    the reference, or the reference because gsplat failed to load (with the reason)."""
    if device == "cuda" and gsplat_cuda_available():
        return "gsplat CUDA"
    if device == "cuda" and _cuda_failure["reason"]:
        return f"reference (gsplat failed: {_cuda_failure['reason']})"
    return "reference"


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


# Arguments as gsplat's `rasterization` on purpose (and so the reference's and the lean path's): one
# call site whatever the backend.
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
    render_mode: reference.RenderMode = "RGB",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backend: Backend = "auto",
    lean: bool = False,
    front: Optional[Front] = None,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Render with classic (non-antialiased) 3DGS rasterization, unpacked, plain gradients.

    Same arguments and outputs on both backends; `info` always carries means2d (with grad after
    backward), radii, width, height and n_cameras for the densification strategies. `lean`, on
    CUDA for RGB or RGB+ED with SH or RGB colours: without autograd, call the kernels directly
    (`rasterize_lean`, which takes `front` when the caller has it); with autograd and one camera,
    the training path of two autograd nodes (`train_raster.rasterize_train_lean`, same values and
    gradients as gsplat's; `front` unused). Ignored otherwise (the reference, other modes).
    """
    on_cuda = resolve_backend(backend, means.device) == "cuda"
    # The lean path composites SH colours or plain RGB (plus depth); other channel counts need the
    # wrapper's padding to a kernel-supported width, so they take gsplat's own path.
    lean_fits = sh_degree is not None or colors.shape[-1] == 3
    lean = on_cuda and lean and lean_fits and render_mode in ("RGB", "RGB+ED")
    if lean and torch.is_grad_enabled() and viewmats.shape[0] == 1:
        return rasterize_train_lean(
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
    if lean and not torch.is_grad_enabled():
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
            front=front,
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
    return reference.rasterize(
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


def _no_stage(name: str) -> ContextManager[Any]:
    return contextlib.nullcontext()


# Arguments as `rasterize` on purpose: the same call, gsplat's kernels without the wrapper.
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
    front: Optional[Front] = None,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Inference-only CUDA rasterization: gsplat's kernels (projection, SH colours, tile
    intersection, tile offsets, compositing) called directly with the arguments `rasterize`
    gives them, without the general wrapper's per-call Python (argument checks, autograd
    functions, packing, distributed and antialiasing branches, a 4x4 inverse for the camera
    centre). Same pixels as `rasterize`. `front`: `lean_front`'s outputs when the caller has
    them (e.g. from a CUDA graph replay); computed here otherwise. `stage(name)` wraps each step
    (projection, color, sorting, compositing): the frame profile times them there.
    """
    if sh_degree is None and colors.shape[-1] != 3:
        raise ValueError(f"the lean path composites RGB colours, got {colors.shape[-1]} channels")
    kernels = gsplat_kernels()
    n_cams = viewmats.shape[0]
    with stage("projection"):
        if front is None:
            front = lean_front(
                means, quats, scales, viewmats, Ks, width, height, sh_degree is not None, near_plane, far_plane
            )
        radii, means2d, depths, conics, dirs, visible, isect_radii = front
    with stage("color"):
        if sh_degree is None:
            rgb = colors.expand(n_cams, *colors.shape) if colors.dim() == 2 else colors
        else:
            rgb = kernels.compute_sh_fwd(sh_degree, dirs, colors.expand(n_cams, *colors.shape), visible)
            rgb = rgb.add_(0.5).clamp_min_(0.0)
        if with_depth:
            rgb = torch.cat([rgb, depths[..., None]], dim=-1)
            if backgrounds is not None:
                backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(n_cams, 1)], dim=-1)
    with stage("sorting"):
        tiles_w, tiles_h = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
        _, isect_ids, flatten_ids = kernels.isect_tiles(
            means2d, isect_radii, depths, None, None, n_cams, TILE_SIZE, tiles_w, tiles_h, True, True
        )
        offsets = kernels.isect_offset_encode(isect_ids, n_cams, tiles_w, tiles_h)
    with stage("compositing"):
        render, alpha, _ = kernels.rasterize_to_pixels_fwd(
            means2d,
            conics,
            rgb.contiguous(),
            opacities.expand(n_cams, -1).contiguous(),
            None if backgrounds is None else backgrounds.contiguous(),
            None,
            width,
            height,
            TILE_SIZE,
            offsets,
            flatten_ids,
        )
    if with_depth:  # expected depth, as gsplat's RGB+ED
        render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp_min(1e-10)], dim=-1)
    info = {"radii": radii, "means2d": means2d, "depths": depths, "width": width, "height": height, "n_cameras": n_cams}
    return render, alpha, info
