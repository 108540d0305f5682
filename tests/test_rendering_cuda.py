"""The lean CUDA rasterization path against gsplat's own `rasterization` (same kernels, so the
same pixels). Needs a CUDA device (run on the GPU machine)."""

from __future__ import annotations

import pytest
import torch

from garo_ns.render.backend import rasterize, rasterize_lean
from garo_ns.render.graphs import InputGraph
from garo_ns.render.kernels import lean_front

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat's kernels need a CUDA device")


def _scene(n: int = 20_000, seed: int = 0):
    g = torch.Generator(device="cpu").manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2.0
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 4.0)
    opacities = torch.rand(n, generator=g)
    colors = torch.randn(n, 16, 3, generator=g) * 0.3
    viewmat = torch.eye(4)[None]
    viewmat[0, :3, 3] = torch.tensor([0.1, -0.2, 4.0])  # the cloud 3 to 5 units ahead, in view
    K = torch.tensor([[[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]]])
    return [t.cuda() for t in (means, quats, scales, opacities, colors, viewmat, K)]


@torch.no_grad()
@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_lean_path_gives_gsplat_pixels(mode):
    means, quats, scales, opacities, colors, viewmat, K = _scene()
    background = torch.tensor([[0.1, 0.2, 0.3]], device="cuda")
    kwargs = dict(sh_degree=3, backgrounds=background, render_mode=mode, backend="cuda")
    ref, ref_alpha, _ = rasterize(means, quats, scales, opacities, colors, viewmat, K, 320, 240, **kwargs)
    lean, alpha, info = rasterize(means, quats, scales, opacities, colors, viewmat, K, 320, 240, lean=True, **kwargs)
    assert info["n_cameras"] == 1 and "means2d" in info
    assert float(ref_alpha.mean()) > 0.05  # the scene is in view
    torch.testing.assert_close(alpha, ref_alpha, rtol=0, atol=1e-6)
    torch.testing.assert_close(lean, ref, rtol=0, atol=1e-5)


def test_lean_under_autograd_takes_the_training_path():
    means, quats, scales, opacities, colors, viewmat, K = _scene(2000)
    means.requires_grad_(True)
    render, _, info = rasterize(means, quats, scales, opacities, colors, viewmat, K, 64, 48, sh_degree=3, lean=True)
    assert type(render.grad_fn).__name__ == "_CompositeBackward"  # garo_ns.render.train_raster, not gsplat's
    render.sum().backward()
    assert means.grad is not None and "gaussian_ids" in info  # with gsplat's info keys


@torch.no_grad()
@pytest.mark.parametrize("reach", [False, True])
@pytest.mark.parametrize("with_depth", [False, True])
def test_projection_graph_gives_the_lean_pixels(with_depth, reach):
    # The model's camera graph: projection, view directions and visibility captured once, then
    # replayed for each camera; the SH and compositing kernels run after it. With `reach`, the tile lists'
    # alpha-reach cut captured in it too: fewer pairs, the same pixels.
    means, quats, scales, opacities, colors, viewmat, K = _scene()
    cut = opacities if reach else None
    background = torch.tensor([[0.1, 0.2, 0.3]], device="cuda")
    graph = InputGraph()
    for shift in (0.0, 0.3, -0.2):
        view = viewmat.clone()
        view[0, 0, 3] += shift
        front = graph(
            "scene", lambda v, k: lean_front(means, quats, scales, v, k, 320, 240, True, opacities=cut), view, K
        )
        args = (means, quats, scales, opacities, colors, view, K, 320, 240, 3, background, with_depth)
        ref, ref_alpha, _ = rasterize_lean(*args)
        got, alpha, info = rasterize_lean(*args, front=front)
        assert float(ref_alpha.mean()) > 0.05
        assert torch.equal(alpha, ref_alpha) and torch.equal(got, ref)
        assert info["radii"] is front[0]
        fewer = bool((front[6] <= front[0]).all()) and int(front[6].sum()) < int(front[0].sum())
        assert fewer if reach else front[6] is front[0]
    assert graph.captures == 1


@torch.no_grad()
def test_lean_falls_back_for_channel_counts_it_cannot_composite():
    means, quats, scales, opacities, _, viewmat, K = _scene(2000)
    features = torch.rand(2000, 2, device="cuda")  # two channels, no SH: gsplat pads them
    ref, _, _ = rasterize(means, quats, scales, opacities, features, viewmat, K, 64, 48)
    lean, _, info = rasterize(means, quats, scales, opacities, features, viewmat, K, 64, 48, lean=True)
    assert lean.shape[-1] == 2 and "gaussian_ids" in info  # gsplat's own path, with its info
    torch.testing.assert_close(lean, ref, rtol=0, atol=0)


def test_the_cameras_keep_fp32_precision_while_a_training_step_allows_tf32():
    """get_outputs turns cuBLAS TF32 on for a training step before it builds the step's camera: the view matrix and
    the SH camera centre must stay exact fp32 (their products are sums, not cuBLAS calls)."""
    from garo_ns.render.view import camera_centres, viewmat_from_c2w

    g = torch.Generator().manual_seed(3)
    rot, _ = torch.linalg.qr(torch.randn(8, 3, 3, generator=g, dtype=torch.float64))
    centres = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=torch.float64), dim=-1) * 4.0
    c2w64 = torch.cat([rot, centres[..., None]], dim=-1)
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = True
    try:
        view = viewmat_from_c2w(c2w64.float().cuda())
        centre = camera_centres(view)
        # What a cuBLAS product gives here, for the record (-s shows it): the error the sums avoid.
        product = -(view[:, :3, :3].transpose(1, 2) @ view[:, :3, 3:4]).squeeze(-1)
        print("TF32-allowed product's camera-centre error:", float((product.double().cpu() - centres).abs().max()))
    finally:
        torch.backends.cuda.matmul.allow_tf32 = was
    torch.testing.assert_close(centre.double().cpu(), centres, rtol=0, atol=2e-6)
    flipped = torch.eye(4, dtype=torch.float64).repeat(8, 1, 1)
    flipped[:, :3, :4] = c2w64
    flipped[:, :3, 1:3] *= -1
    torch.testing.assert_close(view.double().cpu(), torch.linalg.inv(flipped), rtol=0, atol=2e-6)
