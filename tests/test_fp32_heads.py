"""The deformation field's heads in fp32 under bf16 autocast (`deform_fp32_heads`), here under the CPU's bf16
autocast, which runs the same casts as CUDA's (the bf16 training path itself is CUDA-only)."""

from __future__ import annotations

import pytest
import torch

from garo_ns.deformation import DeformationField, DeformationSettings


def _field(fused: bool, fp32_heads: bool, seed: int = 0) -> DeformationField:
    torch.manual_seed(seed)
    field = DeformationField(depth=4, width=64, skip=2, time_net=30, fused_layers=fused, fp32_heads=fp32_heads)
    with torch.no_grad():
        # A scale offset near -4 on every Gaussian: as where a linear offset nearly cancels a scale of about 4, so
        # the offset's rounding is the composed scale's.
        field.d_scale.bias.fill_(-4.0)
    return field


def _inputs(n: int = 500):
    g = torch.Generator().manual_seed(1)
    return torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 1, generator=g)


def _bf16(field: DeformationField, xyz, t):
    with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
        return field(xyz, t)


@pytest.mark.parametrize("fused", [False, True])
def test_fp32_heads_take_the_bf16_hidden_layer_through_fp32_heads(fused):
    """Under autocast the offsets are the fp32 heads of the last hidden layer that bf16 computed: exactly what the
    heads give outside autocast on that layer, in fp32."""
    field = _field(fused, fp32_heads=True)
    xyz, t = _inputs()
    got = _bf16(field, xyz, t)
    with torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False):
        h = field.hidden(xyz, t)[-1]
    assert h.dtype == torch.bfloat16
    want = field.heads(h.float(), torch.float32)
    for a, b in zip(got, want):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("fused", [False, True])
def test_fp32_heads_keep_the_scale_offset_that_bf16_rounds(fused):
    """Against the fp32 field, the scale offset near -4 loses about 2^-7 to bf16's rounding of the result (8 bits);
    with fp32 heads only the hidden layer's rounding is left, at least 8 times smaller here."""
    xyz, t = _inputs()
    ref = _field(fused, fp32_heads=False)(xyz, t)[2]
    plain = _bf16(_field(fused, fp32_heads=False), xyz, t)[2]
    fp32 = _bf16(_field(fused, fp32_heads=True), xyz, t)[2]
    err_plain, err_fp32 = (plain - ref).abs().max().item(), (fp32 - ref).abs().max().item()
    assert err_plain > 2e-3, err_plain  # the rounding this setting exists for
    assert err_fp32 < err_plain / 8, (err_fp32, err_plain)


@pytest.mark.parametrize("fused", [False, True])
def test_fp32_heads_change_nothing_outside_autocast_and_train_under_it(fused):
    xyz, t = _inputs(200)
    plain, fp32 = _field(fused, fp32_heads=False), _field(fused, fp32_heads=True)
    for a, b in zip(plain(xyz, t), fp32(xyz, t)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # Under autocast every parameter still gets a finite gradient, the heads' in fp32 like all of them.
    loss = sum(o.square().sum() for o in _bf16(fp32, xyz, t))
    loss.backward()
    for name, p in fp32.named_parameters():
        assert p.grad is not None and p.grad.dtype == torch.float32 and torch.isfinite(p.grad).all(), name
    assert fp32.d_scale.weight.grad.abs().sum() > 0


def test_the_setting_builds_the_field_with_fp32_heads():
    assert not DeformationSettings().make_deformation().fp32_heads
    assert DeformationSettings(deform_fp32_heads=True).make_deformation().fp32_heads


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA's bf16 autocast, as training runs it")
def test_on_a_gpu_bf16_training_keeps_the_scale_offset_with_fp32_heads():
    """The training path's wrapper (garo_ns.engine.train_graphs.Bf16Field) on CUDA: the heads' fp32 product under its
    autocast, the offsets in fp32 and the scale offset's bf16 rounding gone, as on the CPU."""
    from garo_ns.engine.train_graphs import Bf16Field

    xyz, t = (x.cuda() for x in _inputs())
    ref = _field(True, fp32_heads=False).cuda()(xyz, t)[2]
    errors = []
    for fp32_heads in (False, True):
        out = Bf16Field(_field(True, fp32_heads=fp32_heads).cuda())(xyz, t)
        assert all(o.dtype == torch.float32 for o in out)
        errors.append((out[2] - ref).abs().max().item())
    assert errors[0] > 2e-3 and errors[1] < errors[0] / 8, errors
