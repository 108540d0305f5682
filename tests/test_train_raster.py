"""The lean training rasterization (`garo_ns.render.train_raster`) against gsplat's `rasterization`:
values, gradients and the 2D-mean gradient the densification reads.

On CUDA both call gsplat's kernels. On CPU (where CI runs) both call stand-ins for those kernels
built on the reference rasterizer, with the C++ bindings' positional signatures and input checks,
so the glue around the kernels (argument order, the SH clamp's mask, the depth channel and its
division, backgrounds, the view directions' share of the means' gradient) is checked everywhere.
"""

from __future__ import annotations

import math
import sys
import types

import pytest
import torch

from garo_ns.render import reference
from garo_ns.render.backend import gsplat_cuda_available, rasterize
from garo_ns.render.sh import eval_sh
from garo_ns.render.train_raster import rasterize_train_lean

WIDTH, HEIGHT = 64, 48
COLOURS = ["sh3", "sh0", "rgb"]  # SH degree 3 or 0 of 16 coefficients, or plain RGB
MODES = ["RGB", "RGB+ED"]

cuda_only = pytest.mark.skipif(
    not gsplat_cuda_available(),
    reason="needs a CUDA device and gsplat's CUDA extension: the lean training path calls its kernels",
)


def _camera(device: str):
    """A rotated camera 4 units from the origin (so the closed-form centre is exercised), pinhole K."""
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.8, 0.5]), dim=0)
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = 0.4
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 4.0])
    f = 0.5 * WIDTH / math.tan(0.35)
    K = torch.tensor([[f, 0.0, WIDTH / 2 + 0.7], [0.0, f * 1.02, HEIGHT / 2 - 0.4], [0.0, 0.0, 1.0]])
    return viewmat[None].to(device), K[None].to(device)


def _scene(n: int, colour: str, with_bg: bool, device: str, seed: int = 0):
    """Leaf parameters of a cloud in front of the camera, well conditioned (no Gaussian at the near plane)."""
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": (torch.rand(n, 3, generator=g) * 2 - 1) * 0.9,
        "quats": torch.randn(n, 4, generator=g),  # unnormalised, as the model passes them
        "scales": torch.exp(torch.randn(n, 3, generator=g) * 0.3 - 2.7),
        "opacities": torch.rand(n, generator=g) * 0.9 + 0.05,
        "colors": torch.randn(n, 3, generator=g).sigmoid()
        if colour == "rgb"
        else torch.randn(n, 16, 3, generator=g) * 0.3,
    }
    if colour != "rgb":  # a wide DC band: some colours fall below zero, where the clamp cuts the gradient
        params["colors"][:, 0] *= 5.0
    if with_bg:
        params["backgrounds"] = torch.tensor([[0.2, 0.5, 0.9]])
    return {k: v.to(device) for k, v in params.items()}


def _sh_degree(colour: str):
    return {"sh3": 3, "sh0": 0, "rgb": None}[colour]


def _gsplat(p, viewmat, K, sh_degree, mode):
    from gsplat import rasterization

    return rasterization(
        means=p["means"],
        quats=p["quats"],
        scales=p["scales"],
        opacities=p["opacities"],
        colors=p["colors"],
        viewmats=viewmat,
        Ks=K,
        width=WIDTH,
        height=HEIGHT,
        sh_degree=sh_degree,
        backgrounds=p.get("backgrounds"),
        render_mode=mode,
        packed=False,
        absgrad=False,
        rasterize_mode="classic",
    )


def _lean(p, viewmat, K, sh_degree, mode):
    return rasterize_train_lean(
        p["means"],
        p["quats"],
        p["scales"],
        p["opacities"],
        p["colors"],
        viewmat,
        K,
        WIDTH,
        HEIGHT,
        sh_degree,
        p.get("backgrounds"),
        with_depth=mode == "RGB+ED",
    )


