"""LeanAdam: bitwise torch's fused Adam (updates, state, checkpoints both ways), torch's step where it does not
apply."""

from __future__ import annotations

import copy

import pytest
import torch

from garo_ns.engine import adam
from garo_ns.engine.adam import LeanAdam


def _params(seed=0, shapes=((100, 3), (7,), (5, 4, 2))):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g)) for s in shapes]


def _steps(opt, params, steps, seed=1, decay=0.9):
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        for p in params:
            p.grad = torch.randn(p.shape, generator=g)
        params[1].grad = None if _ % 3 == 2 else params[1].grad  # a parameter without a gradient is left alone
        opt.param_groups[0]["lr"] *= decay  # a scheduler's float learning rate
        opt.step()


def _same(a, b):
    return all(torch.equal(x, y) for x, y in zip(a, b))


def test_lean_updates_are_bitwise_those_of_torchs_fused_adam():
    ref, lean = _params(), _params()
    torch_opt = torch.optim.Adam(ref, lr=1e-2, eps=1e-15, fused=True)
    lean_opt = LeanAdam(lean, lr=1e-2, eps=1e-15)
    _steps(torch_opt, ref, 25)
    _steps(lean_opt, lean, 25)
    assert _same(ref, lean)
    for p, q in zip(ref, lean):
        s, t = torch_opt.state[p], lean_opt.state[q]
        assert set(s) == set(t) == {"step", "exp_avg", "exp_avg_sq"}
        assert all(torch.equal(s[k], t[k]) and s[k].dtype == t[k].dtype for k in s)
    assert not _same(_params(), lean)  # the control: the parameters moved


@pytest.mark.parametrize("first", ["lean", "torch"])
def test_checkpoints_move_between_lean_and_torchs_fused_adam(first):
    make = {
        "lean": lambda ps: LeanAdam(ps, lr=1e-2, eps=1e-15),
        "torch": lambda ps: torch.optim.Adam(ps, lr=1e-2, eps=1e-15, fused=True),
    }
    second = "torch" if first == "lean" else "lean"
    params = _params()
    opt = make[first](params)
    _steps(opt, params, 10)
    saved = ([p.detach().clone() for p in params], copy.deepcopy(opt.state_dict()))
    _steps(opt, params, 10, seed=2)  # go on in the first

    resumed = [torch.nn.Parameter(p.clone()) for p in saved[0]]
    other = make[second](resumed)
    other.load_state_dict(saved[1])
    _steps(other, resumed, 10, seed=2)  # the same ten steps in the second
    assert _same(params, resumed)


def test_an_edited_state_is_followed_as_torch_follows_it():
    # gsplat's densification puts new parameters in the group and carries (grown) moments and the step counter over.
    runs = []
    for make in (lambda ps: LeanAdam(ps, lr=1e-2), lambda ps: torch.optim.Adam(ps, lr=1e-2, fused=True)):
        params = _params()
        opt = make(params)
        _steps(opt, params, 5)
        old = params[0]
        new = torch.nn.Parameter(torch.cat([old.detach(), old.detach()[:10]]))
        state = opt.state.pop(old)
        state["exp_avg"] = torch.cat([state["exp_avg"], torch.zeros(10, 3)])
        state["exp_avg_sq"] = torch.cat([state["exp_avg_sq"], torch.zeros(10, 3)])
        opt.param_groups[0]["params"][0] = new
        opt.state[new] = state
        params[0] = new
        _steps(opt, params, 5, seed=3)
        runs.append(params)
    assert _same(*runs)


@pytest.mark.parametrize("option", [{"amsgrad": True}, {"maximize": True}])
def test_what_the_lean_step_does_not_cover_goes_through_torchs_step(option):
    ref, lean = _params(), _params()
    _steps(torch.optim.Adam(ref, lr=1e-2, fused=True, **option), ref, 8)
    _steps(LeanAdam(lean, lr=1e-2, **option), lean, 8)
    assert _same(ref, lean)


def test_a_closure_is_evaluated_as_torch_evaluates_it():
    params = _params()
    opt = LeanAdam(params, lr=1e-2)
    calls = []

    def closure():
        calls.append(1)
        for p in params:
            p.grad = torch.ones_like(p)
        return 3.0

    assert opt.step(closure) == 3.0 and calls == [1]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: training's optimizers are lean on CUDA only")
