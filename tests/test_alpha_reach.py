"""Tile lists from the box a splat's alpha can reach (garo_ns.ops.alpha_reach): every pixel the rasterizer draws
stays inside it, it is never larger than projection's square, and the reference rasterizer draws the same image
and gradients with it as without it, from fewer (tile, Gaussian) pairs. On CUDA the same radii feed gsplat's
isect_tiles: tests/test_rendering_cuda.py and tests/test_train_raster.py compare those paths with gsplat's."""

from __future__ import annotations

import math

import pytest
import torch
from test_rasterizer import camera, cloud

from garo_ns.ops.alpha_reach import ALPHA_MIN, reach_radii
from garo_ns.render import reference
from garo_ns.render.reference import covariance, project


def _projected(n=400, seed=0, faint=True):
    means, quats, scales, opac, colors = cloud(n, seed=seed, spread=1.2, scale=(0.005, 0.25))
    if faint:  # a band down to and across the skip threshold, and a saturated few
        opac[: n // 4] = torch.logspace(math.log10(0.2 / 255), math.log10(20 / 255), n // 4)
        opac[n // 4 : n // 4 + 10] = 1.0
    views, Ks, W, H = camera(width=80, height=64, n=2, seed=seed)
    radii, means2d, depths, conics = project(means, covariance(quats, scales), views, Ks, W, H)
    return radii, means2d, conics, opac, W, H


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_pixel_a_splat_can_draw_lies_in_its_reach_box(seed):
    radii, means2d, conics, opac, W, H = _projected(seed=seed)
    got = reach_radii(radii, conics, opac)
    assert got.dtype == radii.dtype and got.shape == radii.shape
    assert bool((got <= radii).all()) and bool((got >= 0).all())
    # The compositing test of gsplat and the reference at every pixel centre, in fp32.
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    dx = xs[None, None] - means2d[..., 0, None, None]
    dy = ys[None, None] - means2d[..., 1, None, None]
    a, b, c = (conics[..., i, None, None] for i in range(3))
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp_max(opac[None, :, None, None] * torch.exp(-sigma), reference.ALPHA_MAX)
    tx, ty = (xs // 16).long(), (ys // 16).long()  # each pixel's tile

    def in_tiles(r):
        lo, hi = reference.tile_bounds(means2d, r, 16, math.ceil(W / 16), math.ceil(H / 16))
        lo, hi = lo[..., None, None, :], hi[..., None, None, :]
        return (tx >= lo[..., 0]) & (tx < hi[..., 0]) & (ty >= lo[..., 1]) & (ty < hi[..., 1])

    # Drawn: in a tile of projection's square (a tile may reach past the square) and not skipped.
    drawn = (sigma >= 0) & (alpha >= ALPHA_MIN) & in_tiles(radii)
    lost = drawn & ~in_tiles(got)
    assert not bool(lost.any()), f"{int(lost.sum())} drawn pixels in no tile of the reach box"
    assert bool(drawn.any())
    # Too faint to reach any pixel: no tile at all.
    assert bool((got[:, opac < ALPHA_MIN] == 0).all())
    # The boxes are smaller: most of projection's 3-sigma square area is gone where the splats are faint.
    seen = radii > 0
    shrunk = (got[seen].double() ** 2).sum() / (radii[seen].double() ** 2).sum()
    assert shrunk < 0.8, float(shrunk)


def test_a_conic_it_cannot_trust_keeps_projections_square():
    radii = torch.tensor([[5, 7, 9, 4]], dtype=torch.int32)
    conics = torch.tensor([[[1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [float("nan"), 0.0, 1.0], [0.5, 0.0, 0.5]]])
    opac = torch.tensor([0.9, 0.9, 0.9, float("nan")])
    got = reach_radii(radii, conics, opac)
    # unit conic at opacity 0.9: sqrt(2 ln(229.5)) = 3.30 px -> 4; a singular or NaN conic keeps its square;
    # a NaN opacity reaches nothing.
    assert got.tolist() == [[4, 7, 9, 0]]
    # With the threshold at 0 nothing is skipped, so the square stays.
    assert torch.equal(reach_radii(radii[:, :2], conics[:, :2], opac[:2], alpha_min=0.0), radii[:, :2])


@pytest.mark.parametrize("alpha_min", [ALPHA_MIN, 0.0])
def test_the_reference_draws_the_same_from_fewer_pairs(monkeypatch, alpha_min):
    means, quats, scales, opac, colors = cloud(300, seed=4, spread=1.0, scale=(0.01, 0.2))
    opac[:100] = torch.logspace(math.log10(0.5 / 255), math.log10(30 / 255), 100)
    views, Ks, W, H = camera(width=72, height=56, n=2, seed=4)

    def render():
        leaves = [t.detach().clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
        img, alpha, info = reference.rasterize(*leaves, views, Ks, W, H, alpha_min=alpha_min)
        info["means2d"].retain_grad()
        (img.square().sum() + alpha.sum()).backward()
        return img.detach(), alpha.detach(), info, [t.grad for t in leaves] + [info["means2d"].grad]

    img, alpha, info, grads = render()
    monkeypatch.setattr(reference, "reach_radii", lambda radii, *args: radii)  # projection's squares
    img0, alpha0, info0, grads0 = render()
    torch.testing.assert_close(img, img0, rtol=0, atol=1e-6)
    torch.testing.assert_close(alpha, alpha0, rtol=0, atol=1e-6)
    for got, want in zip(grads, grads0):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)  # chunks split elsewhere: sums reordered
    assert torch.equal(info["radii"], info0["radii"])  # what the strategy counts as seen is projection's
    pairs, pairs0 = int(info["tiles_per_gauss"].sum()), int(info0["tiles_per_gauss"].sum())
    if alpha_min > 0:
        assert pairs < pairs0, (pairs, pairs0)
    else:
        assert pairs == pairs0


@pytest.mark.slow
def test_the_frame_profile_times_every_stage_and_counts_the_cut_pairs(garo_run):
    """The breakdown (garo_ns.bench.frame_profile): every stage timed, and fewer pairs than projection's squares."""
    from garo_ns.bench import frame_profile
    from garo_ns.tools.fps import prepare_views

    model = garo_run["trainer"].pipeline.model
    model.eval()
    cameras = garo_run["trainer"].pipeline.datamanager.eval_dataset.cameras[:2]
    out = frame_profile.profile_frame(model, cameras, warmup=0, repeats=1)
    assert all(out[f"ms_{s}"] > 0 for s in (*frame_profile.STAGES, "frame")), out
    with pytest.MonkeyPatch.context() as patch:  # projection's squares: every pair gsplat 1.4 would sort
        patch.setattr(frame_profile, "reach_radii", lambda radii, *args: radii)
        squares = frame_profile.tile_pairs(model, prepare_views(model, cameras))
    assert 0 < out["tile_pairs"] < squares