def _step(fn, params, viewmat, K, sh_degree, mode, weights):
    """One forward and backward as a training step does it: DefaultStrategy's retain_grad on
    means2d, a loss on the render and the alpha."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
    render, alpha, info = fn(leaves, viewmat, K, sh_degree, mode)
    info["means2d"].retain_grad()
    w_render, w_alpha = weights
    ((render * w_render[..., : render.shape[-1]]).sum() + (alpha * w_alpha).sum()).backward()
    grads = {k: v.grad for k, v in leaves.items()}
    grads["means2d"] = info["means2d"].grad
    return render.detach(), alpha.detach(), info, grads


def _compare(params, viewmat, K, colour, mode, grad_rtol, grad_atol):
    sh_degree = _sh_degree(colour)
    g = torch.Generator().manual_seed(1)
    weights = (torch.randn(1, HEIGHT, WIDTH, 4, generator=g), torch.randn(1, HEIGHT, WIDTH, 1, generator=g))
    weights = tuple(w.to(viewmat.device) for w in weights)
    ref, ref_alpha, ref_info, ref_grads = _step(_gsplat, params, viewmat, K, sh_degree, mode, weights)
    got, alpha, info, grads = _step(_lean, params, viewmat, K, sh_degree, mode, weights)

    assert float(ref_alpha.mean()) > 0.05  # the cloud is in view
    assert got.shape == ref.shape and alpha.shape == ref_alpha.shape
    assert torch.equal(info["radii"], ref_info["radii"])
    for key in ("width", "height", "n_cameras", "tile_size", "tile_width", "tile_height"):
        assert info[key] == ref_info[key], key
    assert info["gaussian_ids"] is None and info["camera_ids"] is None
    # The projection kernel leaves a culled Gaussian's entries unwritten (uninitialised memory, on both sides).
    seen = ref_info["radii"] > 0
    assert 0 < int(seen.sum()) < seen.numel()  # some culled, most seen
    torch.testing.assert_close(info["means2d"].detach()[seen], ref_info["means2d"].detach()[seen], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(info["depths"].detach()[seen], ref_info["depths"].detach()[seen], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(alpha, ref_alpha, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)
    assert set(grads) == set(ref_grads)
    for key, ref_grad in ref_grads.items():
        scale = float(ref_grad.abs().max())
        assert scale > 0, f"{key}: no gradient reached it"
        assert grads[key] is not None and grads[key].shape == ref_grad.shape, key
        torch.testing.assert_close(grads[key], ref_grad, rtol=grad_rtol, atol=grad_atol * scale, msg=key)


# --- On CUDA: gsplat's kernels on both sides -------------------------------------------------------


@cuda_only
@pytest.mark.parametrize("with_bg", [False, True])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("colour", COLOURS)
def test_lean_training_path_matches_gsplat_on_cuda(colour, mode, with_bg):
    # Same kernels, so the values agree to the last bits (the view directions' camera centre is
    # computed in closed form here, by a 4x4 inverse in gsplat). The compositing backward sums with
    # atomics in no fixed order, on both sides: gradients agree to 1e-4 relative, or 1e-5 of the
    # largest entry.
    params = _scene(3000, colour, with_bg, "cuda")
    viewmat, K = _camera("cuda")
    _compare(params, viewmat, K, colour, mode, grad_rtol=1e-4, grad_atol=1e-5)


@cuda_only
def test_rasterize_takes_the_training_path_under_autograd():
    params = _scene(2000, "sh3", True, "cuda")
    viewmat, K = _camera("cuda")
    args = [params[k] for k in ("means", "quats", "scales", "opacities", "colors")] + [viewmat, K, WIDTH, HEIGHT]
    kwargs = dict(sh_degree=3, backgrounds=params["backgrounds"], lean=True)
    params["means"].requires_grad_(True)
    render, _, info = rasterize(*args, **kwargs)
    assert type(render.grad_fn).__name__ == "_CompositeBackward"
    render.sum().backward()
    assert params["means"].grad is not None and "means2d" in info
    with torch.no_grad():  # the inference path stays as it was
        still, _, _ = rasterize(*args, **kwargs)
    assert still.grad_fn is None
    # Two cameras take gsplat's own path.
    kwargs["backgrounds"] = params["backgrounds"].repeat(2, 1)
    two, _, _ = rasterize(*args[:5], viewmat.repeat(2, 1, 1), K.repeat(2, 1, 1), WIDTH, HEIGHT, **kwargs)
    assert two.shape[0] == 2 and type(two.grad_fn).__name__ != "_CompositeBackward"


# --- On CPU: stand-ins for the kernels ---------------------------------------------------------------


def _contiguous(*tensors):
    """GSPLAT_CHECK_INPUT's contiguity check, which the real kernels enforce."""
    for t in tensors:
        assert t is None or t.is_contiguous(), "a kernel input is not contiguous"


