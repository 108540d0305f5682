"""Default render switches: fast for a finished model, plain while training, flags override."""

import math

import pytest
import torch

from garo_ns.render.frame import FrameSettings
from garo_ns.render.switches import measure_on_views, replay, resolve, worst_psnr_loss

AUTO = {"render_precision": None, "static_skip": None, "cuda_graph": None, "lean_raster": None}


def losses(**table):
    """A measure that returns the loss of the first listed switch that the trial turns on."""
    calls = []

    def measure(trial: FrameSettings) -> float:
        calls.append(trial)
        if trial.render_precision != "fp32":
            return table.get(trial.render_precision, math.inf)  # a precision not listed: too lossy
        return table["static_skip"] if trial.static_skip else 0.0

    return measure, calls


def test_training_run_keeps_every_auto_switch_off_even_on_cuda():
    measure, calls = losses(static_skip=0.0, tf32=0.0)
    settings, tried = resolve(AUTO, training_run=True, cuda=True, measure=measure)
    assert settings == FrameSettings()
    assert calls == [] and tried == {}


def test_finished_model_on_cuda_gets_the_exact_switches_and_the_approximate_ones_within_the_bound():
    measure, calls = losses(static_skip=0.005, tf32=0.01)
    settings, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure)
    assert settings.cuda_graph and settings.lean_raster
    assert settings.static_skip and settings.render_precision == "tf32"
    assert tried == {"static_skip": 0.005, "render_precision=fp16": math.inf, "render_precision=tf32": 0.01}
    # tf32 was measured on top of the static skip already accepted.
    assert calls[-1].static_skip and calls[-1].render_precision == "tf32"


def test_a_switch_that_costs_more_than_the_bound_stays_off():
    measure, _ = losses(static_skip=0.5, tf32=float("nan"))
    settings, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure, bound_db=0.02)
    assert not settings.static_skip and settings.render_precision == "fp32"
    assert set(tried) == {"static_skip", "render_precision=fp16", "render_precision=tf32"}


def test_precisions_are_tried_fastest_first_and_the_first_within_the_bound_wins():
    measure, calls = losses(static_skip=1.0, bf16=0.3, tf32=0.001)
    settings, _ = resolve(AUTO, training_run=False, cuda=True, measure=measure, precisions=("bf16", "tf32"))
    assert settings.render_precision == "tf32"
    assert [c.render_precision for c in calls] == ["fp32", "bf16", "tf32"]


def test_on_cpu_no_cuda_switch_and_no_reduced_precision():
    measure, calls = losses(static_skip=0.0, tf32=0.0)
    settings, _ = resolve(AUTO, training_run=False, cuda=False, measure=measure)
    assert not settings.cuda_graph and not settings.lean_raster and settings.render_precision == "fp32"
    assert settings.static_skip  # exact enough on training views, and it runs on a CPU
    assert all(c.render_precision == "fp32" for c in calls)


def test_explicit_flags_override_in_both_directions():
    requested = dict(AUTO, cuda_graph=False, static_skip=False, render_precision="bf16", lean_raster=True)
    measure, calls = losses(static_skip=0.0, tf32=0.0)
    finished, tried = resolve(requested, training_run=False, cuda=True, measure=measure)
    assert (finished.cuda_graph, finished.lean_raster, finished.static_skip) == (False, True, False)
    assert finished.render_precision == "bf16" and calls == [] and tried == {}
    training, _ = resolve(requested, training_run=True, cuda=True, measure=measure)
    assert training.lean_raster and training.render_precision == "bf16"


def test_without_a_measure_the_approximate_switches_stay_off():
    settings, tried = resolve(AUTO, training_run=False, cuda=True)
    assert settings.cuda_graph and not settings.static_skip and settings.render_precision == "fp32"
    assert tried == {}


@pytest.mark.parametrize("bound", [-0.1, float("nan"), float("inf")])
def test_bad_bound_is_a_clear_error(bound):
    with pytest.raises(ValueError, match="bound"):
        resolve(AUTO, training_run=False, cuda=True, bound_db=bound)


def test_unknown_switch_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown render switches"):
        resolve(dict(AUTO, cuda_graphs=True), training_run=False, cuda=True)


def test_worst_psnr_loss_is_the_largest_loss_over_views():
    torch.manual_seed(0)
    targets = torch.rand(3, 8, 8, 3)
    reference = targets + 0.01  # MSE 1e-4 on every view
    trial = reference.clone()
    trial[1] = targets[1] + 0.02  # MSE 4e-4 on view 1: 10 log10(4) dB worse
    assert worst_psnr_loss(reference, trial, targets) == pytest.approx(10 * math.log10(4), rel=1e-4)
    assert worst_psnr_loss(reference, reference, targets) == pytest.approx(0.0, abs=1e-6)
    better = targets.clone()
    assert worst_psnr_loss(reference, better, targets) < 0
    trial[2, 0, 0, 0] = float("nan")
    assert worst_psnr_loss(reference, trial, targets) == math.inf


def test_a_loss_equal_to_the_bound_is_within_it():
    measure, _ = losses(static_skip=0.02, tf32=0.0201)
    settings, _ = resolve(AUTO, training_run=False, cuda=True, measure=measure, bound_db=0.02)
    assert settings.static_skip and settings.render_precision == "fp32"


def test_replay_of_recorded_losses_gives_the_same_decision_and_unmeasured_trials_stay_off():
    measure, _ = losses(static_skip=0.001, fp16=0.5, tf32=0.004)
    first, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure)
    again, _ = resolve(AUTO, training_run=False, cuda=True, measure=replay(tried))
    assert again == first and first.render_precision == "tf32" and first.static_skip
    # Recorded on a CPU (no precision measured): on CUDA the precision stays fp32.
    cpu_only = {"static_skip": 0.0}
    later, _ = resolve(AUTO, training_run=False, cuda=True, measure=replay(cpu_only))
    assert later.static_skip and later.render_precision == "fp32" and later.cuda_graph


def test_measure_on_views_compares_each_trial_with_the_plain_renders():
    torch.manual_seed(1)
    targets = [torch.rand(4, 4, 3) for _ in range(2)]
    noise = {None: 0.01, True: 0.01, False: 0.03}  # static_skip on: as plain; precision trial: worse

    def render(i, trial):
        key = None if trial is None else trial.render_precision == "fp32"
        return targets[i] + noise[key]

    measure = measure_on_views(render, targets)
    assert measure(FrameSettings(static_skip=True)) == pytest.approx(0.0, abs=1e-6)
    assert measure(FrameSettings(render_precision="tf32")) == pytest.approx(10 * math.log10(9), rel=1e-4)
