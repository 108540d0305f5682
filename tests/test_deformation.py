"""The deformation field's initialisation and its health check (CPU, no training)."""

from __future__ import annotations

import pytest
import torch

from garo_ns.deformation import DeformationField, field_health


def small_field(head_init: str = "default") -> DeformationField:
    torch.manual_seed(0)
    return DeformationField(pos_freqs=4, time_freqs=3, depth=4, width=32, skip=2, head_init=head_init)


def points(n: int = 512) -> torch.Tensor:
    return (torch.rand(n, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1) * 1.3


def test_head_inits():
    torch.manual_seed(0)
    zero, default = DeformationField(head_init="zero"), DeformationField()  # the recipe's size
    xyz = points()
    assert all(float(t.abs().max()) == 0 for t in zero(xyz, 0.3))
    offsets = default(xyz, 0.3)
    assert all(float(t.abs().max()) > 0 for t in offsets)
    # Small at the switch-on: a few hundredths of the unit cube, not a scrambled scene.
    assert float(offsets[0].norm(dim=-1).mean()) < 0.1
    with pytest.raises(ValueError, match="head_init"):
        DeformationField(head_init="ones")  # type: ignore[arg-type]


def test_hidden_matches_forward():
    field = small_field()
    xyz = points(64)
    hidden = field.hidden(xyz, 0.7)
    assert len(hidden) == 4 and all(h.shape == (64, 32) for h in hidden)
    torch.testing.assert_close(field.d_xyz(hidden[-1]), field(xyz, 0.7)[0])


@pytest.mark.parametrize(
    "shape", [dict(time_net=30), dict(time_net=0), dict(depth=2, skip=0, width=16), dict(depth=3, skip=5)]
)
def test_the_time_sampler_is_the_field_at_each_time(shape):
    """Sampling fixed positions at many times with the positions' share of the encoding's layers made once gives
    the field's offsets at each time, time-major, up to the order of the sums (fp32)."""
    torch.manual_seed(0)
    field = DeformationField(**shape)
    xyz, times = torch.randn(500, 3), torch.tensor([0.1, 0.5, 0.93])
    with torch.no_grad():
        got = field.time_sampler(xyz)(times)
        want = field(xyz.repeat(3, 1), times.repeat_interleave(500)[:, None])
    for a, b in zip(got, want):
        assert a.shape == b.shape
        assert float((a - b).abs().max()) <= 2e-6 * float(b.abs().max())


def test_health_of_a_live_field_and_of_a_collapsed_one():
    field = small_field()
    xyz, times = points(), torch.linspace(0, 1, 8)
    live = field_health(field, xyz, times)
    assert live["time_sensitivity"] > 1e-4
    assert len(live["dead_fraction"]) == 4 and max(live["dead_fraction"]) < 1.0
    with torch.no_grad():  # the collapse seen in training: every unit of the last layer dead
        field.layers[-1].bias.fill_(-1e3)
    dead = field_health(field, xyz, times)
    assert dead["dead_fraction"][-1] == 1.0
    assert dead["time_sensitivity"] < 1e-6  # rounding of the mean over times
    # Offsets are then the heads' biases alone: the same for every point and time.
    assert dead["mean_offset"] == pytest.approx(float(field.d_xyz.bias.norm()), rel=1e-5)


def test_time_independent_field_has_zero_sensitivity_but_live_units():
    field = small_field()
    with torch.no_grad():  # the time encoding's weights into the first layer removed
        field.layers[0].weight[:, -7:] = 0
        field.layers[3].weight[:, 27:34] = 0  # ... and after the skip: [x, h], time at 27:34 of x
    health = field_health(field, points(), torch.linspace(0, 1, 8))
    assert health["time_sensitivity"] < 1e-7
    assert max(health["dead_fraction"]) < 1.0


@pytest.mark.slow
def test_training_health_check_flags_a_collapse_once(garo_run, capsys):
    model = garo_run["trainer"].pipeline.model
    assert model.health_log, "the trained fixture's field was never checked"
    assert not any(h["collapsed"] for h in model.health_log)
    step = model.config.deform_warmup + 7 * model.config.health_every
    log, bias, trained_step = list(model.health_log), model.deformation.layers[-1].bias.detach().clone(), model.step
    try:
        model.step = step  # the check runs once the deformation is on
        with torch.no_grad():
            model.deformation.layers[-1].bias.fill_(-1e3)
        capsys.readouterr()
        model.check_health(step)
        model.check_health(step + model.config.health_every)
        assert [h["collapsed"] for h in model.health_log[-2:]] == [True, True]
        assert capsys.readouterr().out.count("has collapsed") == 1  # warned once
        model.check_health(step + 1)  # not a checking step
        assert len(model.health_log) == len(log) + 2
    finally:
        with torch.no_grad():
            model.deformation.layers[-1].bias.copy_(bias)
        model.health_log[:] = log
        model.step = trained_step  # the fixture is shared
