"""Tile lists built without a host read: gsplat's lists, entry for entry, whenever the capacity holds them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from garo_ns.render.tiles import TileCapacity, tile_lists

TILE = 16


def gsplat_lists(means2d, radii, depths, tiles_w, tiles_h):
    """gsplat's `isect_tiles` (one camera, sorted) and `isect_offset_encode`, written out as loops in fp32: keys,
    Gaussian ids, tiles per Gaussian and each tile's first entry."""
    entries, counts = [], []
    for i in range(means2d.shape[0]):
        radius = np.float32(radii[i])
        if radius <= 0:
            counts.append(0)
            continue
        size = np.float32(TILE)
        r, x, y = radius / size, np.float32(means2d[i, 0]) / size, np.float32(means2d[i, 1]) / size

        def cell(v, limit):  # a float cast to uint32 saturates at 0 on the GPU
            return min(max(0, int(v)) if v >= 0 else 0, limit)

        x0, x1 = cell(math.floor(x - r), tiles_w), cell(math.ceil(x + r), tiles_w)
        y0, y1 = cell(math.floor(y - r), tiles_h), cell(math.ceil(y + r), tiles_h)
        counts.append((x1 - x0) * (y1 - y0))
        bits = int(np.float32(depths[i]).view(np.int32)) & 0xFFFFFFFF
        for row in range(y0, y1):
            for col in range(x0, x1):
                entries.append((((row * tiles_w + col) << 32) | bits, i))
    entries.sort(key=lambda e: e[0])  # stable: ties keep the order written (Gaussian, then row, then column)
    keys = [k for k, _ in entries]
    tiles = [k >> 32 for k in keys]
    offsets = [next((j for j, t in enumerate(tiles) if t >= tile), len(tiles)) for tile in range(tiles_w * tiles_h)]
    return keys, [g for _, g in entries], counts, offsets


def scene(n=300, width=100, height=70, seed=0):
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(1, n, 2, generator=g) * torch.tensor([width + 100.0, height + 100.0]) - 50.0
    radii = (torch.rand(1, n, generator=g) * 60).to(torch.int32)
    radii[0, ::7] = 0  # culled
    depths = torch.rand(1, n, generator=g) * 5 + 0.1
    depths[0, 1::5] = depths[0, 0]  # ties: equal keys in a shared tile keep the Gaussians' order
    return means2d, radii, depths, math.ceil(width / TILE), math.ceil(height / TILE)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_lists_are_gsplats_entry_for_entry_when_the_capacity_holds_them(seed):
    means2d, radii, depths, tw, th = scene(seed=seed)
    keys, ids, counts, offsets = gsplat_lists(means2d[0].numpy(), radii[0].numpy(), depths[0].numpy(), tw, th)
    total = len(keys)
    lists = tile_lists(means2d, radii, depths, TILE, tw, th, capacity=total + 777)
    assert int(lists.total) == total and lists.counts[0].tolist() == counts
    assert lists.isect_ids[:total].tolist() == keys and lists.flatten_ids[:total].tolist() == ids
    assert lists.offsets.shape == (1, th + 1, tw) and lists.offsets.dtype == torch.int32
    assert lists.offsets[0, :th].flatten().tolist() == offsets
    # The padding lies in the extra row below the image, spread over its tiles, each Gaussian index valid.
    pad_tiles = lists.isect_ids[total:] >> 32
    assert bool((pad_tiles >= th * tw).all()) and bool((pad_tiles < (th + 1) * tw).all())
    spread = torch.bincount(pad_tiles - th * tw, minlength=tw)
    assert int(spread.max()) - int(spread.min()) <= 1
    assert int(lists.flatten_ids.min()) >= 0 and int(lists.flatten_ids.max()) < means2d.shape[1]
    # The first dummy tile starts where the real entries end.
    assert int(lists.offsets[0, th, 0]) == total


def test_a_capacity_too_small_keeps_the_first_entries_and_the_next_step_grows_it():
    means2d, radii, depths, tw, th = scene()
    keys, ids, _, _ = gsplat_lists(means2d[0].numpy(), radii[0].numpy(), depths[0].numpy(), tw, th)
    total = len(keys)
    short = tile_lists(means2d, radii, depths, TILE, tw, th, capacity=total // 2)
    assert int(short.total) == total and short.isect_ids.numel() == total // 2
    assert int((short.isect_ids >> 32).max()) < th * tw  # no room left for padding: every entry is a real one
    capacity = TileCapacity(margin=1.5, step=64)
    first = capacity(means2d, radii, depths, TILE, tw, th)  # a new count of Gaussians: measured, with margin
    assert capacity.capacity == math.ceil(1.5 * total / 64) * 64
    assert first.isect_ids[:total].tolist() == keys and capacity.overflows == 0
    # A later step, same Gaussians, needs more entries than the capacity holds (larger footprints on screen).
    wide = radii * 3
    need = len(gsplat_lists(means2d[0].numpy(), wide[0].numpy(), depths[0].numpy(), tw, th)[0])
    assert need > capacity.capacity
    over = capacity(means2d, wide, depths, TILE, tw, th)
    assert int(over.total) == need and over.isect_ids.numel() < need and capacity.overflows == 0  # not read yet
    capacity(means2d, radii, depths, TILE, tw, th)  # the step after reads its total: counted, and the capacity grows
    assert capacity.overflows == 1 and capacity.largest == need
    assert capacity.capacity == math.ceil(1.5 * need / 64) * 64


def test_no_gaussians_give_lists_of_padding_only():
    lists = tile_lists(torch.zeros(1, 0, 2), torch.zeros(1, 0, dtype=torch.int32), torch.zeros(1, 0), TILE, 4, 3, 10)
    assert int(lists.total) == 0 and lists.counts.shape == (1, 0)
    assert bool(((lists.isect_ids >> 32) >= 12).all()) and lists.offsets[0, :3].abs().sum() == 0


@pytest.mark.slow
@pytest.mark.parametrize("on", [False, True])
def test_a_training_model_hands_the_rasterizer_its_capacity_when_set(tmp_path, monkeypatch, on):
    import garo_ns.garo_model as garo_model
    from garo_ns.tools.scene import SceneSpec, generate_scene
    from garo_ns.tools.train import QuickSchedule, make_config, train

    seen = []
    render = garo_model.render_splats

    def spy(*args, **kwargs):
        seen.append(kwargs.get("tile_lists"))
        return render(*args, **kwargs)

    monkeypatch.setattr(garo_model, "render_splats", spy)
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=16, n_train=4, n_val=1, n_test=1))
    schedule = QuickSchedule(steps=6, num_random=300, deform_width=16, deform_depth=2, deform_skip=0)
    config = make_config("garo-deform", scene, tmp_path / "runs", schedule=schedule)
    config.pipeline.model.rasterizer = "reference"  # on a CPU the lean path, and so the lists, are not taken
    config.pipeline.model.train_tiles_without_wait = on
    model = train(config).pipeline.model
    assert len(seen) >= 6
    assert all(x is model.tile_capacity for x in seen) if on else all(x is None for x in seen)
