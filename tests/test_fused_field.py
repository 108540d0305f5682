"""`render_precision=fp16-fused` (garo_ns.render.fused_field): the fused Triton kernel against the fp32 field
and against a plain restatement of its own arithmetic, its ragged last block, every place the skip layer
can take in the pairing of layers, the wrapper's caches, and the frame path's choice of field.

On a CPU the kernel runs in Triton's interpreter (TRITON_INTERPRET=1, set per test: the module builds a
separate interpreted copy of the kernel, so compiled kernels in the same process are unaffected). The GPU
tests at the end (skipped without CUDA) compile it: within its bound of fp32 at the recipe's shape, and a
CUDA-graph replay equal to eager launches (the frame path's graph against its eager frames is
tests/test_half_field.py's, for both half-precision fields).
"""

from __future__ import annotations

from typing import List, Tuple

import pytest
import torch
from torch import Tensor

from garo_ns.deformation import DeformationField
from garo_ns.render import fused_field as ff
from garo_ns.render.frame import Canonical, FramePath, FrameSettings
from garo_ns.render.fused_field import FusedConfig, FusedField, FusedWeights, is_pair_first, launch
from garo_ns.render.half_field import HalfField, PositionCache, time_features

pytest.importorskip("triton", reason="the fused field is a Triton kernel")

ON_CPU = ("cpu",)
# Largest offset difference from the fp32 field, relative to the largest offset: half rounding of weights,
# caches and activations (11 bits), as HalfField's bound (measured here: at most 7e-4).
FP32_BOUND = 2e-3
# From the same arithmetic restated in torch (fp32 sums of half products, activations rounded to half): only
# the order of the fp32 sums differs, which now and then rounds an activation to the neighbouring half
# (measured: at most 1.6e-4 at width 256).
SAME_ARITHMETIC_BOUND = 5e-4


@pytest.fixture
def interpret(monkeypatch: pytest.MonkeyPatch) -> None:
    """Triton's interpreter for this test (the kernel then runs on CPU tensors)."""
    monkeypatch.setenv("TRITON_INTERPRET", "1")


def _field(depth: int = 4, skip: int = 1, time_net: int = 8, width: int = 32, seed: int = 0) -> DeformationField:
    torch.manual_seed(seed)
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=depth, width=width, skip=skip, time_net=time_net)
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        torch.nn.init.normal_(head.weight, std=0.05)  # offsets of a few hundredths, as a trained field's
    return field.eval()


def _recipe_shaped() -> DeformationField:
    """The recipe's layer sizes (8 x 256, skip after layer 4, 30 time features), random weights."""
    field = DeformationField(pos_freqs=10, time_freqs=6, depth=8, width=256, skip=4, time_net=30)
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        torch.nn.init.normal_(head.weight, std=0.05)
    return field.eval()


def _xyz(n: int, seed: int = 1, device: str = "cpu") -> Tensor:
    return (torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1).to(device)


def _max_diff(got, want) -> float:
    return max(float((a.float() - b.float()).abs().max()) for a, b in zip(got, want))


def _scale(offsets) -> float:
    return max(float(o.abs().max()) for o in offsets)


def emulate(w: FusedWeights, cache: PositionCache, tvec: Tensor) -> Tensor:
    """The kernel's arithmetic layer by layer in torch: fp32 sums of half values, activations rounded to half."""
    h = torch.relu(cache.first.float() + tvec[0]).half()
    for i in range(1, w.depth):
        m = w.weights[i - 1].float()
        m = m if is_pair_first(i, w.depth) else m.t()  # back to [out, in]
        base = cache.skip.float() + tvec[1] if i == w.skip_layer else w.biases[i]  # type: ignore[union-attr]
        h = torch.relu(h.float() @ m.t() + base).half()
    return h.float() @ w.head_w.float()[:, : w.heads] + w.head_b[: w.heads]


def _run(field: DeformationField, xyz: Tensor, t: float, config: FusedConfig) -> Tuple[Tensor, Tensor]:
    """(kernel output, restated arithmetic), both [N, 10]."""
    w = FusedWeights.of(field)
    cache = PositionCache.build(field, xyz, torch.float16)
    tvec = w.time_rows(time_features(field, t, xyz.device))
    return launch(w, cache, tvec, config), emulate(w, cache, tvec)