def test_lean_updates_on_cuda_are_bitwise_torchs_and_training_uses_them():
    from garo_ns.config import AdamConfig

    ref = [torch.nn.Parameter(p.detach().cuda()) for p in _params()]
    lean = [torch.nn.Parameter(p.detach().cuda()) for p in _params()]
    torch_opt = torch.optim.Adam(ref, lr=1e-2, eps=1e-15, fused=True)
    lean_opt = AdamConfig(lr=1e-2, eps=1e-15).setup(lean)
    assert isinstance(lean_opt, LeanAdam)
    for opt, params in ((torch_opt, ref), (lean_opt, lean)):
        g = torch.Generator(device="cuda").manual_seed(1)
        for _ in range(20):
            for p in params:
                p.grad = torch.randn(p.shape, generator=g, device="cuda")
            opt.param_groups[0]["lr"] *= 0.9
            opt.step()
    assert _same(ref, lean)
    assert not isinstance(AdamConfig(lr=1e-2).setup(_params()), LeanAdam)  # the CPU keeps torch's default Adam


def _nerfstudio_optimizers(lean: bool, max_norm=None, device="cpu"):
    from nerfstudio.engine.optimizers import Optimizers

    from garo_ns.config import AdamConfig

    groups = {name: [torch.nn.Parameter(p.detach().to(device))] for name, p in zip("abc", _params())}
    config = {
        name: {"optimizer": AdamConfig(lr=lr, eps=1e-15, max_norm=max_norm), "scheduler": None}
        for name, lr in zip("abc", (1e-2, 3e-3, 5e-2))
    }
    opts = Optimizers(config, groups)
    make = (
        (lambda ps, lr: LeanAdam(ps, lr=lr, eps=1e-15))
        if lean
        else (lambda ps, lr: torch.optim.Adam(ps, lr=lr, eps=1e-15, fused=True))
    )
    opts.optimizers = {name: make(groups[name], config[name]["optimizer"].lr) for name in groups}
    return opts, [groups[n][0] for n in "abc"]


class _Scaler:
    """nerfstudio's grad scaler as the loop sees it; `enabled`: one that scales (mixed precision)."""

    def __init__(self, enabled=False):
        self.enabled, self.steps = enabled, 0

    def is_enabled(self):
        return self.enabled

    def step(self, optimizer):
        self.steps += 1
        return optimizer.step()


def _loop(opts, params, steps, scaler, seed=1):
    g = torch.Generator().manual_seed(seed)
    for i in range(steps):
        opts.zero_grad_some(["a", "b", "c"])
        for p in params:
            if not (p is params[2] and i % 4 == 3):  # a group without a gradient this step
                p.grad = torch.randn(p.shape, generator=g).to(p.device)
        for name in "abc":
            opts.optimizers[name].param_groups[0]["lr"] *= 0.95
        opts.optimizer_scaler_step_some(scaler, ["a", "b", "c"])


def test_the_grouped_step_updates_every_group_as_nerfstudios_loop_does():
    ref, ref_params = _nerfstudio_optimizers(lean=False)
    grouped, params = _nerfstudio_optimizers(lean=True)
    assert adam.install_grouped_step(grouped) and not adam.install_grouped_step(grouped)  # once
    scaler = _Scaler()
    _loop(ref, ref_params, 12, _Scaler())
    _loop(grouped, params, 12, scaler)
    assert scaler.steps == 0  # nothing went through the per-optimizer path
    assert _same(ref_params, params)
    for name in "abc":
        s, t = (o.optimizers[name].state_dict()["state"][0] for o in (ref, grouped))
        assert all(torch.equal(s[k], t[k]) for k in s)
    grouped.zero_grad_some(["a"])
    assert params[0].grad is None and params[1].grad is not None


def test_the_grouped_step_is_not_installed_where_it_would_change_the_step():
    assert not adam.install_grouped_step(_nerfstudio_optimizers(lean=False)[0])  # torch's Adam (the CPU's)
    assert not adam.install_grouped_step(_nerfstudio_optimizers(lean=True, max_norm=1.0)[0])  # clipping


