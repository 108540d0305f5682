"""The official D-3DGS scale composition (`deform_scale_offset linear`: the offset added to the activated scale)
against this project's (`log`), and every reader following it: composition, the static classification, the frame
path's static skip, the time table and a model's training step and render."""

from __future__ import annotations

import pytest
import torch

from garo_ns.deformation import SCALE_FLOOR, DeformationField, as_log_offsets, log_scale_offset
from garo_ns.render.frame import Canonical, FramePath, FrameSettings, activate, compose
from garo_ns.render.time_table import PAD, TableSpec, TimeTable, field_offsets
from garo_ns.static import classify


def test_log_offsets_pass_through_and_linear_ones_add_to_the_scale():
    g = torch.Generator().manual_seed(0)
    log_scales = torch.randn(200, 3, generator=g) - 3
    d = 0.02 * torch.randn(200, 3, generator=g)
    assert log_scale_offset(log_scales, d, "log") is d
    out = log_scale_offset(log_scales, d, "linear")
    want = (torch.exp(log_scales) + d).abs().clamp_min(SCALE_FLOOR)
    assert torch.allclose(torch.exp(log_scales + out), want, rtol=1e-5)
    assert (torch.exp(log_scales) + d < 0).any()  # some offsets overturn their scale: taken by magnitude
    with pytest.raises(ValueError, match="scale offset"):
        log_scale_offset(log_scales, d, "exp")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="log-scales"):  # a linear offset cannot be read without its scales
        as_log_offsets(torch.zeros(200, 10), None, "linear")


def test_an_offset_that_cancels_its_scale_leaves_the_floor_and_finite_gradients():
    log_scales = torch.full((4, 3), -2.0, requires_grad=True)
    d = (-torch.exp(log_scales.detach())).clone().requires_grad_(True)  # exactly zero scales
    out = log_scales + log_scale_offset(log_scales, d, "linear")
    assert torch.allclose(torch.exp(out), torch.full_like(out, SCALE_FLOOR), rtol=1e-4)
    out.sum().backward()
    assert torch.isfinite(log_scales.grad).all() and torch.isfinite(d.grad).all()


def _field_and_canonical(n=96, seed=1):
    g = torch.Generator().manual_seed(seed)
    field = DeformationField(pos_freqs=3, time_freqs=3, depth=2, width=32, skip=0).eval()
    with torch.no_grad():
        field.d_scale.weight.mul_(20.0)  # scale offsets as large as the scales: the two compositions part
    canonical = Canonical(
        torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g) - 3,
        torch.randn(n, 1, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, 15, 3, generator=g),
    )  # fmt: skip
    return field, canonical


def test_compose_follows_the_official_composition():
    field, canonical = _field_and_canonical()
    t = 0.4
    with torch.no_grad():
        d_scale = field(canonical.means, t)[2]
        linear = compose(field, canonical, t, "linear")[2]
        log = compose(field, canonical, t)[2]
    want = (torch.exp(canonical.log_scales) + d_scale).abs().clamp_min(SCALE_FLOOR)
    assert torch.allclose(torch.exp(linear), want, rtol=1e-5)
    assert torch.allclose(log, canonical.log_scales + d_scale)
    assert (linear - log).abs().max() > 0.05  # not the same model


def test_the_static_skip_frame_composes_as_the_model_does():
    field, canonical = _field_and_canonical()
    times = torch.linspace(0, 1, 5)
    static, offset = classify(field, canonical.means, canonical.log_scales, times, 1e-6, "linear")
    static = torch.zeros_like(static)  # every Gaussian through the MLP, by the static path's own composition
    static[:10] = True
    frame = FramePath()
    frame.scale_offset = "linear"
    with torch.no_grad():
        got = frame.splats(field, canonical, static, offset, 0.3, FrameSettings(static_skip=True), None)
        exact = activate(canonical, compose(field, canonical, 0.3, "linear"))
        frozen_scales = torch.exp(canonical.log_scales[:10] + offset[:10, 7:])
    assert torch.allclose(got.scales[10:], exact.scales[10:], rtol=1e-5)
    assert torch.allclose(got.scales[:10], frozen_scales, rtol=1e-5)
    # The classification's offsets are log-scale offsets: the mean over the times of the linear composition's.
    with torch.no_grad():
        logs = torch.stack([compose(field, canonical, float(t), "linear")[2] - canonical.log_scales for t in times])
    assert torch.allclose(offset[:, 7:], logs.mean(0), atol=1e-5)