# (depth, skip, time_net, width): where the skip layer falls in the pairing of layers. Layers 1 .. depth-1
# and the heads pair up; with an odd depth layer 0 is the first pair's first layer, made from the cache.
STRUCTURES = {
    "skip-first-of-pair": (4, 2, 8, 32),  # pairs (1, 2), (3, heads): the skip layer 3 is produced chunk-wise
    "skip-second-of-pair": (4, 1, 8, 32),  # the skip layer 2 accumulates: its cached part added at the end
    "odd-depth": (3, 1, 8, 32),  # pairs (0, 1), (2, heads): layer 0 chunk-wise from the cache
    "odd-depth-skip-second": (3, 0, 0, 64),  # no time network; the skip layer 1 second of the pair (0, 1)
    "no-skip": (3, 5, 0, 64),  # a skip past the last layer re-injects nothing
    "heads-only": (1, 4, 0, 32),  # pair (0, heads)
}


@torch.no_grad()
@pytest.mark.parametrize("name", list(STRUCTURES))
def test_kernel_matches_the_field_in_every_structure(interpret: None, name: str) -> None:
    depth, skip, time_net, width = STRUCTURES[name]
    field, xyz = _field(depth, skip, time_net, width), _xyz(150)
    for t in (0.0, 0.37, 1.0):
        got, same = _run(field, xyz, t, FusedConfig(block_m=64, block_n=16))
        want = torch.cat(field(xyz, t), dim=-1)
        scale = float(want.abs().max())
        assert scale > 1e-2  # the field moves the Gaussians
        assert float((got - same).abs().max()) <= SAME_ARITHMETIC_BOUND * scale
        assert float((got - want).abs().max()) <= FP32_BOUND * scale
    skip_layer = skip + 1 if skip + 1 < depth else -1
    assert FusedWeights.of(field).skip_layer == skip_layer
    if name.startswith("skip-first"):
        assert is_pair_first(skip_layer, depth)
    if name.startswith("skip-second") or name == "odd-depth-skip-second":
        assert not is_pair_first(skip_layer, depth)


@torch.no_grad()
def test_kernel_at_the_recipes_layer_sizes(interpret: None) -> None:
    """8 x 256 with the skip after layer 4 (the skip layer 5 first of the pair (5, 6)) and 30 time features,
    streamed in 64-row weight slices as on a GPU."""
    field, xyz = _recipe_shaped(), _xyz(200)
    got, same = _run(field, xyz, 0.37, ff.DEFAULT_CONFIG)
    want = torch.cat(field(xyz, 0.37), dim=-1)
    scale = float(want.abs().max())
    assert float((got - same).abs().max()) <= SAME_ARITHMETIC_BOUND * scale
    assert 0 < float((got - want).abs().max()) <= FP32_BOUND * scale  # it did run in half precision
    assert is_pair_first(5, 8) and FusedWeights.of(field).skip_layer == 5


@torch.no_grad()
@pytest.mark.parametrize("n", [1, 5, 63, 65, 130])
def test_ragged_last_block_is_masked(interpret: None, n: int) -> None:
    """N not a multiple of the block: the last block's rows beyond N read nothing and write nothing (the
    output is a view into a larger buffer whose tail must stay untouched), and its rows within N are right."""
    field, xyz = _field(), _xyz(n, seed=n)
    w = FusedWeights.of(field)
    cache = PositionCache.build(field, xyz, torch.float16)
    tvec = w.time_rows(time_features(field, 0.6, xyz.device))
    buffer = torch.full((n + 64, w.heads), float("nan"))
    out = launch(w, cache, tvec, FusedConfig(block_m=64, block_n=32), out=buffer[:n])
    assert out.data_ptr() == buffer.data_ptr()
    assert torch.isnan(buffer[n:]).all()
    want = torch.cat(field(xyz, 0.6), dim=-1)
    assert float((out - want).abs().max()) <= FP32_BOUND * float(want.abs().max())
    assert float((out - emulate(w, cache, tvec)).abs().max()) <= SAME_ARITHMETIC_BOUND * float(want.abs().max())


@torch.no_grad()
def test_no_gaussians_launch_nothing(interpret: None) -> None:
    field = _field()
    w = FusedWeights.of(field)
    cache = PositionCache.build(field, torch.zeros(0, 3), torch.float16)
    out = launch(w, cache, w.time_rows(time_features(field, 0.5, torch.device("cpu"))), ff.DEFAULT_CONFIG)
    assert out.shape == (0, 10)


