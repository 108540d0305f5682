"""CUDA only: the training loss and the step's deformed Gaussians replayed from CUDA graphs give the eager values
and gradients, call after call with new inputs, and capture anew for a new size (benchmarks/device_run.sh gputests runs
them)."""

from __future__ import annotations

import gc
from contextlib import contextmanager

import pytest
import torch

from garo_ns.engine.losses import ImageLoss
from garo_ns.engine.ssim import SSIM

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")


def _images(shape, seed):
    g = torch.Generator(device="cuda").manual_seed(seed)
    gt = torch.rand(shape, generator=g, device="cuda")
    pred = (gt + 0.1 * torch.randn(shape, generator=g, device="cuda")).clamp(0, 1).requires_grad_(True)
    return gt, pred


@pytest.mark.parametrize("shape", [(64, 80, 3), (800, 800, 3)])
def test_the_graphed_loss_is_the_eager_loss(shape):
    graphed = ImageLoss(SSIM().cuda(), 0.2, graphed=True)
    for seed in range(4):
        gt, pred = _images(shape, seed)
        loss = graphed(gt, pred)
        (grad,) = torch.autograd.grad(loss, pred)
        gt2, pred2 = _images(shape, seed)
        want = graphed.eager(gt2, pred2)
        (want_grad,) = torch.autograd.grad(want, pred2)
        assert torch.allclose(loss, want, rtol=1e-6, atol=1e-7)
        assert torch.allclose(grad, want_grad, rtol=1e-5, atol=1e-9)
    assert len(graphed.graphs) == 1  # captured once for this size


def test_a_second_size_gets_its_own_graph_and_evaluation_stays_eager():
    graphed = ImageLoss(SSIM().cuda(), 0.2, graphed=True)
    for shape in ((32, 48, 3), (48, 32, 3)):
        gt, pred = _images(shape, 0)
        graphed(gt, pred).backward()
        assert pred.grad is not None and pred.grad.abs().sum() > 0
    with torch.no_grad():
        gt, pred = _images((16, 16, 3), 1)
        graphed(gt, pred)
    assert len(graphed.graphs) == 2


def _backward_grads(loss, leaves):
    """Each leaf's gradient of `loss` from a backward (the graphed step adds the field's into `.grad` itself)."""
    for x in leaves:
        x.grad = None
    loss.backward()
    return [x.grad.clone() for x in leaves]


def _canonical(n, seed):
    from garo_ns.render.frame import Canonical

    g = torch.Generator(device="cuda").manual_seed(seed)

    def leaf(*shape, mean=0.0, std=1.0):
        return (mean + std * torch.randn(*shape, generator=g, device="cuda")).requires_grad_(True)

    return Canonical(
        leaf(n, 3), leaf(n, 4), leaf(n, 3, mean=-3.0, std=0.3), leaf(n, 1), leaf(n, 3), leaf(n, 15, 3, std=0.1)
    )