def test_the_time_table_holds_log_scale_offsets_of_the_linear_composition():
    field, canonical = _field_and_canonical()
    scales = (canonical.log_scales, "linear")
    spec = TableSpec(0.0, 1.0, 12, precision="fp32", tolerance=1e-4)
    table = TimeTable.build(spec, field, canonical.means, scales=scales)
    assert table.network.numel() > 0  # a strict tolerance leaves some Gaussians to the network
    keys = table.spec.key_times()
    with torch.no_grad():
        for t in [float(keys[PAD + 2]), 0.37, 0.81]:
            ref = table.deformed(field, canonical, t)
            exact = compose(field, canonical, t, "linear")
            net = table.network
            assert torch.allclose(ref[2][net], exact[2][net], atol=1e-5)  # the network's rows: the composition's
            if t == float(keys[PAD + 2]):  # at a key: every row is the composition's
                assert torch.allclose(ref[2], exact[2], atol=1e-5)
    raw = field_offsets(field, canonical.means, [0.37])[0][:, 7:]
    converted = field_offsets(field, canonical.means, [0.37], scales=scales)[0][:, 7:]
    assert torch.allclose(converted, log_scale_offset(canonical.log_scales, raw, "linear"), atol=1e-6)


def test_a_model_with_linear_scale_offsets_trains_a_step_and_renders():
    from types import SimpleNamespace

    from test_training_step import _cameras, _model

    model = _model(deform_scale_offset="linear")
    assert model.frame.scale_offset == "linear"
    model.step_cb(SimpleNamespace(optimizers={}), 1)
    cam = _cameras([30.0, 30.0, 30.0])[0:1]
    model.train()
    out = model.get_outputs(cam)
    out["rgb"].mean().backward()
    assert model.deformation.d_scale.weight.grad is not None
    assert torch.isfinite(model.deformation.d_scale.weight.grad).all()
    model.eval()
    with torch.no_grad():
        splats = model.gaussians_at(0.5, exact=True)
        want = activate(model.canonical(), compose(model.deformation, model.canonical(), 0.5, "linear"))
    assert torch.allclose(splats.scales, want.scales)


def test_an_unknown_scale_offset_is_refused_before_training():
    from test_training_step import _model

    with pytest.raises(ValueError, match="deform_scale_offset"):
        _model(deform_scale_offset="exp")


def test_a_checkpoint_composes_its_scales_as_it_was_trained_whatever_the_config_says(capsys):
    """garo-deform's default went from `log` to `linear`: a run trained with `log` and resumed or imported under the
    new default must keep `log`, or every Gaussian's size changes (an offset of 0.2 is x1.22 on the log-scale and
    +0.2 added to the scale)."""
    from test_training_step import _model

    from garo_ns.errors import GaroInputError

    trained = _model(deform_scale_offset="log")
    with torch.no_grad():  # offsets large enough that the two compositions give other sizes
        trained.deformation.d_scale.bias.fill_(0.2)
    trained.eval()
    state = trained.state_dict()
    assert state["_extra_state"]["scale_offset"] == "log"
    loaded = _model(deform_scale_offset="linear")
    loaded.eval()
    loaded.load_state_dict(state)
    assert loaded.config.deform_scale_offset == "log" and loaded.frame.scale_offset == "log"
    assert "trained with deform_scale_offset 'log'" in capsys.readouterr().out
    with torch.no_grad():
        want = trained.gaussians_at(0.5, exact=True).scales
        assert torch.equal(loaded.gaussians_at(0.5, exact=True).scales, want)
        as_config_says = activate(loaded.canonical(), compose(loaded.deformation, loaded.canonical(), 0.5, "linear"))
        assert not torch.allclose(as_config_says.scales, want)  # what the guard prevents is a real change
    # A checkpoint from before the record: the config's composition (its run's config.yml names it).
    del state["_extra_state"]["scale_offset"]
    older = _model(deform_scale_offset="linear")
    older.load_state_dict(state)
    assert older.config.deform_scale_offset == "linear" and older.frame.scale_offset == "linear"
    state["_extra_state"]["scale_offset"] = "exp"
    with pytest.raises(GaroInputError, match="deform_scale_offset 'exp'"):
        _model().load_state_dict(state)
