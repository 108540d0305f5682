"""`render_precision=fp16` (garo_ns.render.half_field): the render-time field against the fp32 field, its
caches invalidated by any parameter change, never used with gradients, and the setting through the config.

On the CPU the half field runs only when asked for (`HalfField(devices=("cpu",))`); in float32 it is the
fp32 field up to the reassociation of the split layers, which tests the caching logic exactly."""

from __future__ import annotations

import pytest
import torch
import yaml

from garo_ns.deformation import DeformationField
from garo_ns.render.frame import Canonical, FramePath, FrameSettings, compose, versions
from garo_ns.render.half_field import HalfField

ON_CPU = ("cpu",)


def _field(time_net: int = 8, depth: int = 4, skip: int = 1, seed: int = 0) -> DeformationField:
    torch.manual_seed(seed)
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=depth, width=32, skip=skip, time_net=time_net)
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        torch.nn.init.normal_(head.weight, std=0.05)  # offsets of a few hundredths, as a trained field's
    return field.eval()


def _canonical(n: int = 400, seed: int = 1) -> Canonical:
    g = torch.Generator().manual_seed(seed)
    return Canonical(
        means=torch.nn.Parameter(torch.rand(n, 3, generator=g) * 2 - 1),
        quats=torch.nn.Parameter(torch.randn(n, 4, generator=g)),
        log_scales=torch.nn.Parameter(torch.randn(n, 3, generator=g) - 3),
        opacities=torch.nn.Parameter(torch.randn(n, 1, generator=g)),
        features_dc=torch.nn.Parameter(torch.rand(n, 3, generator=g)),
        features_rest=torch.nn.Parameter(torch.zeros(n, 3, 3)),
    )


def _max_diff(got, want) -> float:
    return max(float((a - b).abs().max()) for a, b in zip(got, want))


@torch.no_grad()
@pytest.mark.parametrize("time_net,depth,skip", [(8, 4, 1), (0, 4, 1), (8, 3, 2), (8, 3, 5)])
def test_cached_field_in_fp32_is_the_field(time_net: int, depth: int, skip: int) -> None:
    """Position parts cached + one time row a frame = the field, with and without a time network, with the
    skip at the last layer (nothing re-injected) and past it (no skip)."""
    field, xyz = _field(time_net, depth, skip), torch.rand(300, 3) * 2 - 1
    fast = HalfField(dtype=torch.float32, devices=ON_CPU)
    for t in (0.0, 0.37, 1.0, torch.tensor(0.6)):
        got, want = fast(field, xyz, t, "points"), field(xyz, t)
        assert all(g.dtype == torch.float32 and g.shape == w.shape for g, w in zip(got, want))
        assert _max_diff(got, want) <= 1e-6
    assert fast.builds == 1  # one cache for every time


@torch.no_grad()
def test_half_field_is_within_its_bound_of_fp32() -> None:
    field, xyz = _field(), torch.rand(2000, 3) * 2 - 1
    fast = HalfField(devices=ON_CPU)  # float16, as on a GPU
    for t in (0.1, 0.8):
        got, want = fast(field, xyz, t, "points"), field(xyz, t)
        assert all(g.dtype == torch.float32 for g in got)  # offsets come back in the positions' dtype
        scale = max(float(w.abs().max()) for w in want)
        # Half rounding of weights, cache and activations (11 bits): under 1e-3 of the offsets' size
        # (measured here about 6e-4 of the largest offset).
        assert _max_diff(got, want) <= 2e-3 * scale
        assert _max_diff(got, want) > 0  # it did run in half precision
    assert fast.cache_megabytes() == pytest.approx(2 * 2000 * 32 * 2 / 2**20)