def test_a_scaling_grad_scaler_takes_nerfstudios_path():
    ref, ref_params = _nerfstudio_optimizers(lean=False)
    grouped, params = _nerfstudio_optimizers(lean=True)
    adam.install_grouped_step(grouped)
    scaler = _Scaler(enabled=True)
    _loop(ref, ref_params, 4, _Scaler(enabled=True))
    _loop(grouped, params, 4, scaler)
    assert scaler.steps > 0 and _same(ref_params, params)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the grouped step is installed on CUDA runs")
def test_a_cuda_run_steps_its_optimizers_grouped():
    from nerfstudio.engine.optimizers import Optimizers

    from garo_ns.config import AdamConfig

    groups = {name: [torch.nn.Parameter(p.detach().cuda())] for name, p in zip("abc", _params())}
    config = {
        name: {"optimizer": AdamConfig(lr=lr, eps=1e-15), "scheduler": None}
        for name, lr in zip("abc", (1e-2, 3e-3, 5e-2))
    }
    opts = Optimizers(config, groups)  # our config's Adam, as a CUDA training run makes it
    assert all(isinstance(o, LeanAdam) for o in opts.optimizers.values()) and adam.install_grouped_step(opts)
    ref, ref_params = _nerfstudio_optimizers(lean=False, device="cuda")
    params = [groups[n][0] for n in "abc"]
    g = torch.Generator(device="cuda").manual_seed(1)
    grads = [[torch.randn(p.shape, generator=g, device="cuda") for p in params] for _ in range(6)]
    for o, ps in ((opts, params), (ref, ref_params)):
        for step_grads in grads:
            o.zero_grad_some(list("abc"))
            for p, gr in zip(ps, step_grads):
                p.grad = gr.clone()
            o.optimizer_scaler_step_some(_Scaler(), list("abc"))
    assert _same(params, ref_params) and not _same(params, [p.cuda() for p in _params()])


def _backward_loop(opts, params, steps, seed=1, skip=None, edit=None, fp32_rates=False):
    """nerfstudio's loop with gradients from a backward pass (autograd adds into an existing gradient in place), a
    float learning-rate schedule on every group, `skip(i, k)`: parameter k gets no gradient at step i, `edit(i)`: a
    change after step i's update (as densification's)."""
    g = torch.Generator().manual_seed(seed)
    for i in range(steps):
        opts.zero_grad_some(list("abc"))
        targets = [torch.randn(p.shape, generator=g).to(p.device) for p in params]
        used = [k for k in range(len(params)) if not (skip and skip(i, k))]
        loss = sum(((params[k] - targets[k]) ** 2).sum() for k in used)
        loss.backward()
        for name in "abc":
            group = opts.optimizers[name].param_groups[0]
            group["lr"] *= 0.97
            if fp32_rates:  # rates that are fp32 numbers, as CUDA's kernel reads a device rate
                group["lr"] = torch.tensor(group["lr"], dtype=torch.float32).item()
        opts.optimizer_scaler_step_some(_Scaler(), list("abc"))
        if edit is not None:
            edit(i, opts, params)


def _graphed_pair(device="cpu", stable_steps=4):
    ref, ref_params = _nerfstudio_optimizers(lean=True, device=device)
    graphed, params = _nerfstudio_optimizers(lean=True, device=device)
    graph = adam.AdamGraph(stable_steps=stable_steps)
    assert adam.install_grouped_step(ref) and adam.install_grouped_step(graphed, graph)
    return (ref, ref_params), (graphed, params), graph


def _same_states(a, b):
    for name in "abc":
        s, t = (o.optimizers[name].state_dict()["state"][0] for o in (a, b))
        assert all(torch.equal(s[k], t[k]) for k in s), name


def test_the_graphed_step_is_bitwise_the_grouped_step():
    """Once stable, the step runs the graph's calls (eagerly on a CPU): tensor learning rates, gradients kept in the
    graph's buffers and zeroed by it; the parameters and states are those of the step without it, bit for bit."""
    (ref, ref_params), (graphed, params), graph = _graphed_pair()
    _backward_loop(ref, ref_params, 20)
    _backward_loop(graphed, params, 20)
    assert graph.captures == 1 and graph.replays == 16  # states from step 1 on: stable for 4 steps at step 5
    assert _same(ref_params, params) and not _same(params, _params())
    _same_states(ref, graphed)
    graphed.zero_grad_some(list("abc"))  # the graph's buffers stay, zeroed by its last update
    assert all(p.grad is not None and not p.grad.any() for p in params)


