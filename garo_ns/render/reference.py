"""Pure-torch reference rasterizer for 3D Gaussians.

It follows gsplat 1.4.0's conventions closely enough that the densification strategies
(gsplat's and ours) run unchanged on a machine without CUDA:

* projection: quaternion + scale -> covariance, pinhole Jacobian with the view-frustum clamp
  at 1.3x the field of view, near/far culling, a 0.3 px low-pass dilation, 3-sigma radius
  (from the larger eigenvalue), and culling of Gaussians whose box misses the image;
* tiles of 16 px; a Gaussian touches the tiles that the box of its 1/255 alpha ellipse (within its 3-sigma
  square) overlaps, as the CUDA paths sort them (garo_ns.ops.alpha_reach);
* front-to-back compositing per pixel (pixel centres at +0.5), alpha = min(0.999,
  opacity * exp(-sigma)), Gaussians with alpha < 1/255 skipped, and a pixel stops before the
  Gaussian that would bring its transmittance to 1e-4 or below.

Compositing refines each tile's list to blocks of 4x4 px, keeping a Gaussian in a block only where
its alpha can reach 1/255 at some pixel of the block (the pairs dropped are ones the per-pixel loop
skips anyway), then walks each block's list a chunk of depth ranks at a time, carrying the
transmittance, and closes a block once all its pixels have stopped. Memory stays bounded (batches of
blocks, never pixels x Gaussians) and autograd gives exact gradients of the same function, including
`means2d.grad`.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Literal, Optional, Tuple

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from garo_ns.ops.alpha_reach import ALPHA_MIN, reach_half_widths, reach_radii
from garo_ns.ops.quaternions import quat_to_rotmat
from garo_ns.render.sh import eval_sh

RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]

ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4


def covariance(quats: Tensor, scales: Tensor) -> Tensor:
    """3D covariances R S S^T R^T, [N, 3, 3]."""
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def project(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project Gaussians into C pinhole cameras.

    Returns radii [C, N] (int32, 0 = culled), means2d [C, N, 2], depths [C, N], conics [C, N, 3]
    (upper triangle of the inverse 2D covariance). Culled entries hold finite placeholders.
    """
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    covars_c = torch.einsum("cij,njk,clk->cnil", rot, covars, rot)
    tx, ty, tz = means_c.unbind(-1)
    in_depth = (tz > near_plane) & (tz < far_plane)
    # Placeholders keep culled Gaussians finite in value and gradient.
    tz = torch.where(in_depth, tz, torch.ones_like(tz))

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    # The Jacobian is evaluated at a point clamped to 1.3x the frustum (the mean itself is not).
    txc = tz * torch.clamp(tx / tz, min=-lim_x_neg, max=lim_x_pos)
    tyc = tz * torch.clamp(ty / tz, min=-lim_y_neg, max=lim_y_pos)
    zeros = torch.zeros_like(tz)
    jac = torch.stack([fx / tz, zeros, -fx * txc / (tz * tz), zeros, fy / tz, -fy * tyc / (tz * tz)], dim=-1).reshape(
        tz.shape + (2, 3)
    )
    cov2d = jac @ covars_c @ jac.transpose(-1, -2)
    means2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=-1)

    a = cov2d[..., 0, 0] + eps2d
    b = 0.5 * (cov2d[..., 0, 1] + cov2d[..., 1, 0])
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = in_depth & (det > 0) & torch.isfinite(det) & torch.isfinite(means2d).all(-1)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    conics = torch.where(valid[..., None], conics, torch.ones_like(conics))
    means2d = torch.where(valid[..., None], means2d, torch.zeros_like(means2d))

    with torch.no_grad():
        mid = 0.5 * (a + c)
        v1 = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(torch.clamp(v1, min=0.0)))
        radius = torch.where(valid & torch.isfinite(radius), radius, torch.zeros_like(radius))
        radius = torch.where(radius <= radius_clip, torch.zeros_like(radius), radius)
        mx, my = means2d[..., 0], means2d[..., 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radius = torch.where(inside, radius, torch.zeros_like(radius))
        # A radius beyond any image would overflow int32; the tile box is clamped to the image anyway.
        radius = radius.clamp(max=float(4 * max(width, height) + 64))
    depths = torch.where(valid, means_c[..., 2], torch.zeros_like(tz))
    return radius.to(torch.int32), means2d, depths, conics


@torch.no_grad()
def tile_bounds(
    means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> Tuple[Tensor, Tensor]:
    """Tile boxes [min, max) of each projected Gaussian, [C, N, 2] each (x, y)."""
    r = radii.to(means2d.dtype)[..., None]
    lo = torch.floor((means2d - r) / tile_size)
    hi = torch.ceil((means2d + r) / tile_size)
    limit = torch.tensor([tile_width, tile_height], device=means2d.device, dtype=means2d.dtype)
    lo = torch.minimum(lo.clamp(min=0), limit).long()
    hi = torch.minimum(hi.clamp(min=0), limit).long()
    hi = torch.where((radii > 0)[..., None], hi, lo)
    return lo, hi


@torch.no_grad()
def intersect_tiles(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> Tuple[Tensor, Tensor, Tensor]:
    """All (tile, Gaussian) overlaps, sorted by tile then depth.

    Returns:
        tiles_per_gauss [C, N], tile_ids [M] (camera-major global tile index), flat_ids [M]
        (index c * N + n into the flattened projected arrays).
    """
    C, N = radii.shape
    lo, hi = tile_bounds(means2d, radii, tile_size, tile_width, tile_height)
    span = hi - lo
    counts = (span[..., 0] * span[..., 1]).flatten()
    src = torch.nonzero(counts > 0).squeeze(1)
    per = counts[src]
    total = int(per.sum())
    flat_ids = torch.repeat_interleave(src, per)
    first = torch.cumsum(per, 0) - per
    local = torch.arange(total, device=radii.device) - torch.repeat_interleave(first, per)
    w = span.reshape(-1, 2)[flat_ids, 0]
    tx = lo.reshape(-1, 2)[flat_ids, 0] + local % w
    ty = lo.reshape(-1, 2)[flat_ids, 1] + local // w
    cam = flat_ids // N
    tile_ids = cam * (tile_width * tile_height) + ty * tile_width + tx
    # Sort by depth, then stably by tile: each tile's list is front to back.
    order = torch.argsort(depths.flatten()[flat_ids], stable=True)
    tile_ids, flat_ids = tile_ids[order], flat_ids[order]
    order = torch.argsort(tile_ids, stable=True)
    return counts.reshape(C, N).int(), tile_ids[order], flat_ids[order]


@torch.no_grad()
def block_lists(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    tile_ids: Tensor,
    flat_ids: Tensor,
    tile_width: int,
    tile_height: int,
    tile_size: int,
    block_size: int,
    alpha_min: float = ALPHA_MIN,
) -> Tuple[Tensor, Tensor]:
    """Refine (tile, Gaussian) lists into (block, Gaussian) lists over blocks of `block_size` px.

    A pair is kept when the block lies in one of the Gaussian's tiles and some pixel centre of the block
    can see alpha >= `alpha_min` from it: alpha >= alpha_min needs sigma <= log(opacity / alpha_min), an
    ellipse whose bounding box is tested (with a margin against rounding). Every dropped pair is one
    gsplat's per-pixel loop skips anyway, so values and gradients are unchanged; only the work shrinks
    (a 3-sigma tile box of 16 px holds many pixels that a faint or small Gaussian never reaches).

    Args: means2d [CN, 2], conics [CN, 3], opacities [CN] (flattened); the tile lists from `intersect_tiles`.

    Returns:
        block_ids [K] (camera-major global block index, blocks of a tile row-major inside the tile
        grid's block grid) and gauss_ids [K] (into the flattened arrays), sorted by block then depth.
    """
    per_side = tile_size // block_size
    if per_side * block_size != tile_size:
        raise ValueError(f"tile_size {tile_size} must be a multiple of block_size {block_size}")
    blocks_w, blocks_h = tile_width * per_side, tile_height * per_side
    half_x, half_y = reach_half_widths(conics[flat_ids], opacities[flat_ids], alpha_min)
    mx, my = means2d[flat_ids].unbind(-1)
    # Blocks whose pixel centres (index + 0.5) may fall in the box, inclusive (NaN: none).
    lo_x, hi_x = torch.floor((mx - half_x - 0.5) / block_size), torch.floor((mx + half_x - 0.5) / block_size)
    lo_y, hi_y = torch.floor((my - half_y - 0.5) / block_size), torch.floor((my + half_y - 0.5) / block_size)

    tiles_per_cam = tile_width * tile_height
    cam, in_cam = tile_ids // tiles_per_cam, tile_ids % tiles_per_cam
    local = torch.arange(per_side, device=tile_ids.device)
    bx = ((in_cam % tile_width) * per_side)[:, None, None] + local[None, None, :]  # [M, 1, S]
    by = ((in_cam // tile_width) * per_side)[:, None, None] + local[None, :, None]  # [M, S, 1]
    hit = (bx >= lo_x[:, None, None]) & (bx <= hi_x[:, None, None])
    hit = hit & (by >= lo_y[:, None, None]) & (by <= hi_y[:, None, None])  # [M, S, S]
    block_ids = (cam[:, None, None] * (blocks_w * blocks_h) + by * blocks_w + bx).expand_as(hit)
    keep = hit.reshape(-1)
    block_ids = block_ids.reshape(-1)[keep]
    gauss_ids = flat_ids[:, None].expand(-1, per_side * per_side).reshape(-1)[keep]
    # Each tile's list is front to back and its blocks lie inside it: a stable sort keeps the depth order.
    order = torch.argsort(block_ids, stable=True)
    return block_ids[order], gauss_ids[order]


def _composite_blocks(
    splat: Tensor,
    feat: Tensor,
    pixels: Tensor,
    counts: Tensor,
    starts: Tensor,
    gauss_ids: Tensor,
    chunk: int,
    alpha_min: float,
) -> Tuple[Tensor, Tensor]:
    """Composite a batch of blocks front to back: accumulated features [B, P, D], transmittance [B, P].

    splat [6, CN]: per Gaussian x, y, -a/2, -b, -c/2 (a, b, c: the conic) and opacity, one row each so
    that a gather gives contiguous [A, B] columns; feat [CN, D]; pixels [B, P, 2]: pixel centres of each
    block; counts/starts [B]: each block's run in gauss_ids. Depth ranks are taken `chunk` at a time for
    the blocks still open, carrying the log-transmittance; a block closes when its list ends or all its
    pixels have stopped (gsplat's early termination).

    Masks are float factors rather than `torch.where`, and log(1 - alpha) stands for log1p: on CPU both
    are several times cheaper (alpha <= 0.999 keeps them finite and exact enough).
    """
    dev, dt = splat.device, splat.dtype
    n_blocks, P = pixels.shape[:2]
    D = feat.shape[-1]
    open_ids = torch.nonzero(counts > 0).squeeze(1)
    cnt, st = counts[open_ids], starts[open_ids]
    pix_x, pix_y = pixels[open_ids, :, 0, None], pixels[open_ids, :, 1, None]  # [A, P, 1]
    log_trans = torch.zeros(open_ids.numel(), P, device=dev, dtype=dt)
    running = torch.ones(open_ids.numel(), P, device=dev, dtype=dt)  # 0 once a pixel has stopped
    acc = torch.zeros(open_ids.numel(), P, D, device=dev, dtype=dt)
    closed_ids, closed_acc, closed_trans = [], [], []
    log_t_min = math.log(TRANSMITTANCE_MIN)
    s = 0
    while open_ids.numel():
        j = torch.arange(s, s + min(chunk, int(cnt.max()) - s), device=dev)
        present = j[None, :] < cnt[:, None]  # [A, B]
        pos = torch.where(present, st[:, None] + j[None, :], torch.zeros_like(present, dtype=torch.long))
        gid = gauss_ids[pos]  # [A, B]
        gx, gy, ga, gb, gc, opa = splat[:, gid][:, :, None, :]  # each [A, 1, B]
        dx, dy = pix_x - gx, pix_y - gy  # [A, P, B]
        neg_sigma = dx * (ga * dx + gb * dy) + gc * dy * dy
        alpha = torch.clamp_max(opa * torch.exp(neg_sigma), ALPHA_MAX)
        with torch.no_grad():
            keep = ((neg_sigma <= 0) & (alpha >= alpha_min)).to(dt) * present[:, None, :].to(dt)
        alpha = alpha * keep
        log_t = torch.log(1.0 - alpha)
        csum = torch.cumsum(log_t, dim=-1)
        with torch.no_grad():
            # A pixel stops before the first Gaussian that would take its transmittance to 1e-4; the
            # transmittance only falls, so every later Gaussian of the chunk is past the stop too.
            floor = (log_t_min - log_trans)[..., None]
            used = (csum > floor).to(dt) * running[..., None]
            running = running * (csum[..., -1:] > floor).squeeze(-1).to(dt)
        weight = alpha * used * torch.exp(log_trans[..., None] + (csum - log_t))
        acc = acc + torch.bmm(weight, feat[gid])
        log_trans = log_trans + (log_t * used).sum(-1)
        s += j.numel()
        stay = (cnt > s) & (running.amax(-1) > 0)
        if not bool(stay.all()):
            closed_ids.append(open_ids[~stay])
            closed_acc.append(acc[~stay])
            closed_trans.append(torch.exp(log_trans[~stay]))
            open_ids, cnt, st, pix_x, pix_y = open_ids[stay], cnt[stay], st[stay], pix_x[stay], pix_y[stay]
            log_trans, running, acc = log_trans[stay], running[stay], acc[stay]
    out_acc = torch.zeros(n_blocks, P, D, device=dev, dtype=dt)
    out_trans = torch.ones(n_blocks, P, device=dev, dtype=dt)
    if closed_ids:
        ids = torch.cat(closed_ids)
        out_acc = out_acc.index_copy(0, ids, torch.cat(closed_acc))
        out_trans = out_trans.index_copy(0, ids, torch.cat(closed_trans))
    return out_acc, out_trans


BLOCK_SIZE = 4  # compositing blocks (px per side): pixels that share a Gaussian list


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    features: Tensor,
    tile_ids: Tensor,
    flat_ids: Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
    chunk: int = 32,
    max_elements: int = 1 << 22,
    alpha_min: float = ALPHA_MIN,
    block_size: int = BLOCK_SIZE,
) -> Tuple[Tensor, Tensor]:
    """Alpha-composite depth-sorted Gaussians front to back at every pixel, as gsplat does per tile.

    The tile lists are refined to blocks of `block_size` px (`block_lists`: only pairs that can reach
    alpha_min stay, so the result is the same), and each block is composited `chunk` Gaussians at a time
    until its list ends or all its pixels have stopped.

    Args:
        means2d [C, N, 2], conics [C, N, 3], opacities [C, N], features [C, N, D]: projected
            Gaussians; tile_ids/flat_ids from `intersect_tiles` with `tile_size`.
        chunk: depth ranks per block handled at once; max_elements: pixel x Gaussian pairs per batch
            of blocks (with several batches and autograd, each batch is recomputed in backward).
        alpha_min: Gaussians whose alpha at a pixel is below this are skipped there (gsplat: 1/255).
        block_size: a divisor of tile_size (the whole tile when it is smaller).

    Returns:
        accumulated features [C, H, W, D] (no background) and alphas [C, H, W, 1].
    """
    C, N = opacities.shape
    D = features.shape[-1]
    dev, dt = means2d.device, means2d.dtype
    block = min(block_size, tile_size)
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    bw, bh = tw * (tile_size // block), th * (tile_size // block)
    n_blocks = C * bw * bh
    P = block * block
    m2d, con = means2d.reshape(C * N, 2), conics.reshape(C * N, 3)
    opa, feat = opacities.reshape(C * N), features.reshape(C * N, D)
    block_ids, gauss_ids = block_lists(
        m2d.detach(), con.detach(), opa.detach(), tile_ids, flat_ids, tw, th, tile_size, block, alpha_min
    )
    # What a pixel needs of each Gaussian, a row per quantity: one gather per chunk (and one scatter back).
    neg_half_conic = con * torch.tensor([-0.5, -1.0, -0.5], device=dev, dtype=dt)
    splat = torch.cat([m2d, neg_half_conic, opa[:, None]], dim=-1).t()

    counts = torch.bincount(block_ids, minlength=n_blocks)
    starts = torch.cumsum(counts, 0) - counts
    ids = torch.arange(n_blocks, device=dev)
    in_cam = ids % (bw * bh)
    origin = torch.stack([in_cam % bw, in_cam // bw], dim=-1).to(dt) * block
    local = torch.arange(block, device=dev)
    offsets = torch.stack([local.repeat(block), local.repeat_interleave(block)], dim=-1).to(dt) + 0.5
    pixels = origin[:, None, :] + offsets[None]  # [blocks, P, 2] pixel centres (x, y)

    # Batches of whole blocks holding about max_elements pixel x Gaussian pairs each.
    batch_of = torch.div(torch.cumsum(counts, 0) - counts, max(1, max_elements // P), rounding_mode="floor")
    edges = torch.cat([torch.zeros(1, device=dev, dtype=torch.long), torch.cumsum(torch.bincount(batch_of), 0)])
    edges = [int(e) for e in torch.unique(edges)]
    batches = list(zip(edges[:-1], edges[1:]))
    # With several batches, recompute each batch in backward instead of keeping its
    # intermediates (pixels x chunk tensors): memory stays at one batch, e.g. for 800x800.
    remat = len(batches) > 1 and torch.is_grad_enabled() and (splat.requires_grad or feat.requires_grad)
    out_feat, out_trans = [], []
    for b0, b1 in batches:
        args = (pixels[b0:b1], counts[b0:b1], starts[b0:b1], gauss_ids, chunk, alpha_min)
        if remat:
            acc, trans = checkpoint(_composite_blocks, splat, feat, *args, use_reentrant=False)
        else:
            acc, trans = _composite_blocks(splat, feat, *args)
        out_feat.append(acc)
        out_trans.append(trans)

    def to_image(x: Tensor) -> Tensor:
        x = x.reshape(C, bh, bw, block, block, -1)
        x = x.permute(0, 1, 3, 2, 4, 5).reshape(C, bh * block, bw * block, -1)
        return x[:, :height, :width]

    alphas = 1.0 - torch.cat(out_trans, dim=0)
    return to_image(torch.cat(out_feat, dim=0)), to_image(alphas[..., None])


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree) -> None:
    if not isinstance(width, int) or not isinstance(height, int) or width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive ints, got width={width!r}, height={height!r}")
    if means.ndim != 2 or means.shape[-1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    n = means.shape[0]
    for name, t, shape in (("quats", quats, (n, 4)), ("scales", scales, (n, 3)), ("opacities", opacities, (n,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"{name} must be {list(shape)} to match means, got {list(t.shape)}")
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4], got {list(viewmats.shape)}")
    c = viewmats.shape[0]
    if tuple(Ks.shape) != (c, 3, 3):
        raise ValueError(f"Ks must be [{c}, 3, 3] to match viewmats, got {list(Ks.shape)}")
    if not torch.isfinite(viewmats).all():
        raise ValueError("viewmats contains non-finite values")
    if not torch.isfinite(Ks).all():
        raise ValueError("Ks contains non-finite values")
    if sh_degree is None:
        ok = (colors.ndim == 2 and colors.shape[0] == n) or (colors.ndim == 3 and colors.shape[:2] == (c, n))
    else:
        ok = (colors.ndim == 3 and colors.shape[0] == n and colors.shape[2] == 3) or (
            colors.ndim == 4 and colors.shape[:2] == (c, n) and colors.shape[3] == 3
        )
        ok = ok and colors.shape[-2] >= (sh_degree + 1) ** 2
    if not ok:
        raise ValueError(
            f"colors has shape {list(colors.shape)}, which does not fit N={n}, C={c}, sh_degree={sh_degree}"
        )


# Arguments as gsplat's `rasterization` on purpose: the reference stands in for it.
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
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: RenderMode = "RGB",
    chunk: int = 32,
    alpha_min: float = ALPHA_MIN,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Render Gaussians into C cameras; the call mirrors `gsplat.rasterization(packed=False)`.

    Returns render [C, H, W, D], alphas [C, H, W, 1] and an `info` dict with the keys gsplat's
    strategies read: means2d [C, N, 2] (non-leaf; `.grad` after backward), radii [C, N],
    depths, conics, opacities, gaussian_ids/camera_ids (None: not packed), width, height,
    n_cameras, tile_size, tile_width, tile_height. `alpha_min` is gsplat's skip threshold (1/255);
    other values serve diagnosis (the parity benchmark's threshold band).
    """
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree)
    if render_mode not in ("RGB", "D", "ED", "RGB+D", "RGB+ED"):
        raise ValueError(f"render_mode must be one of RGB, D, ED, RGB+D, RGB+ED, got {render_mode!r}")
    C, N = viewmats.shape[0], means.shape[0]
    dt = means.dtype

    # Non-finite Gaussians are rendered as nothing, and placeholders keep their gradients finite.
    finite = (
        torch.isfinite(means).all(-1)
        & torch.isfinite(quats).all(-1)
        & torch.isfinite(scales).all(-1)
        & torch.isfinite(opacities)
    )
    covars = covariance(
        torch.where(finite[:, None], quats, torch.ones_like(quats)),
        torch.where(finite[:, None], scales, torch.ones_like(scales)),
    )
    finite = finite & torch.isfinite(covars).flatten(1).all(-1)
    covars = torch.where(finite[:, None, None], covars, torch.zeros_like(covars))
    safe_means = torch.where(finite[:, None], means, torch.zeros_like(means))
    radii, means2d, depths, conics = project(
        safe_means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane, radius_clip
    )
    radii = torch.where(finite[None, :], radii, torch.zeros_like(radii))
    opac = torch.where(finite, opacities, torch.zeros_like(opacities))[None, :].expand(C, N)

    if sh_degree is None:
        feats = colors if colors.ndim == 3 else colors[None].expand(C, N, colors.shape[-1])
    else:
        campos = torch.linalg.inv(viewmats)[:, :3, 3]
        dirs = safe_means[None, :, :] - campos[:, None, :]
        coeffs = colors if colors.ndim == 4 else colors[None].expand(C, *colors.shape)
        feats = torch.clamp_min(eval_sh(sh_degree, dirs, coeffs) + 0.5, 0.0)
    feats = torch.where(finite[None, :, None], feats, torch.zeros_like(feats))
    bg = backgrounds
    if render_mode in ("RGB+D", "RGB+ED"):
        feats = torch.cat([feats, depths[..., None]], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, torch.zeros_like(bg[:, :1])], dim=-1)
    elif render_mode in ("D", "ED"):
        feats = depths[..., None]
        bg = None if bg is None else torch.zeros_like(bg[:, :1])

    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    # Tiles from the box each splat's alpha can reach (as the CUDA paths sort): the same pixels, fewer pairs.
    isect_radii = reach_radii(radii, conics.detach(), opac.detach(), alpha_min)
    tiles_per_gauss, tile_ids, flat_ids = intersect_tiles(means2d, isect_radii, depths, tile_size, tw, th)
    render, alphas = composite(
        means2d, conics, opac, feats.to(dt), tile_ids, flat_ids, width, height, tile_size, chunk, alpha_min=alpha_min
    )
    if not render.requires_grad and (means2d.requires_grad or feats.requires_grad or opac.requires_grad):
        # Nothing visible: keep the outputs on the autograd graph (zero gradients), as gsplat does,
        # so a training step on an empty view does not fail. Inputs here are already finite.
        tie = 0.0 * (means2d.sum() + feats.sum() + opac.sum() + conics.sum())
        render, alphas = render + tie, alphas + tie
    if bg is not None:
        render = render + bg[:, None, None, :] * (1.0 - alphas)
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp(min=1e-10)], dim=-1)

    info: Dict[str, Any] = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": opac,
        "tiles_per_gauss": tiles_per_gauss,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "tile_width": tw,
        "tile_height": th,
        "n_cameras": C,
    }
    return render, alphas, info
