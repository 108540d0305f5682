"""The reference rasterizer against gsplat's pure-torch functions, a brute-force compositor,
finite differences, and hard inputs."""

from __future__ import annotations

import math

import pytest
import torch
from gsplat.cuda import _torch_impl as gs

from garo_ns.render.reference import composite, covariance, intersect_tiles, project, rasterize
from garo_ns.render.sh import eval_sh


def camera(width=64, height=48, distance=4.0, n=1, seed=0):
    """n cameras looking at the origin from `distance`, gsplat world-to-camera convention."""
    g = torch.Generator().manual_seed(seed)
    views = []
    for _ in range(n):
        axis = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0)
        angle = float(torch.rand(1, generator=g)) * 0.6
        k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = torch.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
        v = torch.eye(4)
        v[:3, :3] = rot
        v[2, 3] = distance
        views.append(v)
    f = 0.5 * width / math.tan(0.35)
    K = torch.tensor([[f, 0, width / 2 + 1.3], [0, f * 1.01, height / 2 - 0.7], [0, 0, 1.0]])
    return torch.stack(views), K[None].repeat(n, 1, 1), width, height


def cloud(n=300, seed=0, spread=1.0, scale=(0.01, 0.08)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2 - 1) * spread
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * (scale[1] - scale[0]) + scale[0]
    opac = torch.rand(n, generator=g) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g)
    return means, quats, scales, opac, colors