@pytest.mark.parametrize("own_grads", [False, True])
@pytest.mark.parametrize("scale_offset", ["log", "linear"])
def test_the_graphed_splats_are_the_composed_gaussians_forward_and_backward(scale_offset, own_grads):
    """The whole step's Gaussians (field, composition, activations) from one graph: the eager values and the
    gradients of every canonical tensor and field parameter, call after call; a new count captures anew."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats
    from garo_ns.render.frame import Canonical, activate, compose

    torch.manual_seed(0)
    field = DeformationField(time_net=30).cuda().train()
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=own_grads)
    kept = ()
    for n, seed in ((4000, 0), (4000, 1), (4000, 2), (6000, 3), (3000, 4)):
        canonical = _canonical(n, seed)
        t = 0.1 + 0.2 * seed
        leaves = list(canonical) + list(field.parameters())
        out = graphed(canonical, t, scale_offset)
        got = _backward_grads(sum(o.square().sum() for o in out[:5]), leaves)
        twin = Canonical(*(x.detach().clone().requires_grad_(True) for x in canonical))
        want = activate(twin, compose(field, twin, t, scale_offset))
        want_grads = torch.autograd.grad(sum(o.square().sum() for o in want[:5]), list(twin) + list(field.parameters()))
        assert type(out[0].grad_fn).__name__ != "AddBackward0"  # the graph's node, not the eager sum
        for a, b in zip(out[:5], want[:5]):
            assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
        for a, b in zip(got, want_grads):
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-6 * float(b.abs().max().clamp_min(1.0)))
        if seed == 2:  # the 4000-Gaussian graph's last replay (a replay rewrites its graph's outputs in place)
            kept = (out[0], out[0].detach().clone())
    # Later captures share the first one's memory pool: an output of a dropped graph still held keeps its values.
    assert torch.equal(kept[0], kept[1])
    assert graphed.captures == 3  # 4000 Gaussians, then 6000, then 3000


def test_the_graphed_splats_run_eagerly_without_gradients_or_when_off():
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats

    field = DeformationField(time_net=30).cuda().train()
    canonical = _canonical(1000, 0)
    on, off = GraphedSplats(lambda: field, enabled=True), GraphedSplats(lambda: field, enabled=False)
    with torch.no_grad():
        on(canonical, 0.5, "log")
    field.eval()
    on(canonical, 0.5, "log")  # an evaluation: no graph either
    field.train()
    off(canonical, 0.5, "log")
    assert on.captures == 0 and off.captures == 0
    on(canonical, 0.5, "log")
    assert on.captures == 1


def test_a_graphed_backward_accumulates_into_grad_as_autograd_does():
    """With `own_grads` (deform_graph_grads) the graph adds the field's gradients into each parameter's `.grad`:
    from zero after an optimizer's zero_grad (None), onto a gradient already there (another tensor, or its own buffer
    from an earlier backward, whose version it bumps), and a parameter that is not trained gets none; the canonical
    tensors' gradients come through autograd as before."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.adam import is_graph_gradient
    from garo_ns.engine.train_graphs import GraphedSplats

    torch.manual_seed(0)
    field = DeformationField(time_net=30).cuda().train()
    frozen = field.layers[0].bias
    frozen.requires_grad_(False)
    canonical = _canonical(2000, 7)
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=True)
    trained = [p for p in field.parameters() if p.requires_grad]

    def loss():
        return sum(o.square().sum() for o in graphed(canonical, 0.5, "log")[:5])

    once = _backward_grads(loss(), list(canonical) + trained)
    loss().backward()
    versions = [p.grad._version for p in trained]
    loss().backward()  # onto its own buffer: the replay bumps its version, as an eager add would (AdamGraph reads it)
    assert all(is_graph_gradient(p.grad) and p.grad._version > v for p, v in zip(trained, versions))
    for x in list(canonical) + trained:
        x.grad = None  # an optimizer's zero_grad
    loss().backward()
    loss().backward()
    assert all(torch.allclose(p.grad, 2 * g, rtol=1e-5, atol=1e-7) for p, g in zip(trained, once[6:]))
    assert all(torch.allclose(x.grad, 2 * g, rtol=1e-5, atol=1e-7) for x, g in zip(canonical, once[:6]))
    extra = [torch.randn_like(p) for p in trained]
    for p, e in zip(trained, extra):
        p.grad = e.clone()  # another tensor
    loss().backward()
    assert all(torch.allclose(p.grad, e + g, rtol=1e-5, atol=1e-6) for p, e, g in zip(trained, extra, once[6:]))
    assert frozen.grad is None and graphed.captures == 1


def test_two_graphed_backwards_of_different_gradients_add_up():
    """Two backward passes without a zero between them (gradient accumulation) give the sum of two different
    gradients, for the canonical tensors (their gradients leave the graph through autograd) and the field's
    parameters (added into their buffers). Two equal gradients could not tell g1 + g2 from g2 + g2."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats

    torch.manual_seed(0)
    field = DeformationField(time_net=30).cuda().train()
    canonical = _canonical(2000, 3)
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=True)
    leaves = list(canonical) + [p for p in field.parameters() if p.requires_grad]

    def loss(time: float):
        return sum(o.square().sum() for o in graphed(canonical, time, "log")[:5])

    first = _backward_grads(loss(0.2), leaves)
    second = _backward_grads(loss(0.7), leaves)
    assert any(not torch.allclose(a, b) for a, b in zip(first, second))  # the two gradients differ
    for x in leaves:
        x.grad = None
    loss(0.2).backward()
    loss(0.7).backward()
    for x, a, b in zip(leaves, first, second):
        assert torch.allclose(x.grad, a + b, rtol=1e-4, atol=1e-6 * float((a + b).abs().max().clamp_min(1.0)))
    assert graphed.captures == 1


def _stream_waits(step) -> int:
    """cudaStreamWaitEvent calls while `step` runs (after one call outside the count)."""
    step()
    torch.cuda.synchronize()
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=activities) as prof:
        step()
        torch.cuda.synchronize()
    return sum(e.count for e in prof.key_averages() if e.key == "cudaStreamWaitEvent")


@pytest.mark.parametrize("own_grads", [False, True])
def test_a_graphed_step_accumulates_its_gradients_on_the_step_stream(own_grads):
    """A graphed step's backward hands no gradient across streams, whether the graph adds the field's gradients
    itself or hands them to autograd (`functional_splats`' stand-ins keep the capture's accumulators). The module
    graphed as itself, its parameters its own, waits on an event per parameter: the case the stand-ins exist for,
    and what shows that this test can fail."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats, _SplatsCall

    field = DeformationField(time_net=30).cuda().train()
    canonical = _canonical(3000, 0)
    t = torch.full((1, 1), 0.4, device="cuda")
    leaves = list(canonical) + list(field.parameters())
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=own_grads)

    def step(run) -> None:
        for p in leaves:
            p.grad = None
        sum(o.square().sum() for o in run()[:5]).backward()

    assert _stream_waits(lambda: step(lambda: graphed(canonical, 0.4, "log"))) == 0
    assert graphed.captures == 1 and all(p.grad is not None for p in leaves)
    # Graphed as itself, the module's capture makes (and keeps) its parameters' accumulators on the side stream.
    samples = tuple(x.detach().clone().requires_grad_(True) for x in canonical) + (t.clone(),)
    module_graphed = torch.cuda.make_graphed_callables(_SplatsCall(field, "log"), samples)
    assert _stream_waits(lambda: step(lambda: module_graphed(*canonical, t))) >= len(list(field.parameters()))