@torch.no_grad()
def test_the_skip_layer_reads_its_cached_part_and_its_time_row(interpret: None) -> None:
    """The re-injected input reaches the kernel only through the skip cache and the second time row: changing
    either moves the output exactly as the restated arithmetic says, for both places of the skip layer."""
    for depth, skip in ((4, 2), (4, 1)):
        field, xyz = _field(depth, skip), _xyz(100)
        w = FusedWeights.of(field)
        cache = PositionCache.build(field, xyz, torch.float16)
        tvec = w.time_rows(time_features(field, 0.3, xyz.device))
        base = launch(w, cache, tvec, FusedConfig(block_m=32, block_n=16))
        for changed_cache, changed_tvec in (
            (PositionCache(cache.first, cache.skip * 0.5), tvec),  # type: ignore[operator]
            (cache, torch.stack([tvec[0], tvec[1] + 0.2])),
        ):
            got = launch(w, changed_cache, changed_tvec, FusedConfig(block_m=32, block_n=16))
            want = emulate(w, changed_cache, changed_tvec)
            assert float((got - base).abs().max()) > 1e-3
            assert float((got - want).abs().max()) <= SAME_ARITHMETIC_BOUND * float(want.abs().max())


@torch.no_grad()
def test_weights_are_stored_in_the_layout_of_their_role() -> None:
    field = _field(depth=4, skip=1)
    w = FusedWeights.of(field)
    # pairs (1, 2), (3, heads): layer 1 [out, in], the skip layer 2's hidden columns [in, out], layer 3 [out, in]
    assert torch.equal(w.weights[0], field.layers[1].weight.half())
    t = field.layers[0].in_features
    assert torch.equal(w.weights[1], field.layers[2].weight[:, t:].t().half())
    assert torch.equal(w.weights[2], field.layers[3].weight.half())
    assert w.biases[2].abs().max() == 0 and torch.equal(w.biases[3], field.layers[3].bias)  # skip bias is cached
    assert w.head_w.shape == (32, 16) and w.head_w[:, 10:].abs().max() == 0
    p = ff.position_dims(field)
    assert torch.equal(w.time_w[1], field.layers[2].weight[:, p:t])  # the skip layer's time columns


def test_configs_and_their_names() -> None:
    assert ff.parse_config(ff.config_name(ff.DEFAULT_CONFIG)) == ff.DEFAULT_CONFIG
    assert ff.DEFAULT_CONFIG in ff.TUNE_CONFIGS
    for c in ff.TUNE_CONFIGS:
        assert 256 % c.block_n == 0 and c.block_m % 16 == 0 and c.num_warps in (4, 8)
    assert FusedConfig(block_n=64).for_width(32).block_n == 32
    assert not ff.supports(DeformationField(depth=2, width=48)) and ff.supports(_field())


# --- the wrapper and the frame path -------------------------------------------------------------------


@torch.no_grad()
def test_fused_field_caches_and_follows_weight_changes(interpret: None) -> None:
    field, xyz = _field(), _xyz(200)
    fast = FusedField(devices=ON_CPU)
    assert fast.runs_on(torch.device("cpu"))
    for t in (0.1, 0.8, torch.tensor(0.4)):
        got, want = fast(field, xyz, t, "points"), field(xyz, t)
        assert all(g.dtype == torch.float32 and g.shape == w.shape for g, w in zip(got, want))
        assert 0 < _max_diff(got, want) <= FP32_BOUND * _scale(want)
    assert fast.builds == 1
    for change in (
        lambda: field.layers[0].weight.add_(0.05),  # the first layer: its cached position part
        lambda: field.layers[2].bias.add_(0.05),  # the skip layer's bias, folded into the cache
        lambda: field.layers[3].weight.mul_(1.5),  # a layer of the kernel's own copies
        lambda: field.d_rot.bias.add_(0.01),  # a head
    ):
        before = [o.clone() for o in field(xyz, 0.5)]
        change()
        want = field(xyz, 0.5)
        assert _max_diff(want, before) > 1e-3
        assert _max_diff(fast(field, xyz, 0.5, "points"), want) <= FP32_BOUND * _scale(want)
    assert fast.builds == 5
    fast(field, xyz * 0.5, 0.5, "other points")
    assert fast.builds == 6


@torch.no_grad()
def test_a_width_the_kernel_does_not_take_runs_as_the_half_field(interpret: None) -> None:
    field, xyz = _field(width=48), _xyz(100)
    fused, half = FusedField(devices=ON_CPU), HalfField(devices=ON_CPU)
    for a, b in zip(fused(field, xyz, 0.3, "p"), half(field, xyz, 0.3, "p")):
        assert torch.equal(a, b)


def _canonical(n: int = 300, seed: int = 1) -> Canonical:
    g = torch.Generator().manual_seed(seed)
    return Canonical(
        means=torch.rand(n, 3, generator=g) * 2 - 1,
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        opacities=torch.randn(n, 1, generator=g),
        features_dc=torch.rand(n, 3, generator=g),
        features_rest=torch.zeros(n, 3, 3),
    )


