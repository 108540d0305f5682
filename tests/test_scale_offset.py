"""The official D-3DGS scale composition (`deform_scale_offset linear`: the offset added to the activated scale)
against this project's (`log`), and every reader following it: composition, the static classification, the frame
path's static skip, the time table and a model's training step and render."""

from __future__ import annotations

import math

import pytest
import torch

from garo_ns.deformation import SCALE_FLOOR, DeformationField, as_log_offsets, log_scale_offset
from garo_ns.render.frame import Canonical, FramePath, FrameSettings, activate, compose, rows_splats, table_rows
from garo_ns.render.static import classify
from garo_ns.render.time_table import PAD, TableSpec, TimeTable


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


class Breathing:
    """Scale offsets alone, d = a sin(2 pi t + phase) per Gaussian and axis, for the Gaussian whose canonical x is
    its index: amplitudes up to twice the scale, so that under `linear` many offsets cancel their scale at times."""

    def __init__(self, amp, phase):
        self.amp, self.phase = amp, phase

    def __call__(self, xyz, t):
        i = xyz[:, 0].long()
        t = torch.as_tensor(t, dtype=torch.float32).reshape(-1, 1)
        d = self.amp[i] * torch.sin(2 * math.pi * t + self.phase[i])
        return torch.zeros(xyz.shape[0], 3), torch.zeros(xyz.shape[0], 4), d


def _breathing(n=64):
    g = torch.Generator().manual_seed(0)
    log_scales = torch.randn(n, 3, generator=g) - 4
    field = Breathing(torch.exp(log_scales) * 2 * torch.rand(n, 3, generator=g), 6 * torch.rand(n, 3, generator=g))
    xyz = torch.stack([torch.arange(n).float(), torch.zeros(n), torch.zeros(n)], dim=-1)
    canonical = Canonical(
        xyz, torch.randn(n, 4, generator=g), log_scales, torch.randn(n, 1, generator=g), torch.randn(n, 3, generator=g),
        torch.randn(n, 15, 3, generator=g),
    )  # fmt: skip
    return field, canonical


@pytest.mark.parametrize("precision", ["fp32", "int16"])
def test_the_time_table_interpolates_the_linear_compositions_own_offsets_and_judges_scales_in_scene_units(precision):
    """Under `linear` the table holds the field's scale offsets as they come and a frame adds them to the scales:
    interpolated as log-scale offsets they bend where an offset cancels a small Gaussian's scale (log |s + d|
    falls to the floor and back), and 72 to 90% of 40k models' Gaussians stayed on the network."""
    field, canonical = _breathing()
    spec = TableSpec(0.0, 1.0, 60, precision=precision, tolerance=1e-4, extent=2.0)
    table = TimeTable.build(spec, field, canonical.means, scale_offset="linear")
    assert table.network.numel() == 0  # every Gaussian tabled
    keys = table.spec.key_times()
    raw = field(canonical.means, float(keys[PAD + 3]))[2]
    step = 0.0 if table.codec.scale is None else 0.5 * table.codec.scale[:, 7:]  # int16's rounding
    assert ((table.offsets_at(float(keys[PAD + 3]))[:, 7:] - raw).abs() <= step + 1e-6).all()  # the field's own
    rows, network_rows, opacities, colors = table_rows(canonical, table)
    halfway = [float(keys[PAD - 1 + p]) + 0.5 * table.spec.spacing for p in range(spec.intervals + 1)]
    scene_err, log_err = 0.0, 0.0
    with torch.no_grad():
        for t in halfway + [float(keys[PAD + 3]), 0.0, 1.0]:
            frame = rows_splats(table.frame_rows(rows, network_rows, field, canonical.means, t), opacities, colors,
                                "linear")  # fmt: skip
            reference = activate(canonical, table.deformed(field, canonical, t))
            exact = activate(canonical, compose(field, canonical, t, "linear")).scales
            assert torch.allclose(frame.scales, reference.scales, rtol=1e-5, atol=1e-7), t
            scene_err = max(scene_err, float((frame.scales - exact).abs().max()))
            log_err = max(log_err, float((frame.scales.log() - exact.log()).abs().max()))
    assert scene_err <= spec.tolerance * table.spec.extent  # the build's promise, in scene units
    assert log_err > 100 * spec.tolerance  # what a log-scale measure would have sent to the network
    # A table of linear keys with every Gaussian tabled: the frame's CUDA-graph path (`rows_at`) reads it alike.
    linear = TimeTable.build(TableSpec(0.0, 1.0, 60, precision=precision, tolerance=1e-3), field, canonical.means,
                             scale_offset="linear")  # fmt: skip
    assert linear.graphable
    rows, network_rows, opacities, colors = table_rows(canonical, linear)
    for t in torch.linspace(-0.05, 1.05, 37).tolist():
        want = linear.frame_rows(rows, network_rows, field, canonical.means, t)
        assert torch.allclose(linear.rows_at(rows, torch.tensor(t)), want, rtol=1e-5, atol=1e-7), t
    # A strict tolerance leaves some Gaussians to the network: theirs are the composition's own scales.
    strict = TimeTable.build(TableSpec(0.0, 1.0, 12, precision=precision, tolerance=1e-4), field, canonical.means,
                             scale_offset="linear")  # fmt: skip
    assert 0 < strict.network.numel() < canonical.means.shape[0]
    rows, network_rows, opacities, colors = table_rows(canonical, strict)
    with torch.no_grad():
        got = rows_splats(strict.frame_rows(rows, network_rows, field, canonical.means, 0.37), opacities, colors,
                          "linear").scales  # fmt: skip
        exact = activate(canonical, compose(field, canonical, 0.37, "linear")).scales
    assert torch.allclose(got[strict.network], exact[strict.network], rtol=1e-5)
    with pytest.raises(ValueError, match="scale offset"):
        TimeTable.build(spec, field, canonical.means, scale_offset="exp")  # type: ignore[arg-type]


def test_a_models_time_table_renders_its_linear_scales():
    """The frame path builds the table with the model's composition and renders its scales."""
    field, canonical = _field_and_canonical()
    frame = FramePath()
    frame.scale_offset = "linear"
    spec = TableSpec(0.0, 1.0, 40, precision="int16", tolerance=1e-1)
    with torch.no_grad():
        got = frame.splats(field, canonical, None, None, 0.43, FrameSettings(time_table=True), spec)
        exact = activate(canonical, compose(field, canonical, 0.43, "linear"))
        table = frame.table
        assert table is not None and table.scale_offset == "linear"
        reference = activate(canonical, table.deformed(field, canonical, 0.43))
    assert torch.allclose(got.scales, reference.scales, rtol=1e-5, atol=1e-7)
    assert (got.scales - exact.scales).abs().max() <= spec.tolerance * spec.extent


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