@torch.no_grad()
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_heads_run_in_fp32_and_halve_the_offsets_error(seed: int) -> None:
    """The heads write the offsets: in fp32 (the default) the offsets' largest error against the fp32 field is
    well under that of half heads (measured here 30-55% lower), the hidden layers still in half."""
    field, xyz = _field(seed=seed), torch.rand(2000, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    fast = HalfField(devices=ON_CPU)
    weights = fast.copy_weights(field)
    assert weights.head_w.dtype == torch.float32 and weights.head_b.dtype == torch.float32
    assert all(w.dtype == torch.float16 for w, _ in weights.layers)
    want = field(xyz, 0.3)
    fp32_heads = _max_diff(fast(field, xyz, 0.3, "points"), want)
    half_heads = _max_diff(HalfField(devices=ON_CPU, head_dtype=torch.float16)(field, xyz, 0.3, "points"), want)
    assert 0 < fp32_heads < 0.8 * half_heads


@torch.no_grad()
def test_half_field_refreshes_when_the_weights_change() -> None:
    """The weight copies and the position cache follow in-place updates (an optimizer step) of any weight,
    and a replaced storage (checkpoint loading assigns `.data`), even with an unchanged points key."""
    field, xyz = _field(), torch.rand(200, 3) * 2 - 1
    fast = HalfField(dtype=torch.float32, devices=ON_CPU)
    fast(field, xyz, 0.5, "points")
    for change in (
        lambda: field.layers[0].weight.add_(0.05),  # the first layer: its cached position part
        lambda: field.layers[2].bias.add_(0.05),  # the skip layer's bias, folded into the cache
        lambda: field.layers[1].weight.mul_(1.5),  # a hidden layer: the weight copies only
        lambda: field.d_xyz.bias.add_(0.01),  # a head
        lambda: setattr(field.layers[3].weight, "data", field.layers[3].weight.data * 0.5),
    ):
        before = [o.clone() for o in field(xyz, 0.5)]
        change()
        want = field(xyz, 0.5)
        assert _max_diff(want, before) > 1e-3  # the change moves the offsets
        assert _max_diff(fast(field, xyz, 0.5, "points"), want) <= 1e-6
    assert fast.builds == 6


@torch.no_grad()
@pytest.mark.parametrize("static_skip", [False, True])
def test_frame_path_in_fp16_follows_parameter_changes(static_skip: bool) -> None:
    """Through the frame path: the cache is rebuilt when the means or the field change, whichever Gaussians
    (all, or the dynamic ones) go through the MLP."""
    field, canonical = _field(), _canonical()
    static = torch.zeros(400, dtype=torch.bool)
    static[::3] = True
    offset = torch.zeros(400, 10)
    frame = FramePath(HalfField(dtype=torch.float32, devices=ON_CPU))
    settings = FrameSettings(render_precision="fp16", static_skip=static_skip, cache_deformation=False)
    plain = FramePath()
    plain_settings = FrameSettings(render_precision="fp32", static_skip=static_skip, cache_deformation=False)

    def check() -> None:
        got = frame.splats(field, canonical, static, offset, 0.4, settings)
        want = plain.splats(field, canonical, static, offset, 0.4, plain_settings)
        assert _max_diff(got[:5], want[:5]) <= 1e-6

    check()
    assert frame.half_field.builds == 1
    moved = [o.clone() for o in field(canonical.means, 0.4)]
    canonical.means.mul_(0.5)  # new means: another position part
    assert _max_diff(field(canonical.means, 0.4), moved) > 1e-3
    check()
    assert frame.half_field.builds == 2
    field.layers[0].weight.add_(0.05)
    check()
    assert frame.half_field.builds == 3
    frame.splats(field, canonical, static, offset, 0.9, settings)
    assert frame.half_field.builds == 3  # another time alone: the same cache


@torch.no_grad()
def test_fp16_is_the_plain_field_on_a_cpu_by_default() -> None:
    field, canonical = _field(), _canonical()
    frame = FramePath()  # the half field runs on CUDA only unless asked
    fp16 = frame.splats(field, canonical, None, None, 0.3, FrameSettings(render_precision="fp16"))
    fp32 = FramePath().splats(field, canonical, None, None, 0.3, FrameSettings())
    assert all(torch.equal(a, b) for a, b in zip(fp16[:5], fp32[:5]))
    assert frame.half_field.builds == 0


def test_gradients_never_go_through_the_half_field() -> None:
    field, canonical = _field(), _canonical()
    frame = FramePath(HalfField(devices=ON_CPU))
    settings = FrameSettings(render_precision="fp16", cache_deformation=False)
    key = versions(list(canonical) + list(field.parameters()))
    with torch.enable_grad():
        deformed = frame.deform(field, canonical, None, None, 0.3, settings, key)
    assert frame.half_field.builds == 0
    assert all(torch.equal(a, b) for a, b in zip(deformed, compose(field, canonical, 0.3)))
    deformed[0].sum().backward()
    assert field.layers[0].weight.grad is not None and field.layers[0].weight.grad.abs().sum() > 0
    with pytest.raises(RuntimeError, match="without gradients"):
        HalfField(devices=ON_CPU)(field, canonical.means.detach(), 0.3, "points")


def _model(**config):
    from nerfstudio.data.scene_box import SceneBox

    from garo_ns.garo_model import GaroModelConfig

    box = SceneBox(torch.tensor([[-1.5] * 3, [1.5] * 3]))
    cfg = GaroModelConfig(num_random=300, deform_width=32, deform_depth=3, deform_skip=1, **config)
    model = cfg.setup(scene_box=box, num_train_data=1, metadata={"camera_extent": 4.0})
    model.step = model.config.deform_warmup  # the field is on
    model.frame.half_field = HalfField(devices=ON_CPU)
    return model


def test_a_training_model_uses_the_fp32_field() -> None:
    model = _model(render_precision="fp16")
    model.train()
    splats = model.gaussians_at(0.3)
    assert model.frame.half_field.builds == 0
    exact = compose(model.deformation, model.canonical(), 0.3)
    assert torch.equal(splats.means, exact[0])
    splats.means.sum().backward()
    assert model.deformation.layers[0].weight.grad is not None  # the field gets its gradients
    model.eval()
    with torch.no_grad():
        fast = model.gaussians_at(0.3)
        assert model.frame.half_field.builds == 1  # rendering, not training: the half field
        assert 0 < float((fast.means - exact[0]).abs().max()) <= 1e-3
        assert torch.equal(model.gaussians_at(0.3, exact=True).means, exact[0])  # `exact` stays the fp32 field


def test_render_precision_round_trips_through_the_config() -> None:
    import tyro

    from garo_ns.garo_model import GaroModelConfig

    config = tyro.cli(GaroModelConfig, args=["--render-precision", "fp16"])
    assert config.render_precision == "fp16"
    again = yaml.load(yaml.dump(config), Loader=yaml.Loader)  # as nerfstudio's config.yml
    assert again.render_precision == "fp16"
    with pytest.raises(SystemExit):
        tyro.cli(GaroModelConfig, args=["--render-precision", "fp8"])
    model = _model(render_precision="fp16")
    model.eval()
    with torch.no_grad():
        model.gaussians_at(0.5)
    assert model.frame.half_field.builds == 1  # the model's setting reaches the frame path
    model.config.render_precision = "fp32"
    with torch.no_grad():
        model.gaussians_at(0.5)
    assert model.frame.half_field.cache_megabytes() == 0  # switched off: its cache is dropped


@torch.no_grad()
def test_half_products_accumulate_in_fp32(monkeypatch: pytest.MonkeyPatch) -> None:
    """cuBLAS may reduce half products' partial sums in half: the half field turns that off while it runs
    (what the micro-benchmark measured), and puts the switch back."""
    from garo_ns.render import half_field

    seen = []
    forward = half_field.cached_forward

    def recording(*args):
        seen.append(torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction)
        return forward(*args)

    monkeypatch.setattr(half_field, "cached_forward", recording)
    matmul = torch.backends.cuda.matmul  # a module-like object monkeypatch cannot restore
    previous = matmul.allow_fp16_reduced_precision_reduction
    matmul.allow_fp16_reduced_precision_reduction = True
    try:
        HalfField(devices=ON_CPU)(_field(), torch.rand(10, 3), 0.2, "points")
        assert seen == [False]
        assert matmul.allow_fp16_reduced_precision_reduction is True
    finally:
        matmul.allow_fp16_reduced_precision_reduction = previous


requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="the half field runs on CUDA (a GPU test)")


