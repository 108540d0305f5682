"""CUDA-graph replay of the render-time deformation (garo_ns.render.graphs): exact against eager
kernels, captured again when the key changes. Needs a CUDA device (run on the GPU machine)."""

from __future__ import annotations

import pytest
import torch

from garo_ns.deformation import DeformationField
from garo_ns.render.graphs import InputGraph, TimeGraph

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")


def _field() -> DeformationField:
    torch.manual_seed(0)
    field = DeformationField().cuda()
    for head in (field.d_xyz, field.d_rot, field.d_scale):
        torch.nn.init.normal_(head.weight, std=0.05)
    return field


@torch.no_grad()
def test_replay_matches_eager():
    """The fp32 field, as the frame path's deformation graph replays it."""
    field, xyz = _field(), torch.rand(20_000, 3, device="cuda")

    def step(t):
        return field(xyz, t)

    graph = TimeGraph()
    for t in (0.0, 0.37, 1.0, 0.37):
        replay = [x.clone() for x in graph("k", step, t, xyz.device)]
        eager = step(torch.tensor(t, device="cuda"))
        for a, b in zip(replay, eager):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert graph.captures == 1


@torch.no_grad()
def test_new_key_recaptures_and_reuse_skips_the_replay():
    field, xyz = _field(), torch.rand(1000, 3, device="cuda")
    graph = TimeGraph()
    out = graph(1, lambda t: field(xyz, t), 0.5, xyz.device)[0].clone()
    field.d_xyz.bias.add_(1.0)  # a parameter changed: the caller's key changes with it
    moved = graph(2, lambda t: field(xyz, t), 0.5, xyz.device)[0]
    assert graph.captures == 2
    torch.testing.assert_close(moved, out + 1.0)
    buffers = graph(2, lambda t: field(xyz, t), 0.5, xyz.device, reuse=True)
    assert buffers[0] is moved  # same time, same key: the buffers as they are


def test_replay_refuses_autograd():
    field, xyz = _field(), torch.rand(10, 3, device="cuda")
    with pytest.raises(RuntimeError, match="inference only"):
        TimeGraph()("k", lambda t: field(xyz, t), 0.1, xyz.device)


@torch.no_grad()
def test_input_graph_replays_new_inputs_and_recaptures_on_new_shapes():
    weight = torch.randn(64, 32, device="cuda")

    def fn(a, b):
        return torch.relu(a @ weight + b), (a > 0).sum(-1)

    graph = InputGraph()
    for seed in range(3):
        torch.manual_seed(seed)
        a, b = torch.randn(100, 64, device="cuda"), torch.randn(32, device="cuda")
        replay = [x.clone() for x in graph("k", fn, a, b)]
        for x, y in zip(replay, fn(a, b)):
            torch.testing.assert_close(x, y, rtol=0, atol=0)
    assert graph.captures == 1
    smaller = torch.randn(50, 64, device="cuda")
    out = graph("k", fn, smaller, b)
    assert graph.captures == 2 and out[0].shape == (50, 32)
    graph("other", fn, smaller, b)
    assert graph.captures == 3


def test_input_graph_refuses_autograd():
    with pytest.raises(RuntimeError, match="inference only"):
        InputGraph()("k", lambda a: a * 2, torch.ones(3, device="cuda"))