@pytest.mark.parametrize("change", ["no_gradient", "moved_state", "replaced_gradient"])
def test_the_graph_steps_aside_where_the_step_would_differ(change):
    """A parameter without a gradient at a step (no update at all, not a zero one), a state that moved (as
    densification moves them) or a gradient replaced: that step is the grouped step's, and the graph is captured anew
    once things are stable again; the numbers stay those of the step without it."""
    (ref, ref_params), (graphed, params), graph = _graphed_pair()
    skip = (lambda i, k: i == 9 and k == 1) if change == "no_gradient" else None

    def edit(i, opts, ps):
        if change == "moved_state" and i == 9:
            state = opts.optimizers["b"].state[ps[1]]
            state["exp_avg"] = state["exp_avg"].clone()
        if change == "replaced_gradient" and i == 9:
            ps[2].grad = torch.zeros_like(ps[2])  # a new tensor where the graph's buffer was

    _backward_loop(ref, ref_params, 20, skip=skip, edit=edit)
    _backward_loop(graphed, params, 20, skip=skip, edit=edit)
    assert _same(ref_params, params)
    _same_states(ref, graphed)
    assert graph.captures == 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the graph is captured on CUDA")
def test_the_adam_cuda_graph_replays_the_grouped_step_bitwise():
    """On CUDA, bit for bit where the learning rates are fp32 numbers; otherwise within their rounding to fp32."""
    skip = lambda i, k: i == 12 and k == 0  # noqa: E731
    for fp32_rates in (True, False):
        (ref, ref_params), (graphed, params), graph = _graphed_pair(device="cuda")
        _backward_loop(ref, ref_params, 30, skip=skip, fp32_rates=fp32_rates)
        _backward_loop(graphed, params, 30, skip=skip, fp32_rates=fp32_rates)
        assert graph.captures == 2 and isinstance(graph.run.__self__, torch.cuda.CUDAGraph)
        if fp32_rates:
            assert _same(ref_params, params)
            _same_states(ref, graphed)
        else:
            for p, q in zip(ref_params, params):  # the rates' rounding to fp32: a few ulps after 30 steps
                assert torch.allclose(p, q, rtol=5e-7, atol=1e-7)


def test_the_graph_shares_a_gradient_another_graph_writes_in_place():
    """A gradient marked as another graph's fixed buffer (the training step's StepGraph, which adds into it without
    autograd and bumps its version) stays that parameter's `.grad` through the capture: taking a copy would have
    the step graph copy it back each step and each drop the other. Unmarked gradients get the graph's own buffers;
    the numbers are the grouped step's either way."""
    from torch.autograd.graph import increment_version

    (ref, ref_params), (graphed, params), graph = _graphed_pair()
    buffers = {}
    for run, ps in ((ref, ref_params), (graphed, params)):
        buffer = torch.zeros_like(ps[0])
        adam.graph_gradients([buffer])
        buffers[id(ps[0])] = buffer
        g = torch.Generator().manual_seed(1)
        for _ in range(20):
            run.zero_grad_some(list("abc"))
            targets = [torch.randn(p.shape, generator=g) for p in ps]
            if ps[0].grad is not buffer:  # as StepGraph's backward attaches its buffer (attach_gradients)
                buffer.zero_() if ps[0].grad is None else buffer.copy_(ps[0].grad)
                ps[0].grad = buffer
            buffer.data.add_(2 * (ps[0].detach() - targets[0]))  # an add autograd does not see, as a replay's
            increment_version(buffer)
            sum(((p - t) ** 2).sum() for p, t in zip(ps[1:], targets[1:])).backward()
            for name in "abc":
                run.optimizers[name].param_groups[0]["lr"] *= 0.97
            run.optimizer_scaler_step_some(_Scaler(), list("abc"))
    assert graph.captures == 1 and graph.replays == 16
    assert params[0].grad is buffers[id(params[0])] and all(not adam.is_graph_gradient(p.grad) for p in params[1:])
    assert _same(ref_params, params)
    _same_states(ref, graphed)