@requires_cuda
@torch.no_grad()
def test_half_field_on_cuda_is_within_its_bound_and_replays_as_eager() -> None:
    from garo_ns.render.graphs import TimeGraph

    field = DeformationField(time_net=30).cuda().eval()  # the recipe's shape
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        torch.nn.init.normal_(head.weight, std=0.05)
    xyz = torch.rand(20_000, 3, device="cuda") * 2 - 1
    fast, graph = HalfField(), TimeGraph()
    for t in (0.0, 0.37, 1.0, 0.37):
        want = field(xyz, t)
        eager = fast(field, xyz, torch.tensor(t, device="cuda"), "points")
        scale = max(float(w.abs().max()) for w in want)
        assert 0 < _max_diff(eager, want) <= 2e-3 * scale
        replay = [x.clone() for x in graph("k", lambda tt: fast(field, xyz, tt, "points"), t, xyz.device)]
        for a, b in zip(replay, eager):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert graph.captures == 1 and fast.builds == 1


@requires_cuda
@torch.no_grad()
@pytest.mark.parametrize("static_skip", [False, True])
def test_frame_path_graph_in_fp16_equals_its_eager_frames(static_skip: bool) -> None:
    """The half-precision field through the frame path: a CUDA graph replays its eager frames exactly."""
    field = _field().cuda()
    canonical = Canonical(*(x.detach().cuda() for x in _canonical()))
    static = torch.zeros(400, dtype=torch.bool, device="cuda")
    static[::3] = True
    offset = torch.zeros(400, 10, device="cuda")
    graphed, eager = FramePath(), FramePath()
    settings = dict(render_precision="fp16", static_skip=static_skip, cache_deformation=False)
    for t in (0.2, 0.7):
        got = graphed.splats(field, canonical, static, offset, t, FrameSettings(cuda_graph=True, **settings))
        want = eager.splats(field, canonical, static, offset, t, FrameSettings(**settings))
        assert got.graph is not None and want.graph is None
        for a, b in zip(got[:5], want[:5]):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    canonical.means.mul_(0.5)  # new means: a new capture and a new position cache
    got = graphed.splats(field, canonical, static, offset, 0.7, FrameSettings(cuda_graph=True, **settings))
    want = FramePath().splats(field, canonical, static, offset, 0.7, FrameSettings(**settings))
    for a, b in zip(got[:5], want[:5]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert graphed.half_field.builds == 2


class ReplayChecker:
    """Stands in for TimeGraph on a CPU: a new key 'captures' (runs the step once and keeps what it read of
    the half field), the same key 'replays', which must find those very weight copies and that cache still
    held, as a real replay reads their addresses whether or not they were freed."""

    def __init__(self, half: HalfField) -> None:
        self.half, self.key, self.captures, self.outputs, self.read = half, None, 0, None, None

    def held(self):
        weights, cache = self.half._weights, self.half._cache
        return (weights[1] if weights else None, cache[1] if cache else None)

    def __call__(self, key, fn, time, device, reuse=False):
        if self.key != key:
            self.key, self.captures = key, self.captures + 1
            self.outputs = fn(torch.tensor(float(time)))
            self.read = self.held()
        else:
            now = self.held()
            assert now[0] is self.read[0] and now[1] is self.read[1], "replay on released half-field memory"
        return self.outputs


@torch.no_grad()
@pytest.mark.parametrize("eager", ["fp32", "other static setting"])
def test_a_graph_never_replays_on_half_field_memory_an_eager_frame_released(monkeypatch, eager: str) -> None:
    """A graph captured in fp16 reads the half field's copies; an eager frame in fp32 releases them, one with
    the other static setting rebuilds the cache: the next graph frame must capture again, and only then."""
    import garo_ns.render.frame as frame_module

    monkeypatch.setattr(frame_module, "graphs_available", lambda device: True)
    field, canonical = _field(), _canonical()
    static = torch.zeros(400, dtype=torch.bool)
    static[::3] = True
    offset = torch.zeros(400, 10)
    frame = FramePath(HalfField(dtype=torch.float32, devices=ON_CPU))
    graph = frame._graph = ReplayChecker(frame.half_field)
    graphed = FrameSettings(render_precision="fp16", static_skip=True, cuda_graph=True)
    frame.splats(field, canonical, static, offset, 0.4, graphed)
    frame.splats(field, canonical, static, offset, 0.6, graphed)
    assert graph.captures == 1  # a replay: nothing changed
    if eager == "fp32":
        other = FrameSettings(render_precision="fp32", static_skip=True)
    else:
        other = FrameSettings(render_precision="fp16", static_skip=False)
    frame.splats(field, canonical, static, offset, 0.5, other)
    frame.splats(field, canonical, static, offset, 0.4, graphed)
    assert graph.captures == 2
    frame.splats(field, canonical, static, offset, 0.7, graphed)
    assert graph.captures == 2