def test_projection_matches_gsplat_torch():
    means, quats, scales, _, _ = cloud(500, spread=1.8)
    views, Ks, W, H = camera(n=2)
    covars = covariance(quats, scales)
    radii, m2d, depths, conics = project(means, covars, views, Ks, W, H)
    ref_radii, ref_m2d, ref_depths, ref_conics, _ = gs._fully_fused_projection(means, covars, views, Ks, W, H)
    assert (radii > 0).sum() > 100 and (radii == 0).sum() > 0  # both visible and culled Gaussians present
    assert torch.equal(radii, ref_radii)
    vis = radii > 0
    torch.testing.assert_close(m2d[vis], ref_m2d[vis], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(depths[vis], ref_depths[vis])
    torch.testing.assert_close(conics[vis], ref_conics[vis], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat_torch(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(200, 3, generator=g)
    coeffs = torch.randn(200, 16, 3, generator=g)
    torch.testing.assert_close(eval_sh(degree, dirs, coeffs), gs._spherical_harmonics(degree, dirs, coeffs))


def test_tile_intersection_matches_gsplat_torch():
    means, quats, scales, _, _ = cloud(40, seed=3, spread=1.5, scale=(0.02, 0.3))
    views, Ks, W, H = camera(n=2, seed=3)
    radii, m2d, depths, _ = project(means, covariance(quats, scales), views, Ks, W, H)
    tw, th = math.ceil(W / 16), math.ceil(H / 16)
    per_gauss, tile_ids, flat_ids = intersect_tiles(m2d, radii, depths, 16, tw, th)
    ref_per_gauss, isect_ids, ref_flat = gs._isect_tiles(m2d, radii, depths, 16, tw, th)
    bits = (tw * th).bit_length()
    ref_tiles = (isect_ids >> 32 >> bits) * (tw * th) + ((isect_ids >> 32) & ((1 << bits) - 1))
    assert torch.equal(per_gauss, ref_per_gauss)
    assert torch.equal(tile_ids, ref_tiles)
    assert torch.equal(flat_ids, ref_flat.long())


def brute_force(means2d, conics, opacities, features, radii, depths, W, H, tile=16):
    """Per-pixel loop over depth-sorted Gaussians of the pixel's tile, gsplat's rules."""
    C, N = opacities.shape
    out = torch.zeros(C, H, W, features.shape[-1], dtype=means2d.dtype)
    alpha_out = torch.zeros(C, H, W, 1, dtype=means2d.dtype)
    for c in range(C):
        order = torch.argsort(depths[c], stable=True)
        for y in range(H):
            for x in range(W):
                tx, ty = x // tile, y // tile
                T = 1.0
                for n in order.tolist():
                    r = float(radii[c, n])
                    if r <= 0:
                        continue
                    mx, my = means2d[c, n].tolist()
                    lo_x, hi_x = math.floor((mx - r) / tile), math.ceil((mx + r) / tile)
                    lo_y, hi_y = math.floor((my - r) / tile), math.ceil((my + r) / tile)
                    if not (lo_x <= tx < hi_x and lo_y <= ty < hi_y):
                        continue
                    dx, dy = x + 0.5 - mx, y + 0.5 - my
                    a, b, cc = conics[c, n].tolist()
                    sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    alpha = min(0.999, float(opacities[c, n]) * math.exp(-sigma))
                    if sigma < 0 or alpha < 1 / 255:
                        continue
                    if T * (1 - alpha) <= 1e-4:
                        break
                    out[c, y, x] += alpha * T * features[c, n]
                    T *= 1 - alpha
                alpha_out[c, y, x] = 1 - T
    return out, alpha_out


def test_compositing_matches_brute_force_including_early_stop():
    means, quats, scales, opac, colors = cloud(60, seed=5, spread=0.6, scale=(0.05, 0.25))
    opac[:20] = 0.999  # opaque ones make pixels saturate and stop early
    views, Ks, W, H = camera(width=40, height=24, n=1, seed=5)
    img, alpha, info = rasterize(means, quats, scales, opac, colors, views, Ks, W, H, chunk=7)
    ref, ref_alpha = brute_force(
        info["means2d"].detach(), info["conics"], info["opacities"], colors[None], info["radii"], info["depths"], W, H
    )
    assert (ref_alpha > 0.999).any(), "the case must exercise early termination"
    torch.testing.assert_close(img, ref, atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(alpha, ref_alpha, atol=2e-5, rtol=1e-4)


@pytest.mark.parametrize("alpha_min", [1 / 255, 0.0])
def test_block_culling_changes_neither_pixels_nor_gradients(alpha_min):
    """Blocks of 2, 4 and 16 px (16: the whole tile) composite the same image with the same gradients:
    the block lists drop only pairs whose alpha stays below alpha_min at every pixel of the block."""
    means, quats, scales, opac, colors = cloud(150, seed=6, spread=0.8, scale=(0.02, 0.2))
    opac[:20] = 0.999  # saturated pixels: the early stop inside a block
    views, Ks, W, H = camera(width=36, height=20, n=2, seed=6)
    radii, m2d, depths, conics = project(means, covariance(quats, scales), views, Ks, W, H)
    _, tile_ids, flat_ids = intersect_tiles(m2d, radii, depths, 16, math.ceil(W / 16), math.ceil(H / 16))
    feats = colors[None].expand(2, -1, -1)
    results = []
    for block in (16, 4, 2):
        args = [t.detach().clone().requires_grad_() for t in (m2d, conics, opac[None].expand(2, -1), feats)]
        img, alpha = composite(*args, tile_ids, flat_ids, W, H, chunk=9, alpha_min=alpha_min, block_size=block)
        (img.square().sum() + alpha.sum()).backward()
        results.append((img.detach(), alpha.detach(), [a.grad for a in args]))
    assert (results[0][1] > 0.999).any()
    for img, alpha, grads in results[1:]:
        torch.testing.assert_close(img, results[0][0], atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(alpha, results[0][1], atol=1e-6, rtol=1e-5)
        for got, want in zip(grads, results[0][2]):
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4)


def test_batches_of_blocks_recomputed_in_backward_give_the_same_result():
    """A small max_elements splits the blocks into batches, each recomputed in backward (checkpoint)."""
    means, quats, scales, opac, colors = cloud(150, seed=7, spread=0.8, scale=(0.02, 0.2))
    views, Ks, W, H = camera(width=36, height=20, n=2, seed=7)
    radii, m2d, depths, conics = project(means, covariance(quats, scales), views, Ks, W, H)
    _, tile_ids, flat_ids = intersect_tiles(m2d, radii, depths, 16, math.ceil(W / 16), math.ceil(H / 16))
    results = []
    for max_elements in (1 << 22, 1 << 13):
        args = [t.detach().clone().requires_grad_() for t in (m2d, conics, opac[None].expand(2, -1), colors[None])]
        args[3] = args[3].expand(2, -1, -1)
        img, alpha = composite(*args[:3], args[3], tile_ids, flat_ids, W, H, max_elements=max_elements)
        (img.square().sum() + alpha.sum()).backward()
        results.append((img.detach(), alpha.detach(), [a.grad for a in args[:3]]))
    torch.testing.assert_close(results[1][0], results[0][0])
    torch.testing.assert_close(results[1][1], results[0][1])
    for got, want in zip(results[1][2], results[0][2]):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


def test_composite_gradcheck_float64():
    torch.manual_seed(0)
    C, N, W, H = 1, 4, 8, 8
    means2d = torch.tensor([[[2.5, 3.0], [5.0, 4.5], [3.7, 6.1], [6.2, 1.9]]], dtype=torch.float64)
    conics = torch.tensor(
        [[[0.30, 0.05, 0.25], [0.2, -0.04, 0.3], [0.5, 0.1, 0.4], [0.15, 0.0, 0.2]]], dtype=torch.float64
    )
    opac = torch.tensor([[0.6, 0.5, 0.7, 0.4]], dtype=torch.float64)
    feats = torch.rand(C, N, 3, dtype=torch.float64)
    radii = torch.full((C, N), 8, dtype=torch.int32)
    depths = torch.tensor([[1.0, 2.0, 3.0, 4.0]], dtype=torch.float64)
    _, tile_ids, flat_ids = intersect_tiles(means2d, radii, depths, 4, 2, 2)

    def f(m, c, o, x):
        img, a = composite(m, c, o, x, tile_ids, flat_ids, W, H, tile_size=4, chunk=3)
        return img, a

    args = tuple(t.clone().requires_grad_() for t in (means2d, conics, opac, feats))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


def test_several_cameras_equal_separate_renders_and_background():
    means, quats, scales, opac, _ = cloud(200, seed=1)
    sh = torch.randn(200, 16, 3) * 0.3
    views, Ks, W, H = camera(n=3, seed=1)
    bg = torch.tensor([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    img, alpha, info = rasterize(means, quats, scales, opac, sh, views, Ks, W, H, sh_degree=3, backgrounds=bg)
    assert info["n_cameras"] == 3 and info["means2d"].shape == (3, 200, 2)
    for c in range(3):
        one, a1, _ = rasterize(
            means,
            quats,
            scales,
            opac,
            sh,
            views[c : c + 1],
            Ks[c : c + 1],
            W,
            H,
            sh_degree=3,
            backgrounds=bg[c : c + 1],
        )
        torch.testing.assert_close(img[c : c + 1], one)
        torch.testing.assert_close(alpha[c : c + 1], a1)
    empty = alpha[..., 0] == 0
    assert empty.any()
    torch.testing.assert_close(img[empty], bg[:, None, None, :].expand(3, H, W, 3)[empty])


def test_alpha_threshold_skips_faint_gaussians_and_can_be_moved():
    """A Gaussian whose peak alpha is below 1/255 is skipped (gsplat's rule); lowering the
    threshold, as the parity benchmark's band does, brings it back."""
    views, Ks, W, H = camera(seed=2)
    means = torch.zeros(1, 3)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), 0.2)
    colors = torch.ones(1, 3)
    faint = torch.tensor([0.9 / 255])
    img, alpha, _ = rasterize(means, quats, scales, faint, colors, views, Ks, W, H)
    assert float(alpha.max()) == 0.0 and float(img.max()) == 0.0
    img, alpha, _ = rasterize(means, quats, scales, faint, colors, views, Ks, W, H, alpha_min=0.5 / 255)
    assert 0.8 / 255 < float(alpha.max()) < 0.9 / 255
    strong = torch.tensor([0.5])
    base = rasterize(means, quats, scales, strong, colors, views, Ks, W, H)[0]
    same = rasterize(means, quats, scales, strong, colors, views, Ks, W, H, alpha_min=1.0 / 255)[0]
    assert torch.equal(base, same)


def test_depth_modes_and_means2d_gradient():
    means, quats, scales, opac, colors = cloud(150, seed=2)
    means = means.requires_grad_()
    views, Ks, W, H = camera(seed=2)
    img, alpha, info = rasterize(means, quats, scales, opac, colors, views, Ks, W, H, render_mode="RGB+ED")
    assert img.shape == (1, H, W, 4)
    info["means2d"].retain_grad()
    img[..., :3].sum().backward()
    g = info["means2d"].grad
    assert g is not None and torch.isfinite(g).all()
    visible = info["radii"] > 0
    assert g[visible].abs().sum() > 0 and g[~visible].abs().sum() == 0
    d = img[..., 3][alpha[..., 0] > 0.5]
    assert d.min() > 4.0 - 1.8 and d.max() < 4.0 + 1.8  # expected depth lies within the cloud's depth range


@pytest.mark.parametrize(
    "case",
    [
        "behind",
        "near_plane",
        "zero_scale",
        "huge_scale",
        "inf_scale",
        "zero_quat",
        "transparent",
        "opaque",
        "empty",
        "looking_away",
        "nan_mean",
    ],
)
def test_hard_cases_stay_finite(case):
    means, quats, scales, opac, colors = cloud(100, seed=4)
    views, Ks, W, H = camera(seed=4)
    if case == "behind":
        means[:, 2] = -6.0  # camera at z=-4 in world looks along +z: these are behind it
    elif case == "near_plane":
        means[:50] = torch.tensor([0.0, 0.0, -4.0 + 0.01])
    elif case == "zero_scale":
        scales[:50] = 0.0
    elif case == "huge_scale":
        scales[:5] = 1e4
    elif case == "inf_scale":
        scales[:5] = float("inf")
    elif case == "zero_quat":
        quats[:50] = 0.0
    elif case == "transparent":
        opac[:] = 0.0
    elif case == "opaque":
        opac[:] = 1.0
    elif case == "empty":
        means, quats, scales, opac, colors = (t[:0] for t in (means, quats, scales, opac, colors))
    elif case == "looking_away":
        views = views.clone()
        views[0, :3, :3] = -views[0, :3, :3]
        views[0, 2, 3] = -4.0
    elif case == "nan_mean":
        means[:3] = float("nan")
    params = [t.clone().requires_grad_() for t in (means, quats, scales, opac, colors)]
    img, alpha, info = rasterize(*params, views, Ks, W, H, render_mode="RGB+ED")
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all()
    (img.sum() + alpha.sum()).backward()
    for p in params:
        assert p.grad is None or torch.isfinite(p.grad).all(), case
    if case in ("behind", "transparent", "empty", "looking_away"):
        assert alpha.max() == 0
    if case == "zero_quat":
        assert alpha.max() > 0


def test_bad_inputs_raise_value_errors_naming_the_argument():
    means, quats, scales, opac, colors = cloud(10)
    views, Ks, W, H = camera()
    with pytest.raises(ValueError, match="quats"):
        rasterize(means, quats[:5], scales, opac, colors, views, Ks, W, H)
    with pytest.raises(ValueError, match="Ks"):
        rasterize(means, quats, scales, opac, colors, views, Ks.repeat(2, 1, 1), W, H)
    bad = views.clone()
    bad[0, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="viewmats"):
        rasterize(means, quats, scales, opac, colors, bad, Ks, W, H)
    badk = Ks.clone()
    badk[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="Ks"):
        rasterize(means, quats, scales, opac, colors, views, badk, W, H)
    with pytest.raises(ValueError, match="width"):
        rasterize(means, quats, scales, opac, colors, views, Ks, 0, H)
    with pytest.raises(ValueError, match="colors"):
        rasterize(means, quats, scales, opac, colors, views, Ks, W, H, sh_degree=3)


def test_viewmat_inverts_the_pose_with_opencv_axes():
    from garo_ns.render.view import viewmat_from_c2w

    torch.manual_seed(0)
    rot, _ = torch.linalg.qr(torch.randn(2, 3, 3))
    c2w = torch.cat([rot, torch.randn(2, 3, 1)], dim=-1)
    flipped = torch.eye(4).repeat(2, 1, 1)
    flipped[:, :3, :4] = c2w
    flipped[:, :3, 1:3] *= -1  # OpenGL camera axes (nerfstudio) to OpenCV (gsplat)
    torch.testing.assert_close(viewmat_from_c2w(c2w), torch.linalg.inv(flipped), rtol=0, atol=1e-5)


def _poses_around_the_origin(n: int = 8, distance: float = 4.0) -> torch.Tensor:
    """D-NeRF-like camera-to-world poses [n, 3, 4]: random rotations, centres `distance` from the origin."""
    g = torch.Generator().manual_seed(3)
    rot, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    centres = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1) * distance
    return torch.cat([rot, centres[..., None]], dim=-1)


def _tf32(x: torch.Tensor) -> torch.Tensor:
    """fp32 values rounded to TF32's 10-bit mantissa (to nearest), as tensor cores read a product's inputs."""
    bits = x.contiguous().view(torch.int32)
    return ((bits + 0x1000) & ~0x1FFF).view(torch.float32)


def test_the_cameras_keep_fp32_precision_when_matrix_products_round_to_tf32(monkeypatch):
    """A training step lets cuBLAS round products' inputs to TF32 (`deform_train_tf32`). The camera's translation
    and centre must not go through such a product: rounded, a camera 4 units out moves by about 2e-3, half a pixel
    of an 800 x 800 D-NeRF image. Emulated here on the CPU by rounding every matrix product's inputs."""
    from garo_ns.render.view import camera_centres, viewmat_from_c2w

    matmul = torch.Tensor.__matmul__
    monkeypatch.setattr(torch.Tensor, "__matmul__", lambda a, b: matmul(_tf32(a), _tf32(b)))
    torch_matmul, bmm = torch.matmul, torch.bmm
    monkeypatch.setattr(torch, "matmul", lambda a, b, **k: torch_matmul(_tf32(a), _tf32(b), **k))
    monkeypatch.setattr(torch, "bmm", lambda a, b, **k: bmm(_tf32(a), _tf32(b), **k))
    c2w64 = _poses_around_the_origin()
    rounded = torch.ones(2, 3) * 4.001
    assert float((_tf32(rounded) - rounded).abs().max()) > 1e-4  # the emulation rounds as TF32 does
    flipped = torch.eye(4, dtype=torch.float64).repeat(len(c2w64), 1, 1)
    flipped[:, :3, :4] = c2w64
    flipped[:, :3, 1:3] *= -1
    expected = torch.linalg.inv(flipped)
    view = viewmat_from_c2w(c2w64.float())
    torch.testing.assert_close(view.double(), expected, rtol=0, atol=2e-6)
    torch.testing.assert_close(camera_centres(view).double(), c2w64[:, :, 3], rtol=0, atol=2e-6)


def test_a_gsplat_that_fails_to_load_is_said_once_and_recorded(monkeypatch, capsys):
    import builtins

    from garo_ns.bench.benchmark import environment
    from garo_ns.render import backend

    real_import = builtins.__import__

    def no_extension(name, *args, **kwargs):
        if name.startswith("gsplat.cuda._backend"):
            raise ImportError("libcudart.so.13: cannot open shared object file")
        return real_import(name, *args, **kwargs)

    backend.gsplat_cuda_available.cache_clear()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(builtins, "__import__", no_extension)
    try:
        assert backend.gsplat_cuda_available() is False
        assert backend.gsplat_cuda_available() is False  # cached: said once
        said = capsys.readouterr().err
        assert said.count("warning: gsplat's CUDA rasterizer cannot run") == 1 and "libcudart" in said
        assert backend.rasterizer_in_use("cuda").startswith("reference (gsplat failed: ImportError: libcudart")
        assert backend.rasterizer_in_use("cpu") == "reference"
    finally:
        backend.gsplat_cuda_available.cache_clear()
        backend._cuda_failure["reason"] = None
    monkeypatch.setattr(builtins, "__import__", real_import)
    assert environment("cpu")["rasterizer"] == "reference"