class StandInKernels:
    """gsplat's `_C` functions that both paths call, in pure torch (the reference rasterizer's
    projection, SH and compositing), with the positional signatures of gsplat 1.4.0's
    csrc/bindings.h: a misplaced or missing argument fails here as it would there. Backward
    functions recompute their forward and differentiate it, zero for culled Gaussians as the
    kernels are."""

    class CameraModelType:
        PINHOLE = "pinhole"

    PINHOLE = "pinhole"  # gsplat's _make_lazy_cuda_obj looks the last name up on the module itself

    @staticmethod
    def _project(means, quats, scales, viewmats, Ks, width, height, eps2d):
        return reference.project(means, reference.covariance(quats, scales), viewmats, Ks, width, height, eps2d)

    def fully_fused_projection_fwd(
        self,
        means,
        covars,
        quats,
        scales,
        viewmats,
        Ks,
        image_width,
        image_height,
        eps2d,
        near_plane,
        far_plane,
        radius_clip,
        calc_compensations,
        camera_model,
    ):
        _contiguous(means, quats, scales, viewmats, Ks)
        assert covars is None and camera_model == "pinhole" and calc_compensations is False
        assert isinstance(image_width, int) and isinstance(image_height, int) and radius_clip == 0.0
        with torch.no_grad():
            radii, means2d, depths, conics = reference.project(
                means,
                reference.covariance(quats, scales),
                viewmats,
                Ks,
                image_width,
                image_height,
                eps2d,
                near_plane,
                far_plane,
            )
        return radii, means2d, depths, conics, None

    def fully_fused_projection_bwd(
        self,
        means,
        covars,
        quats,
        scales,
        viewmats,
        Ks,
        image_width,
        image_height,
        eps2d,
        camera_model,
        radii,
        conics,
        compensations,
        v_means2d,
        v_depths,
        v_conics,
        v_compensations,
        viewmats_requires_grad,
    ):
        _contiguous(means, quats, scales, viewmats, Ks, radii, conics, v_means2d, v_depths, v_conics)
        assert covars is None and compensations is None and v_compensations is None and camera_model == "pinhole"
        assert radii.dtype == torch.int32 and v_depths.shape == radii.shape
        seen = (radii > 0).to(v_means2d.dtype)
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(True) for t in (means, quats, scales)]
            _, means2d, depths, conics = self._project(*leaves, viewmats, Ks, image_width, image_height, eps2d)
            v_means, v_quats, v_scales = torch.autograd.grad(
                (means2d, depths, conics),
                leaves,
                (v_means2d * seen[..., None], v_depths * seen, v_conics * seen[..., None]),
            )
        return v_means, None, v_quats, v_scales, torch.zeros_like(viewmats) if viewmats_requires_grad else None

    def compute_sh_fwd(self, degrees_to_use, dirs, coeffs, masks):
        _contiguous(dirs, coeffs, masks)
        assert masks.dtype == torch.bool and dirs.shape[:-1] == coeffs.shape[:-2] == masks.shape
        # The kernel leaves culled Gaussians' colours unwritten: NaN shows if one leaks anywhere.
        return torch.where(masks[..., None], eval_sh(degrees_to_use, dirs, coeffs), float("nan"))

    def compute_sh_bwd(self, K, degrees_to_use, dirs, coeffs, masks, v_colors, compute_v_dirs):
        _contiguous(dirs, coeffs, masks, v_colors)
        assert K == coeffs.shape[-2] and isinstance(compute_v_dirs, bool)
        with torch.enable_grad():
            d, c = dirs.detach().requires_grad_(compute_v_dirs), coeffs.detach().requires_grad_(True)
            colors = eval_sh(degrees_to_use, d, c)
            leaves = [c, d] if compute_v_dirs else [c]
            grads = torch.autograd.grad(colors, leaves, v_colors * masks[..., None], allow_unused=True)
        v_dirs = None if not compute_v_dirs else torch.zeros_like(dirs) if grads[1] is None else grads[1]
        return grads[0], v_dirs  # degree 0 does not depend on the directions

    def isect_tiles(
        self,
        means2d,
        radii,
        depths,
        camera_ids,
        gaussian_ids,
        C,
        tile_size,
        tile_width,
        tile_height,
        sort,
        double_buffer,
    ):
        _contiguous(means2d, radii, depths)
        assert camera_ids is None and gaussian_ids is None and sort is True and double_buffer is True
        assert C == radii.shape[0] and isinstance(tile_size, int)
        tiles_per_gauss, tile_ids, flat_ids = reference.intersect_tiles(
            means2d.detach(), radii, depths.detach(), tile_size, tile_width, tile_height
        )
        return tiles_per_gauss, tile_ids, flat_ids.int()  # tile ids stand in for the sort keys

    def isect_offset_encode(self, isect_ids, n_cameras, tile_width, tile_height):
        _contiguous(isect_ids)
        tiles = torch.arange(n_cameras * tile_width * tile_height, device=isect_ids.device)
        return torch.searchsorted(isect_ids, tiles).int().reshape(n_cameras, tile_height, tile_width)

    @staticmethod
    def _composite(means2d, conics, colors, opacities, backgrounds, width, height, tile_size, offsets, flatten_ids):
        counts = torch.diff(offsets.flatten().long(), append=torch.tensor([flatten_ids.numel()]))
        tile_ids = torch.repeat_interleave(torch.arange(offsets.numel()), counts)
        render, alpha = reference.composite(
            means2d, conics, opacities, colors, tile_ids, flatten_ids.long(), width, height, tile_size
        )
        if backgrounds is not None:
            render = render + backgrounds[:, None, None, :] * (1.0 - alpha)
        return render, alpha

    def rasterize_to_pixels_fwd(
        self,
        means2d,
        conics,
        colors,
        opacities,
        backgrounds,
        masks,
        image_width,
        image_height,
        tile_size,
        tile_offsets,
        flatten_ids,
    ):
        _contiguous(means2d, conics, colors, opacities, backgrounds, tile_offsets, flatten_ids)
        assert masks is None and opacities.shape == means2d.shape[:2] and colors.shape[:2] == means2d.shape[:2]
        assert backgrounds is None or backgrounds.shape == (colors.shape[0], colors.shape[-1])
        with torch.no_grad():
            render, alpha = self._composite(
                means2d,
                conics,
                colors,
                opacities,
                backgrounds,
                image_width,
                image_height,
                tile_size,
                tile_offsets,
                flatten_ids,
            )
        last_ids = torch.zeros(alpha.shape[:-1], dtype=torch.int32)
        return render, alpha, last_ids

    def rasterize_to_pixels_bwd(
        self,
        means2d,
        conics,
        colors,
        opacities,
        backgrounds,
        masks,
        image_width,
        image_height,
        tile_size,
        tile_offsets,
        flatten_ids,
        render_alphas,
        last_ids,
        v_render_colors,
        v_render_alphas,
        absgrad,
    ):
        _contiguous(means2d, conics, colors, opacities, backgrounds, tile_offsets, flatten_ids)
        _contiguous(render_alphas, last_ids, v_render_colors, v_render_alphas)
        assert masks is None and absgrad is False and last_ids.dtype == torch.int32
        assert v_render_colors.shape[-1] == colors.shape[-1] and v_render_alphas.shape == render_alphas.shape
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(True) for t in (means2d, conics, colors, opacities)]
            render, alpha = self._composite(
                *leaves, backgrounds, image_width, image_height, tile_size, tile_offsets, flatten_ids
            )
            grads = torch.autograd.grad((render, alpha), leaves, (v_render_colors, v_render_alphas), allow_unused=True)
        return (None, *(torch.zeros_like(t) if g is None else g for t, g in zip(leaves, grads)))


