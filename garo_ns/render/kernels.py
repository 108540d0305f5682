"""gsplat's CUDA kernels as both rasterization paths call them: the kernel handle, the tile size and classic
mode's low-pass, and the lean projection (`lean_front`) that the inference path (`backend.rasterize_lean`) and the
training path (`train_raster`) share. Here, below both, so neither imports the other for them.
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

from torch import Tensor

from garo_ns.render.view import camera_centres

TILE_SIZE = 16
EPS2D = 0.3  # gsplat's classic-mode low-pass: added to the 2D covariance's diagonal


# What the lean path computes before sorting: radii, means2d, depths, conics, view directions and
# the visibility mask (the last two only when colours come from SH).
Front = Tuple[Tensor, Tensor, Tensor, Tensor, Optional[Tensor], Optional[Tensor]]


def gsplat_kernels() -> Any:
    """gsplat's compiled CUDA kernels (imported on first use: importing may build them)."""
    from gsplat.cuda._backend import _C

    return _C


def lean_front(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    with_sh: bool,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Front:
    """Projection (gsplat's fused kernel, classic mode, unpacked) and, for SH colours, the view
    directions and visibility mask. Fixed-shape work on the current stream: a CUDA graph can
    capture it (the SH kernel itself cannot: it launches on the legacy default stream)."""
    radii, means2d, depths, conics, _ = gsplat_kernels().fully_fused_projection_fwd(
        means.contiguous(),
        None,
        quats.contiguous(),
        scales.contiguous(),
        viewmats.contiguous(),
        Ks.contiguous(),
        width,
        height,
        EPS2D,
        near_plane,
        far_plane,
        0.0,  # no radius clip
        False,  # no antialiasing compensation
        gsplat_kernels().CameraModelType.PINHOLE,
    )
    if not with_sh:
        return radii, means2d, depths, conics, None, None
    # Camera centre in closed form (-R^T t): the world-to-camera matrices are rigid.
    campos = camera_centres(viewmats)
    return radii, means2d, depths, conics, means[None] - campos[:, None], radii > 0