@torch.no_grad()
@pytest.mark.parametrize("static_skip", [False, True])
def test_frame_path_renders_fp16_fused_with_the_fused_field(interpret: None, static_skip: bool) -> None:
    field, canonical = _field(), _canonical()
    static = torch.zeros(300, dtype=torch.bool)
    static[::3] = True
    offset = torch.zeros(300, 10)
    frame = FramePath(HalfField(devices=ON_CPU), FusedField(devices=ON_CPU))
    common = dict(static_skip=static_skip, cache_deformation=False)
    got = frame.splats(field, canonical, static, offset, 0.4, FrameSettings(render_precision="fp16-fused", **common))
    want = FramePath().splats(field, canonical, static, offset, 0.4, FrameSettings(**common))
    assert 0 < _max_diff(got[:3], want[:3]) <= FP32_BOUND
    assert frame.fused_field.builds == 1 and frame.half_field.builds == 0
    frame.splats(field, canonical, static, offset, 0.4, FrameSettings(render_precision="fp16", **common))
    assert frame.half_field.builds == 1 and frame.fused_field.cache_megabytes() == 0  # one cache at a time
    frame.splats(field, canonical, static, offset, 0.4, FrameSettings(**common))
    assert frame.half_field.cache_megabytes() == 0


@torch.no_grad()
def test_fp16_fused_is_the_plain_field_on_a_cpu_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the interpreter (and by default only CUDA is listed) the CPU renders exactly as fp32."""
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    field, canonical = _field(), _canonical()
    assert not FusedField(devices=ON_CPU).runs_on(torch.device("cpu"))
    frame = FramePath()
    fused = frame.splats(field, canonical, None, None, 0.3, FrameSettings(render_precision="fp16-fused"))
    plain = FramePath().splats(field, canonical, None, None, 0.3, FrameSettings())
    assert all(torch.equal(a, b) for a, b in zip(fused[:5], plain[:5]))
    assert frame.fused_field.builds == 0 and frame.half_field.builds == 0


def test_fused_field_refuses_gradients(interpret: None) -> None:
    field = _field()
    with pytest.raises(RuntimeError, match="without gradients"):
        FusedField(devices=ON_CPU)(field, _xyz(10), 0.3, "points")


def test_fp16_fused_round_trips_through_the_config_and_the_benchmark_names() -> None:
    import tyro
    import yaml

    from garo_ns.bench.benchmark import split_variant
    from garo_ns.garo_model import GaroModelConfig

    config = tyro.cli(GaroModelConfig, args=["--render-precision", "fp16-fused"])
    assert config.render_precision == "fp16-fused"
    assert yaml.load(yaml.dump(config), Loader=yaml.Loader).render_precision == "fp16-fused"
    base, render = split_variant("garo-deform+static+graph+fused+lean")
    assert base == "garo-deform" and render["render_precision"] == "fp16-fused" and render["cuda_graph"]


# --- GPU ----------------------------------------------------------------------------------------------

requires_cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="the fused kernel compiles for CUDA (a GPU test)"
)


@requires_cuda
@torch.no_grad()
@pytest.mark.parametrize("config", [ff.DEFAULT_CONFIG, FusedConfig(128, 32, 8, 3)], ids=ff.config_name)
def test_fused_field_on_cuda_is_within_its_bound_and_replays_as_eager(config: FusedConfig) -> None:
    from garo_ns.render.graphs import TimeGraph

    field = _recipe_shaped().cuda()
    xyz = _xyz(20_001, device="cuda")  # a ragged last block
    fast, graph = FusedField(config), TimeGraph()
    for t in (0.0, 0.37, 1.0, 0.37):
        want = field(xyz, t)
        eager = fast(field, xyz, torch.tensor(t, device="cuda"), "points")
        assert 0 < _max_diff(eager, want) <= FP32_BOUND * _scale(want)
        w, cache = fast._weights[1], fast._cache[1]  # type: ignore[index]
        tvec = w.time_rows(time_features(field, t, xyz.device))
        same = emulate(w, cache, tvec)
        assert float((torch.cat(eager, -1) - same).abs().max()) <= SAME_ARITHMETIC_BOUND * _scale(want)
        replay = [x.clone() for x in graph("k", lambda tt: fast(field, xyz, tt, "points"), t, xyz.device)]
        for a, b in zip(replay, eager):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert graph.captures == 1 and fast.builds == 1


@requires_cuda
@torch.no_grad()
def test_autotune_times_every_config() -> None:
    field, xyz = _recipe_shaped().cuda(), _xyz(4096, device="cuda")
    configs: List[FusedConfig] = [ff.DEFAULT_CONFIG, FusedConfig(64, 32, 8, 2)]
    best, table = ff.autotune(field, xyz, configs, repeats=3)
    assert best in configs and set(table) == {ff.config_name(c) for c in configs}
    assert all(isinstance(v, float) and v > 0 for v in table.values()), table
