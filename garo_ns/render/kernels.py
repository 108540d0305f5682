"""gsplat's CUDA kernels as both rasterization paths call them: the kernel handle, the tile size and classic
mode's low-pass, and the lean projection (`lean_front`) that the inference path (`backend.rasterize_lean`) and the
training path (`train_raster`) share. Here, below both, so neither imports the other for them.
"""

from __future__ import annotations

from typing import Any, Optional, Tuple

from torch import Tensor

from garo_ns.ops.alpha_reach import reach_radii
from garo_ns.render.view import camera_centres

TILE_SIZE = 16
EPS2D = 0.3  # gsplat's classic-mode low-pass: added to the 2D covariance's diagonal


# What the lean path computes before sorting: radii, means2d, depths, conics, view directions and
# the visibility mask (these two only when colours come from SH), and the radii its tile lists take.
Front = Tuple[Tensor, Tensor, Tensor, Tensor, Optional[Tensor], Optional[Tensor], Tensor]


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
    opacities: Optional[Tensor] = None,
) -> Front:
    """Projection (gsplat's fused kernel, classic mode, unpacked) and, for SH colours, the view
    directions and visibility mask. Fixed-shape work on the current stream: a CUDA graph can
    capture it (the SH kernel itself cannot: it launches on the legacy default stream).

    The tile lists' radii: with `opacities`, each splat's box cut to where its alpha reaches 1/255
    (garo_ns.ops.alpha_reach: the same pixels, fewer pairs); else projection's 3-sigma squares. Pass them
    where this runs inside a CUDA graph only: run eagerly, the cut's dozen small kernels cost a frame more
    launch time than its fewer pairs save (benchmarks/results/table1_*_H200.json, `profile` against
    `profile_projection_squares`)."""
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
    isect_radii = radii if opacities is None else reach_radii(radii, conics, opacities)
    if not with_sh:
        return radii, means2d, depths, conics, None, None, isect_radii
    # Camera centre in closed form (-R^T t): the world-to-camera matrices are rigid.
    campos = camera_centres(viewmats)
    return radii, means2d, depths, conics, means[None] - campos[:, None], radii > 0, isect_radii