@pytest.fixture
def stand_in_kernels(monkeypatch):
    # A module of its own in place of gsplat.cuda._backend: importing the real one off CUDA would try
    # to compile the extension. Both gsplat's wrapper and ours import `_C` from it at each call.
    module = types.ModuleType("gsplat.cuda._backend")
    module._C = StandInKernels()
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", module)


@pytest.mark.parametrize("with_bg", [False, True])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("colour", COLOURS)
def test_lean_training_path_matches_gsplat_with_stand_in_kernels(stand_in_kernels, colour, mode, with_bg):
    # Deterministic stand-ins: what differs is the glue, and the camera centre's last bits.
    params = _scene(150, colour, with_bg, "cpu")
    viewmat, K = _camera("cpu")
    _compare(params, viewmat, K, colour, mode, grad_rtol=1e-5, grad_atol=1e-6)


def test_lean_training_path_refuses_what_it_does_not_cover():
    params = _scene(10, "rgb", False, "cpu")
    viewmat, K = _camera("cpu")
    with pytest.raises(ValueError, match="one camera"):
        _lean(params, viewmat.repeat(2, 1, 1), K.repeat(2, 1, 1), None, "RGB")
    params["colors"] = torch.rand(10, 2)
    with pytest.raises(ValueError, match="RGB colours"):
        _lean(params, viewmat, K, None, "RGB")


@pytest.mark.parametrize("mode", MODES)
def test_lean_is_ignored_by_the_reference_under_autograd(mode):
    # Off CUDA `lean` changes nothing: the reference's values and gradients, bit for bit.
    params = _scene(200, "sh3", True, "cpu")
    viewmat, K = _camera("cpu")
    results = []
    for lean in (False, True):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}
        args = [leaves[k] for k in ("means", "quats", "scales", "opacities", "colors")]
        render, alpha, info = rasterize(
            *args,
            viewmat,
            K,
            WIDTH,
            HEIGHT,
            sh_degree=3,
            backgrounds=leaves["backgrounds"],
            render_mode=mode,
            lean=lean,
        )
        assert type(render.grad_fn).__name__ != "_CompositeBackward"
        info["means2d"].retain_grad()
        (render.sum() + alpha.sum()).backward()
        results.append((render, alpha, info["means2d"].grad, *(v.grad for v in leaves.values())))
    assert float(results[0][1].detach().mean()) > 0.05
    for plain, lean in zip(*results):
        assert torch.equal(plain, lean)
