"""Fixed-length tile lists (garo_ns.render.tile_lists) against the reference rasterizer's lists and pixels.

The lists feed gsplat's compositing kernel on a GPU; here `composite` walks them as that kernel does (a tile's pairs
from its offset to the next tile's, the last tile's to the end of the buffer; alpha capped at 0.999, skipped under
1/255; a pixel stops before the splat that brings its transmittance to 1e-4), so the CPU checks the lists a GPU
frame composites.
"""

from __future__ import annotations

import math

import pytest
import torch

from garo_ns.render import tile_lists as tile_lists_module
from garo_ns.render.reference import intersect_tiles, project, rasterize
from garo_ns.render.tile_lists import TileGrid, smallest_sigma, tile_lists

W, H = 70, 45  # 5 x 3 tiles, the last column and row partial


def _scene(n: int = 400, seed: int = 0):
    """Random splats in front of a camera: sizes from specks to a third of the image, opacities from under 1/255 up,
    a few sharing one depth (the sort must keep their order)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 3.0, 3.0]) - torch.tensor([2.0, 1.5, -2.0])
    means[:20, 2] = 3.0
    scales = torch.exp(torch.rand(n, 3, generator=g) * 4 - 5.5)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    opacities = torch.rand(n, generator=g) ** 3
    colors = torch.rand(n, 3, generator=g)
    return means, quats, scales, opacities, colors


def _camera():
    K = torch.tensor([[[60.0, 0.0, W / 2 + 1.3], [0.0, 58.0, H / 2 - 0.7], [0.0, 0.0, 1.0]]])
    return torch.eye(4)[None], K


def _projected(seed: int = 0):
    from garo_ns.render.reference import covariance

    means, quats, scales, opacities, colors = _scene(seed=seed)
    viewmat, K = _camera()
    radii, means2d, depths, conics = project(means, covariance(quats, scales), viewmat, K, W, H)
    return radii[0], means2d[0], depths[0], conics[0], opacities, colors


def composite(means2d, conics, colors, opacities, flatten_ids, offsets, width, height, tile=16):
    """gsplat's forward compositing over given lists, without a background (slow; small images only): a tile per
    entry of `offsets` [1, rows, columns], its pairs up to the next tile's offset (the last tile's to the end of the
    buffer); pixels outside width x height are done from the start, and a tile whose pixels are all done stops before
    reading another pair."""
    _, rows, cols = offsets.shape
    image = torch.zeros(rows * tile, cols * tile, colors.shape[-1], dtype=torch.float64)
    flat = offsets.flatten().tolist()
    for t in range(rows * cols):
        start, end = flat[t], flat[t + 1] if t + 1 < rows * cols else flatten_ids.numel()
        ty, tx = divmod(t, cols)
        iy, ix = torch.meshgrid(torch.arange(tile) + ty * tile, torch.arange(tile) + tx * tile, indexing="ij")
        py, px = iy + 0.5, ix + 0.5
        T = torch.ones(tile, tile, dtype=torch.float64)
        done = (iy >= height) | (ix >= width)
        out = torch.zeros(tile, tile, colors.shape[-1], dtype=torch.float64)
        for k in flatten_ids[start:end].tolist():
            if done.all():
                break
            a, b, c = conics[k].double()
            dx, dy = means2d[k, 0].double() - px, means2d[k, 1].double() - py
            sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
            alpha = torch.clamp_max(opacities[k].double() * torch.exp(-sigma), 0.999)
            skip = (sigma < 0) | (alpha < 1 / 255) | done
            next_t = T * (1 - alpha)
            stop = ~skip & (next_t <= 1e-4)
            take = ~skip & ~stop
            out += torch.where(take[..., None], colors[k].double() * (alpha * T)[..., None], 0.0)
            T = torch.where(take, next_t, T)
            done = done | stop
        image[ty * tile : (ty + 1) * tile, tx * tile : (tx + 1) * tile] = out
    return image[:height, :width]


@pytest.mark.parametrize("wide_keys", [False, True])
def test_uncut_lists_are_gsplats_pairs_in_gsplats_order(monkeypatch, wide_keys):
    if wide_keys:  # as for a frame whose tiles x splats pass 32 bits
        monkeypatch.setattr(tile_lists_module, "INT32_KEYS", 0)
    radii, means2d, depths, conics, opacities, _ = _projected()
    grid = TileGrid(W, H)
    _, ref_tiles, ref_ids = intersect_tiles(means2d[None], radii[None], depths[None], 16, grid.tiles_w, grid.tiles_h)
    ids, offsets, needed = tile_lists(means2d, conics, opacities, depths, radii, grid, len(ref_ids) + 37, cut=False)
    assert int(needed) == len(ref_ids) > 0
    assert torch.equal(ids[: len(ref_ids)].long(), ref_ids) and (ids[len(ref_ids) :] == 0).all()
    starts = torch.searchsorted(ref_tiles, torch.arange(grid.n_tiles)).int()
    assert torch.equal(offsets.flatten(), starts)
    # the unused tail lies in the last tile, below the image
    assert int(offsets.flatten()[-1]) == len(ref_ids)


def test_cut_pairs_are_ones_no_pixel_of_their_tile_shows():
    radii, means2d, depths, conics, opacities, _ = _projected(seed=1)
    grid = TileGrid(W, H)
    capacity = 20_000
    full, full_offsets, needed = tile_lists(means2d, conics, opacities, depths, radii, grid, capacity, cut=False)
    cut, offsets, needed_cut = tile_lists(means2d, conics, opacities, depths, radii, grid, capacity)
    assert int(needed_cut) <= int(needed) < capacity

    def pairs(ids, offs):
        flat = offs.flatten().tolist() + [capacity]
        return [(t, k) for t in range(grid.n_tiles - 1) for k in ids[flat[t] : flat[t + 1]].tolist()]

    kept, before = pairs(cut, offsets), pairs(full, full_offsets)
    assert len(kept) < 0.7 * len(before)
    # kept pairs keep the uncut order within each tile
    for t in range(grid.n_tiles - 1):
        mine = [k for tt, k in kept if tt == t]
        theirs = [k for tt, k in before if tt == t and k in set(mine)]
        assert mine == theirs
    # a dropped pair: at every pixel centre of its tile (inside the image) the splat's alpha is under 1/255
    dropped = set(before) - set(kept)
    assert dropped
    for t, k in dropped:
        ty, tx = divmod(t, grid.tiles_w)
        xs = torch.arange(tx * 16, min(tx * 16 + 16, W)) + 0.5
        ys = torch.arange(ty * 16, min(ty * 16 + 16, H)) + 0.5
        py, px = torch.meshgrid(ys, xs, indexing="ij")
        a, b, c = conics[k]
        dx, dy = means2d[k, 0] - px, means2d[k, 1] - py
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        assert (opacities[k] * torch.exp(-sigma)).max() < 1 / 255, (t, k)


def test_the_lists_composite_the_reference_image():
    from garo_ns.render.reference import covariance

    means, quats, scales, opacities, colors = _scene(seed=2)
    viewmat, K = _camera()
    ref, _, _ = rasterize(means, quats, scales, opacities, colors, viewmat, K, W, H, sh_degree=None)
    radii, means2d, depths, conics = (x[0] for x in project(means, covariance(quats, scales), viewmat, K, W, H))
    grid = TileGrid(W, H)
    images = []
    for cut in (False, True):
        ids, offsets, needed = tile_lists(means2d, conics, opacities, depths, radii, grid, 9000, cut=cut)
        # the unused pairs: in the tile row below the image, pointing at a splat that exists
        assert offsets.shape == (1, grid.tiles_h + 1, grid.tiles_w) and int(offsets.flatten()[-1]) < 9000
        assert (ids[int(offsets.flatten()[-1]) :] == 0).all()
        images.append(composite(means2d, conics, colors, opacities, ids, offsets, W, H))
    assert torch.equal(images[0], images[1])  # cutting changes no pixel
    assert torch.allclose(images[1].float(), ref[0], atol=2e-5)


def test_too_small_a_capacity_says_so_and_an_empty_frame_is_blocked():
    radii, means2d, depths, conics, opacities, _ = _projected()
    grid = TileGrid(W, H)
    ids, offsets, needed = tile_lists(means2d, conics, opacities, depths, radii, grid, 10)
    assert int(needed) > 10 and ids.shape == (10,)
    ids, offsets, needed = tile_lists(means2d[:0], conics[:0], opacities[:0], depths[:0], radii[:0], grid, 8)
    assert int(needed) == 0 and (ids == 0).all() and (offsets == 0).all()


@pytest.mark.parametrize("seed", range(3))
def test_the_smallest_exponent_over_a_rectangle_is_the_brute_force_one(seed):
    g = torch.Generator().manual_seed(seed)
    n = 200
    L = torch.randn(n, 2, 2, generator=g, dtype=torch.float64)
    cov = L @ L.transpose(-1, -2) * 30 + torch.eye(2, dtype=torch.float64) * 0.3
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    means2d = torch.rand(n, 2, generator=g, dtype=torch.float64) * 60 - 10
    x0, y0 = torch.rand(n, generator=g, dtype=torch.float64) * 40, torch.rand(n, generator=g, dtype=torch.float64) * 40
    x1, y1 = x0 + 15, y0 + 15
    least = smallest_sigma(means2d, conics, x0, x1, y0, y1)
    t = torch.linspace(0, 1, 301, dtype=torch.float64)
    px = x0[:, None, None] + 15 * t[None, :, None]
    py = y0[:, None, None] + 15 * t[None, None, :]
    dx, dy = px - means2d[:, 0, None, None], py - means2d[:, 1, None, None]
    a, b, c = (v[:, None, None] for v in conics.unbind(-1))
    brute = (0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy).flatten(1).min(1).values
    assert (least <= brute + 1e-9).all()  # never above a point's exponent: a cut is never wrong
    assert torch.allclose(least, brute, rtol=1e-3, atol=1e-3)  # and tight: the grid's spacing is 0.05 px
    assert math.isclose(
        float(
            smallest_sigma(
                means2d[:1], conics[:1], means2d[:1, 0] - 1, means2d[:1, 0] + 1, means2d[:1, 1] - 1, means2d[:1, 1] + 1
            )
        ),
        0.0,
    )


@pytest.mark.parametrize("cut", [False, True])
def test_the_pair_kernel_makes_the_torch_pairs(monkeypatch, cut):
    """The Triton kernel a GPU frame uses (through Triton's interpreter here) against the torch path, pair for pair,
    and the lists it gives against the torch path's."""
    pytest.importorskip("triton", reason="Triton is not installed: the torch path makes the pairs")
    radii, means2d, depths, conics, opacities, _ = _projected(seed=3)
    grid = TileGrid(W, H)
    capacity = 5000
    monkeypatch.setattr(tile_lists_module, "runs_on", lambda device: False)
    want = tile_lists(means2d, conics, opacities, depths, radii, grid, capacity, cut=cut)
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    monkeypatch.setattr(tile_lists_module, "runs_on", lambda device: True)
    got = tile_lists(means2d, conics, opacities, depths, radii, grid, capacity, cut=cut)
    assert int(got[2]) == int(want[2]) < capacity
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    assert int((want[0] < len(radii)).sum()) > 100
