"""garo_ns.ops.dense and the deformation field's fused layers (`deform_fused_layers`) against torch's own layers."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from garo_ns.deformation import DeformationField
from garo_ns.ops.dense import aligned, dense


def test_aligned_pads_to_the_next_multiple_of_eight():
    assert [aligned(w) for w in (93, 349, 96, 10, 1)] == [3, 3, 0, 6, 7]


@pytest.mark.parametrize("relu", [False, True])
def test_dense_gradients_match_finite_differences(relu):
    torch.manual_seed(0)
    x = torch.randn(7, 5, dtype=torch.float64, requires_grad=True)
    w = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    b = torch.randn(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, w, b: dense(x, w, b, relu), (x, w, b))


@pytest.mark.parametrize("relu", [False, True])
def test_dense_is_a_linear_layer_in_fp32(relu):
    torch.manual_seed(1)
    x = torch.randn(300, 93, requires_grad=True)
    layer = torch.nn.Linear(93, 256)
    g = torch.randn(300, 256)
    ours = dense(x, layer.weight, layer.bias, relu)
    ref = F.linear(x, layer.weight, layer.bias)
    ref = torch.relu(ref) if relu else ref
    torch.testing.assert_close(ours, ref, rtol=1e-6, atol=1e-6)
    grads = torch.autograd.grad(ours, (x, layer.weight, layer.bias), g)
    refs = torch.autograd.grad(ref, (x, layer.weight, layer.bias), g)
    for a, r in zip(grads, refs):
        torch.testing.assert_close(a, r, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param(
            "cuda",
            marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA: cuBLASLt's ReLU epilogue"),
        ),
    ],
)
def test_dense_under_autocast_computes_in_its_dtype_and_returns_gradients_in_the_inputs(device):
    """As F.linear under autocast: a bf16 product and output; the fp32 weights get fp32 gradients (torch would cast
    them too), within bf16's rounding of torch's own layer."""
    torch.manual_seed(2)
    x = torch.randn(500, 96, requires_grad=True, device=device)
    layer = torch.nn.Linear(96, 64).to(device)
    with torch.autocast(device, dtype=torch.bfloat16):
        ours = dense(x, layer.weight, layer.bias, relu=True)
        ref = torch.relu(F.linear(x, layer.weight, layer.bias))
    assert ours.dtype == ref.dtype == torch.bfloat16
    g = torch.randn_like(ref)
    grads = torch.autograd.grad(ours, (x, layer.weight, layer.bias), g)
    refs = torch.autograd.grad(ref, (x, layer.weight, layer.bias), g)
    assert [t.dtype for t in grads] == [torch.float32] * 3
    torch.testing.assert_close(ours.float(), ref.float(), rtol=2e-2, atol=2e-2)
    for a, r in zip(grads, refs):
        assert ((a - r).norm() / r.norm()).item() < 2e-2


def _pair(time_net: int = 30):
    torch.manual_seed(3)
    plain = DeformationField(time_net=time_net)
    fused = DeformationField(time_net=time_net, fused_layers=True)
    fused.load_state_dict(plain.state_dict())
    return plain, fused


@pytest.mark.parametrize("time_net", [30, 0])
def test_a_fused_field_computes_the_plain_fields_offsets_and_gradients(time_net):
    """fp32 on the CPU: the same offsets and parameter gradients up to the order of the sums (tolerances 1e-5 of
    each tensor's scale), with time as a scalar and per row, with the time network (input width 93) and without
    (63: both padded to 64 and 96 + 256 after the skip)."""
    plain, fused = _pair(time_net)
    xyz = torch.randn(400, 3)
    for time in (0.37, torch.rand(400, 1)):
        out_p, out_f = plain(xyz, time), fused(xyz, time)
        coefs = [torch.randn_like(o) for o in out_p]
        loss_p = sum((o * c).sum() for o, c in zip(out_p, coefs))
        loss_f = sum((o * c).sum() for o, c in zip(out_f, coefs))
        grads_p = torch.autograd.grad(loss_p, list(plain.parameters()))
        grads_f = torch.autograd.grad(loss_f, list(fused.parameters()))
        for a, r in zip(out_f, out_p):
            assert a.shape == r.shape
            torch.testing.assert_close(a, r, rtol=1e-5, atol=1e-5 * r.abs().max().item())
        for (name, _), a, r in zip(plain.named_parameters(), grads_f, grads_p):
            assert ((a - r).norm() / r.norm().clamp_min(1e-12)).item() < 1e-5, name


def test_a_fused_field_has_the_plain_fields_parameters_and_checkpoints():
    plain, fused = _pair()
    assert plain.state_dict().keys() == fused.state_dict().keys()
    for a, b in zip(plain.state_dict().values(), fused.state_dict().values()):
        assert a.shape == b.shape


def test_the_setting_builds_a_fused_field():
    from garo_ns.deformation import DeformationSettings

    assert not DeformationSettings().make_deformation().fused_layers
    assert DeformationSettings(deform_fused_layers=True).make_deformation().fused_layers


@pytest.mark.slow
def test_garo_deform_trains_the_built_in_scene_with_fused_layers(scene_dir, tmp_path):
    """The setting end to end on the CPU: the model builds the fused field, trains to the demo's quality (the bound
    of tests/test_training.py), and its checkpoint loads into a model with the fused field that renders the same
    image."""
    from conftest import _train, render_view
    from test_training import MIN_TEST_PSNR

    from garo_ns.tools.eval import load_run

    run = _train("garo-deform", scene_dir, tmp_path, deform_fused_layers=True)
    model = run["trainer"].pipeline.model
    assert model.deformation.fused_layers
    assert run["l1_after"] < 0.5 * run["l1_before"]
    assert run["eval"]["psnr"] > MIN_TEST_PSNR, run["eval"]
    model.eval()
    # A CUDA machine loads the checkpoint onto the GPU; the run trained on the CPU, and the two rasterizers differ.
    loaded = load_run(run["config_path"])[1].model.to(model.device)
    assert loaded.deformation.fused_layers
    loaded.config.time_table = False  # the network's frame on both sides
    cam = run["trainer"].pipeline.datamanager.train_dataset.cameras[3:4].to(model.device)
    torch.testing.assert_close(render_view(loaded, cam), render_view(model, cam), rtol=0, atol=1e-6)


def test_dense_without_torchs_fused_relu_op_computes_the_same(monkeypatch):
    """`torch._addmm_activation` is private: without it the layer takes the product and the ReLU apart."""
    torch.manual_seed(4)
    x, layer = torch.randn(50, 24), torch.nn.Linear(24, 16)
    want = dense(x, layer.weight, layer.bias, relu=True)
    monkeypatch.delattr(torch, "_addmm_activation")
    torch.testing.assert_close(dense(x, layer.weight, layer.bias, relu=True), want, rtol=1e-6, atol=1e-6)
