"""The camera's share of a frame as one graph (garo_ns.render.frame_graph).

On the CPU, gsplat's two kernels are stood in for by the reference projection and by `composite` (tests/
test_tile_lists.py, which walks lists as gsplat's compositing kernel does), and the graph by an eager call: the frame
function's colours, depth channel, lists and the capacity's regrowth are checked against the reference
rasterizer. On a GPU, the real graph against the lean path's pixels.
"""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from test_tile_lists import composite

from garo_ns.render import frame_graph
from garo_ns.render.reference import covariance, project, rasterize
from garo_ns.render.tile_lists import TileGrid

W, H = 53, 37


def _scene(n: int = 300, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([3.0, 2.0, 2.0]) - torch.tensor([1.5, 1.0, -2.5])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.rand(n, 3, generator=g) * 3 - 5.0)
    opacities = torch.rand(n, generator=g)
    colors = torch.randn(n, 16, 3, generator=g) * 0.3
    viewmat = torch.eye(4)[None]
    viewmat[0, :3, 3] = torch.tensor([0.05, -0.1, 0.5])
    K = torch.tensor([[[45.0, 0.0, W / 2], [0.0, 45.0, H / 2], [0.0, 0.0, 1.0]]])
    return means, quats, scales, opacities, colors, viewmat, K


class _ReferenceKernels:
    """gsplat's projection and compositing kernels, as the reference rasterizer and the tests compute them."""

    @staticmethod
    def fully_fused_projection_fwd(means, covars, quats, scales, viewmats, Ks, width, height, eps2d, near, far, *_):
        radii, means2d, depths, conics = project(means, covariance(quats, scales), viewmats, Ks, width, height, eps2d)
        return radii, means2d, depths, conics, None

    @staticmethod
    def rasterize_to_pixels_fwd(means2d, conics, colors, opacities, bg, masks, width, height, tile, offsets, ids):
        image = composite(means2d[0], conics[0], colors[0], opacities[0], ids, offsets, width, height, tile)
        ones = torch.ones_like(colors[0][:, :1])
        alpha = composite(means2d[0], conics[0], ones, opacities[0], ids, offsets, width, height, tile)
        return (image + (1 - alpha) * bg[0]).float()[None], alpha.float()[None], None

    CameraModelType = SimpleNamespace(PINHOLE=0)


@pytest.fixture
def reference_kernels(monkeypatch):
    monkeypatch.setattr(frame_graph, "gsplat_kernels", lambda: _ReferenceKernels)
    monkeypatch.setattr("garo_ns.render.kernels.gsplat_kernels", lambda: _ReferenceKernels)


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_the_frame_function_renders_the_reference_image(reference_kernels, mode):
    means, quats, scales, opacities, colors, viewmat, K = _scene()
    background = torch.tensor([[0.1, 0.2, 0.3]])
    with_depth = mode == "RGB+ED"
    fn = frame_graph.frame_fn(means, quats, scales, opacities, colors, 3, TileGrid(W, H), 20_000, with_depth)
    render, alpha, radii, means2d, depths, needed = fn(viewmat, K, background)
    ref, ref_alpha, info = rasterize(
        means, quats, scales, opacities, colors, viewmat, K, W, H, sh_degree=3, backgrounds=background, render_mode=mode
    )
    assert render.shape == ref.shape == (1, H, W, 4 if with_depth else 3) and 0 < int(needed) < 20_000
    assert float(ref_alpha.mean()) > 0.1  # in view
    torch.testing.assert_close(alpha, ref_alpha, rtol=0, atol=2e-5)
    torch.testing.assert_close(render[..., :3], ref[..., :3], rtol=0, atol=2e-5)
    if with_depth:
        torch.testing.assert_close(render[..., 3], ref[..., 3], rtol=1e-4, atol=1e-4)
    assert torch.equal(radii, info["radii"])


class _EagerGraph:
    """InputGraph's interface, run eagerly (a CPU has no CUDA graphs); counts captures as new keys."""

    def __init__(self):
        self.key, self.captures = None, 0

    def __call__(self, key, fn, *inputs):
        if key != self.key:
            self.key, self.captures = key, self.captures + 1
        return fn(*inputs)

    def release(self):
        self.key = None