def test_a_new_capture_reuses_the_memory_of_the_graph_it_replaces():
    """Densification captures anew at every new count of Gaussians. Each `StepGraph` capture (deform_graph_grads)
    must reuse the memory its dropped predecessor held: what the process keeps reserved stops growing after the
    first captures. Captures on a new stream each (torch hands out up to 32) could not reuse it, and grew by about
    one capture's memory every time. torch's make_graphed_callables (deform_graph_grads off), which warms up on a new
    stream at every capture, failed this bound on an H100 (benchmarks/results/cuda_subset_memory_H100.log)."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats

    field = DeformationField(time_net=30).cuda().train()
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=True)
    gc.collect()
    torch.cuda.empty_cache()
    before = torch.cuda.memory_reserved()
    reserved = []
    for i in range(12):
        canonical = _canonical(20000 + 100 * i, i)  # grows as densification does
        sum(o.square().sum() for o in graphed(canonical, 0.3, "log")[:5]).backward()
        del canonical
        gc.collect()
        torch.cuda.empty_cache()  # what is left reserved is held: live tensors and the graphs' pool
        reserved.append(torch.cuda.memory_reserved())
    first = reserved[0] - before
    assert graphed.captures == 12 and first > 0
    assert reserved[-1] - reserved[2] < 0.5 * first, [r - before for r in reserved]


def test_the_bf16_step_graph_replays_the_eager_bf16_step():
    """`deform_train_bf16` graphed: the same autocast kernels as the eager bf16 step, so the same values and
    gradients up to the order of the products' sums; the weights the graph reads are recast at every replay (an
    optimizer step between two replays shows in the second)."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats

    torch.manual_seed(0)
    field = DeformationField(time_net=30).cuda().train()
    graphed = GraphedSplats(lambda: field, enabled=True, bf16=True, own_grads=True)
    eager = GraphedSplats(lambda: field, enabled=False, bf16=True)
    for seed in range(3):
        canonical = _canonical(4000, seed)
        leaves = list(canonical) + list(field.parameters())
        out = graphed(canonical, 0.2 + 0.2 * seed, "log")
        got = _backward_grads(sum(o.square().sum() for o in out[:5]), leaves)
        want = eager(canonical, 0.2 + 0.2 * seed, "log")
        want_grads = _backward_grads(sum(o.square().sum() for o in want[:5]), leaves)
        for a, b in zip(out[:5], want[:5]):
            assert torch.allclose(a, b, rtol=1e-3, atol=1e-5)
        for a, b in zip(got, want_grads):
            assert torch.allclose(a, b, rtol=1e-2, atol=1e-4 * float(b.abs().max().clamp_min(1.0)))
        with torch.no_grad():
            for p in field.parameters():
                p.add_(0.01 * torch.randn_like(p))
    assert graphed.captures == 1


@contextmanager
def _collections_seen():
    """Python's collector run at (nearly) every allocation; yields, per collection, whether a CUDA graph was being
    captured on the current stream when it ran."""
    seen = []

    def watch(phase, info):
        if phase == "start":
            seen.append(torch.cuda.is_current_stream_capturing())

    saved = gc.get_threshold()
    gc.callbacks.append(watch)
    gc.set_threshold(1)
    try:
        yield seen
    finally:
        gc.set_threshold(*saved)
        gc.callbacks.remove(watch)


@pytest.mark.parametrize("own_grads", [False, True])
def test_no_collection_runs_inside_a_capture(own_grads):
    """A dropped graph of torch's is freed only by a collection, and one freed during another capture invalidates that
    capture (a training run crashed so): every capture here runs with the collector paused, `StepGraph`'s (the
    default, `deform_graph_grads`) as well."""
    from garo_ns.deformation import DeformationField
    from garo_ns.engine.train_graphs import GraphedSplats
    from garo_ns.render.graphs import capture

    field = DeformationField(time_net=30).cuda().train()
    graphed = GraphedSplats(lambda: field, enabled=True, own_grads=own_grads)
    loss = ImageLoss(SSIM().cuda(), 0.2, graphed=True)
    with _collections_seen() as seen:
        for n in (3000, 3100, 3200):  # each new count drops the previous graph
            out = graphed(_canonical(n, n), 0.3, "log")
            out[0].sum().backward()
        gt, pred = _images((32, 32, 3), 0)
        loss(gt, pred).backward()
        capture(lambda x: 2 * x, (torch.ones(4, device="cuda"),), torch.device("cuda"), 1)
    assert graphed.captures == 3 and len(seen) > 10  # the collector did run, often
    assert not any(seen)