def test_a_frame_that_needs_more_pairs_is_rendered_again_with_room(reference_kernels, monkeypatch):
    monkeypatch.setattr(frame_graph, "GRANULE", 64)
    means, quats, scales, opacities, colors, viewmat, K = _scene(seed=1)
    graph = frame_graph.FrameGraph()
    graph._graph = _EagerGraph()
    background = torch.zeros(1, 3)
    render, alpha, info = graph(
        "splats", (means, quats, scales, opacities, colors), 3, viewmat, K, W, H, background, False
    )
    ref, _, _ = rasterize(means, quats, scales, opacities, colors, viewmat, K, W, H, sh_degree=3)
    torch.testing.assert_close(render, ref, rtol=0, atol=2e-5)
    assert graph.regrown == 1 and graph._graph.captures == 2 and graph.capacity > 64
    capacity = graph.capacity
    graph("splats", (means, quats, scales, opacities, colors), 3, viewmat, K, W, H, background, False)
    assert graph.regrown == 1 and graph._graph.captures == 2 and graph.capacity == capacity  # kept while it fits
    assert frame_graph.capacity_for(0) == 64 and frame_graph.capacity_for(100) == 128
    with pytest.raises(RuntimeError, match="int32"):  # past the rasterizer's offsets: the lean path renders it
        frame_graph.capacity_for(2**31 - 2**20)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat's kernels and CUDA graphs need a CUDA device")
@torch.no_grad()
@pytest.mark.parametrize("with_depth", [False, True])
def test_one_graph_gives_the_lean_pixels_on_cuda(with_depth):
    from garo_ns.render.backend import rasterize_lean

    means, quats, scales, opacities, colors, viewmat, _ = (t.cuda() for t in _scene(20_000, seed=2))
    # The small scene's camera centred on a 320x240 image: about 60% covered, many splats a tile.
    K = torch.tensor([[[260.0, 0.0, 160.0], [0.0, 260.0, 120.0], [0.0, 0.0, 1.0]]], device="cuda")
    background = torch.tensor([[0.1, 0.2, 0.3]], device="cuda")
    graph = frame_graph.FrameGraph()
    for shift in (0.0, 0.05, -0.08):
        view = viewmat.clone()
        view[0, 0, 3] += shift
        args = (means, quats, scales, opacities, colors)
        got, alpha, info = graph("scene", args, 3, view, K, 320, 240, background, with_depth)
        ref, ref_alpha, _ = rasterize_lean(*args, view, K, 320, 240, 3, background, with_depth)
        assert float(ref_alpha.mean()) > 0.05
        torch.testing.assert_close(alpha, ref_alpha, rtol=0, atol=1e-6)
        torch.testing.assert_close(got, ref, rtol=0, atol=2e-5)
    assert graph._graph.captures <= 2  # the first capture, and at most one regrowth


def test_a_frame_graph_that_cannot_be_captured_leaves_the_lean_path_rendering(monkeypatch, capsys):
    from garo_ns.render import frame
    from garo_ns.render.view import RenderView

    def refuse(*args):
        raise RuntimeError("operation not permitted when stream is capturing\nmore")

    path = frame.FramePath()
    path._frame_graph = refuse
    path._frame_graph.release = lambda: None
    monkeypatch.setattr(frame, "resolve_backend", lambda backend, device: "cuda")
    monkeypatch.setattr(frame, "render_splats", lambda *args: "lean")
    monkeypatch.setattr(frame.FramePath, "front", lambda self, splats, view: None)
    means, quats, scales, opacities, colors, viewmat, K = _scene(10)
    splats = frame.Splats(means, quats, scales, opacities, colors, graph=1)
    view = RenderView(viewmat, K, W, H, 0.0)
    with torch.no_grad():
        assert path.rasterize(splats, view, 3, None, "RGB", "auto", True, frame_graph=True) == "lean"
    assert path._frame_graph_failed
    assert (
        capsys.readouterr().out
        == "frame_graph: off for this model, its capture failed (operation not permitted when stream is capturing)\n"
    )


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_the_colour_kernel_is_the_torch_colours(monkeypatch, degree):
    """The SH colours a GPU frame graph composites (one Triton kernel, through Triton's interpreter here) against
    the torch path: SH + 0.5 clamped at 0, every degree, two cameras, zero-length directions kept finite."""
    pytest.importorskip("triton", reason="Triton is not installed: torch computes the colours")
    from garo_ns.render.sh import rendered_colors

    g = torch.Generator().manual_seed(degree)
    coeffs = torch.randn(300, 16, 3, generator=g)
    dirs = torch.randn(2, 300, 3, generator=g) * 3
    dirs[0, :5] = 0.0
    want = rendered_colors(degree, dirs, coeffs)
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    got = rendered_colors(degree, dirs, coeffs)
    assert got.shape == want.shape == (2, 300, 3) and (want == 0).any() and (want > 0.5).any()
    torch.testing.assert_close(got, want, rtol=0, atol=2e-6)
