"""Default render switches: fast for a finished model, plain while training, flags override."""

import hashlib
import math
from dataclasses import dataclass

import pytest
import torch
import yaml

from garo_ns.render.frame import FrameSettings
from garo_ns.render.switches import (
    APPROXIMATE,
    MEASURE_VERSION,
    TABLE,
    RenderSettings,
    SwitchDecision,
    measure_on_views,
    replay,
    resolve,
    rung_name,
    table_ladder,
    trimmed_rung,
    view_change_db,
    worst_view_change_db,
)
from garo_ns.render.time_table import TableSpec, build_bytes

AUTO = {"static_skip": None, "cuda_graph": None, "lean_raster": None, "time_table": None}


def losses(**table):
    """A measure that returns the loss of the first listed switch that the trial turns on."""
    calls = []

    def measure(trial: FrameSettings) -> float:
        calls.append(trial)
        if trial.time_table:
            return table.get("time_table", math.inf)  # not listed: no table for this model
        return table["static_skip"] if trial.static_skip else 0.0

    return measure, calls


def test_training_run_keeps_every_auto_switch_off_even_on_cuda():
    measure, calls = losses(static_skip=0.0, time_table=0.0)
    settings, tried = resolve(AUTO, training_run=True, cuda=True, measure=measure)
    assert settings == FrameSettings()
    assert calls == [] and tried == {}


def test_finished_model_on_cuda_gets_the_exact_switches_and_the_static_skip_within_the_bound():
    measure, calls = losses(static_skip=0.005)
    settings, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure)
    assert settings.cuda_graph and settings.lean_raster and settings.static_skip
    assert tried == {APPROXIMATE: 0.005, TABLE: math.inf}
    assert not settings.time_table and len(calls) == 2 and calls[0].static_skip and not calls[0].time_table
    assert calls[1].time_table and not calls[1].static_skip  # the table measured alone


def test_a_switch_that_costs_more_than_the_bound_stays_off():
    for loss in (0.5, float("nan")):
        measure, _ = losses(static_skip=loss)
        settings, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure, bound_db=0.02)
        assert not settings.static_skip and not settings.time_table
        assert set(tried) == {APPROXIMATE, TABLE}


def test_render_precision_is_no_switch_and_an_old_records_precisions_decide_nothing():
    """The MLP renders in fp32 only (fp16 was deleted with its setting: benchmarks/HISTORY.md): a precision asked
    of `resolve` is an unknown switch, and a record that measured precisions lossless decides as one without."""
    assert "render_precision" not in FrameSettings.__dataclass_fields__
    with pytest.raises(ValueError, match="unknown render switches"):
        resolve(dict(AUTO, render_precision="fp16"), training_run=False, cuda=True)
    record = {"static_skip": 0.0, "render_precision=fp16": 0.0, "render_precision=tf32": 0.0}
    with_precisions = resolve(AUTO, training_run=False, cuda=True, measure=replay(record))[0]
    assert with_precisions == resolve(AUTO, training_run=False, cuda=True, measure=replay({"static_skip": 0.0}))[0]
    assert with_precisions.static_skip and with_precisions.cuda_graph


def test_on_cpu_no_cuda_switch():
    measure, calls = losses(static_skip=0.0)
    settings, _ = resolve(AUTO, training_run=False, cuda=False, measure=measure)
    assert not settings.cuda_graph and not settings.lean_raster
    assert settings.static_skip  # exact enough on training views, and it runs on a CPU
    assert calls and not any(c.cuda_graph or c.lean_raster for c in calls)


def test_explicit_flags_override_in_both_directions():
    requested = dict(AUTO, cuda_graph=False, static_skip=False, lean_raster=True)
    requested["time_table"] = False
    measure, calls = losses(static_skip=0.0, time_table=0.0)
    finished, tried = resolve(requested, training_run=False, cuda=True, measure=measure)
    assert (finished.cuda_graph, finished.lean_raster, finished.static_skip) == (False, True, False)
    assert not finished.time_table and calls == [] and tried == {}
    training, _ = resolve(requested, training_run=True, cuda=True, measure=measure)
    assert training.lean_raster and not training.cuda_graph


def test_without_a_measure_the_approximate_switches_stay_off():
    settings, tried = resolve(AUTO, training_run=False, cuda=True)
    assert settings.cuda_graph and not settings.static_skip and not settings.time_table
    assert tried == {}


@pytest.mark.parametrize("bound", [-0.1, float("nan"), float("inf")])
def test_bad_bound_is_a_clear_error(bound):
    with pytest.raises(ValueError, match="bound"):
        resolve(AUTO, training_run=False, cuda=True, bound_db=bound)


def test_unknown_switch_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown render switches"):
        resolve(dict(AUTO, cuda_graphs=True), training_run=False, cuda=True)


def test_worst_view_change_is_the_largest_change_over_views_in_either_direction():
    torch.manual_seed(0)
    targets = torch.rand(3, 8, 8, 3)
    reference = targets + 0.01  # MSE 1e-4 on every view
    trial = reference.clone()
    trial[1] = targets[1] + 0.02  # MSE 4e-4 on view 1: 10 log10(4) dB worse (and as far from the plain render)
    assert worst_view_change_db(reference, trial, targets) == pytest.approx(10 * math.log10(4), rel=1e-4)
    assert worst_view_change_db(reference, reference, targets) == pytest.approx(0.0, abs=1e-6)
    # A render closer to the ground truth than the plain one changed the view too: no negative "loss".
    better = reference.clone()
    better[0] = targets[0] + 0.005  # MSE 2.5e-5: 6 dB better, pixels 0.005 from the plain render
    assert worst_view_change_db(reference, better, targets) == pytest.approx(10 * math.log10(4), rel=1e-4)
    trial[2, 0, 0, 0] = float("nan")
    assert worst_view_change_db(reference, trial, targets) == math.inf


def test_the_bound_catches_pixels_that_change_while_the_error_stays_the_same():
    """A trial whose error against the ground truth equals the plain render's (here: the error's sign
    flipped on half the pixels) scores the same PSNR, but its pixels moved: the change is caught."""
    torch.manual_seed(2)
    targets = torch.rand(2, 8, 8, 3) * 0.5 + 0.25
    reference = targets + 0.01
    flip = torch.ones_like(targets)
    flip[:, :, :4] = -1
    trial = targets + 0.01 * flip
    mse = lambda a: ((a - targets) ** 2).mean(dim=(1, 2, 3))  # noqa: E731
    assert torch.allclose(mse(trial), mse(reference))  # the same error against the ground truth
    change = view_change_db(reference, trial, targets)
    # Half the pixels moved by 0.02: MSE(trial, plain) = 2e-4 = 2 x the plain error, 10 log10(3) dB.
    assert torch.allclose(change, torch.full((2,), 10 * math.log10(3)), rtol=1e-4)
    # Through `resolve`: a static skip rendering these pixels stays off.
    measure = measure_on_views(lambda i, switches: reference[i] if switches is None else trial[i], list(targets))
    settings, tried = resolve(AUTO, training_run=False, cuda=False, measure=measure)
    assert not settings.static_skip and tried["static_skip"] > 0.02


def test_a_loss_equal_to_the_bound_is_within_it():
    measure, _ = losses(static_skip=0.02)
    assert resolve(AUTO, training_run=False, cuda=True, measure=measure, bound_db=0.02)[0].static_skip
    measure, _ = losses(static_skip=0.0201)
    assert not resolve(AUTO, training_run=False, cuda=True, measure=measure, bound_db=0.02)[0].static_skip


def test_replay_of_recorded_losses_gives_the_same_decision_and_unmeasured_trials_stay_off():
    measure, _ = losses(static_skip=0.001)
    first, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure)
    again, _ = resolve(AUTO, training_run=False, cuda=True, measure=replay(tried))
    assert again == first and first.static_skip and first.cuda_graph
    # A record without the static skip's measurement: it stays off.
    later, _ = resolve(AUTO, training_run=False, cuda=True, measure=replay({}))
    assert not later.static_skip and not later.time_table and later.cuda_graph


def test_measure_on_views_compares_each_trial_with_the_plain_renders():
    torch.manual_seed(1)
    targets = [torch.rand(4, 4, 3) for _ in range(2)]
    noise = {None: 0.01, True: 0.01, False: 0.03}  # static_skip on: as plain; table trial: worse

    def render(i, trial):
        key = None if trial is None else not trial.time_table
        return targets[i] + noise[key]

    measure = measure_on_views(render, targets)
    assert measure(FrameSettings(static_skip=True)) == pytest.approx(0.0, abs=1e-6)
    # 0.03 against 0.01 off the ground truth: 10 log10(9) dB worse, pixels 0.02 from the plain render
    # (10 log10(1 + 4) dB on the plain error's scale): the larger counts.
    assert measure(FrameSettings(time_table=True)) == pytest.approx(10 * math.log10(9), rel=1e-4)


def test_the_line_on_load_names_the_switches_and_each_measured_change():
    decision = SwitchDecision()
    config = RenderSettings()
    cpu = torch.device("cpu")
    assert "none measured" in decision.line(config, False, cpu)
    decision.record = {"step": 99, "views": 32, "tried": {"static_skip": 0.004}, "measure": MEASURE_VERSION}
    line = decision.line(config, False, cpu)
    assert line.startswith("Render switches: static_skip") and "static_skip" in line.split(";")[0]  # in use
    assert "render_precision" not in line
    assert "static_skip 0.0040 dB" in line and "32 training views at step 99" in line and "bound 0.02 dB" in line
    summary = decision.summary(config, False, cpu)
    assert summary["in_use"]["static_skip"] and summary["measured_db"] == {"static_skip": 0.004}
    assert summary["measured_views"] == 32 and summary["bound_db"] == 0.02
    # A record of the older one-sided check is not trusted: the switches it allowed stay off.
    decision.record = {"step": 99, "views": 16, "tried": {"static_skip": -0.5}}
    assert not decision.settings(config, False, cpu).static_skip
    assert "older one-sided check" in decision.line(config, False, cpu)
    assert decision.summary(config, False, cpu)["untrusted_record"]


def _old_config_model(render_precision):
    """A model set up from a config.yml written while `render_precision` was a setting, naming this value."""
    from nerfstudio.data.scene_box import SceneBox

    from garo_ns.garo_model import GaroModelConfig

    config = GaroModelConfig(num_random=50, deform_width=16, deform_depth=2, deform_skip=0)
    config.render_precision = render_precision  # as a config.yml written before the deletion holds it
    config = yaml.load(yaml.dump(config), Loader=yaml.Loader)
    assert config.render_precision == render_precision  # the old file's value reaches the loaded config
    box = SceneBox(torch.tensor([[-1.5] * 3, [1.5] * 3]))
    return config.setup(scene_box=box, num_train_data=1, metadata={"camera_extent": 4.0})


@pytest.mark.parametrize("deleted", ["bf16", "fp16-fused", "tf32", "fp16"])
def test_an_old_config_naming_a_deleted_precision_loads_with_a_warning_and_renders_exactly(deleted, capsys):
    model = _old_config_model(deleted)
    assert not hasattr(model.config, "render_precision")  # dropped: nothing reads it
    assert "render_precision" not in yaml.dump(model.config)  # nor writes it back
    out = capsys.readouterr().out
    assert out.count("was deleted") == 1
    assert f"render_precision={deleted} was deleted (benchmarks/HISTORY.md)" in out and "exact fp32" in out
    assert model.render_settings() == FrameSettings()  # a CPU, no record: the plain fp32 path


def test_an_old_config_with_the_deleted_tile_lists_setting_loads_and_says_so_only_if_it_was_on(capsys):
    from nerfstudio.data.scene_box import SceneBox

    from garo_ns.garo_model import GaroModelConfig

    box = SceneBox(torch.tensor([[-1.5] * 3, [1.5] * 3]))
    for on in (True, False):
        config = GaroModelConfig(num_random=50, deform_width=16, deform_depth=2, deform_skip=0)
        config.train_tiles_without_wait = on  # as a config.yml written while it was a setting holds it
        config = yaml.load(yaml.dump(config), Loader=yaml.Loader)
        model = config.setup(scene_box=box, num_train_data=1, metadata={"camera_extent": 4.0})
        assert not hasattr(model.config, "train_tiles_without_wait")
        out = capsys.readouterr().out
        if on:
            assert "train_tiles_without_wait=True was deleted (benchmarks/HISTORY.md)" in out and "isect_tiles" in out
        else:
            assert "train_tiles_without_wait" not in out


@pytest.mark.parametrize("value", ["fp32", None])
def test_an_old_config_naming_fp32_or_auto_loads_silently(value, capsys):
    model = _old_config_model(value)
    assert not hasattr(model.config, "render_precision")
    assert "render_precision" not in capsys.readouterr().out


def test_an_old_record_naming_tf32_loads_and_renders_fp32(monkeypatch):
    """A checkpoint measured while MLP precisions were switches (since deleted) holds their changes, within the
    bound: the loaded model renders fp32 with the other switches it allows, and reports only the change of a
    switch that decides something."""
    monkeypatch.setattr(RenderSettings, "renders_on_cuda", lambda self, device: True)  # as on a GPU
    decision, config, device = SwitchDecision(), RenderSettings(), torch.device("cpu")
    tried = {"static_skip": 0.004, "render_precision=fp16": 0.003, "render_precision=tf32": 0.002}
    decision.record = {"step": 39999, "views": 32, "tried": tried, "measure": MEASURE_VERSION}
    settings = decision.settings(config, False, device)
    assert settings.static_skip and settings.cuda_graph
    line = decision.line(config, False, device)
    assert line.startswith("Render switches: static_skip") and "static_skip 0.0040 dB" in line
    assert "tf32" not in line and "fp16" not in line
    assert decision.summary(config, False, device)["measured_db"] == {"static_skip": 0.004}


def test_the_table_is_chosen_within_the_bound_and_replayed_from_the_record():
    measure, calls = losses(static_skip=0.5, time_table=0.01)
    settings, tried = resolve(AUTO, training_run=False, cuda=True, measure=measure)
    assert settings.time_table and not settings.static_skip and tried[TABLE] == 0.01
    assert resolve(AUTO, training_run=False, cuda=True, measure=replay(tried))[0] == settings
    over, _ = resolve(AUTO, training_run=False, cuda=True, measure=losses(static_skip=0.5, time_table=0.03)[0])
    assert not over.time_table
    # Set explicitly, it is not measured.
    forced, tried = resolve(dict(AUTO, time_table=True), training_run=False, cuda=True, measure=measure)
    assert forced.time_table and TABLE not in tried


def _record(step, table_mb=10.0):
    spec = {"t_lo": 0.0, "t_hi": 1.0, "intervals": 8, "anchor_every": 16}
    info = {"keys": 12, "mb": table_mb, "network": 3, "gaussians": 100, "spec": dict(spec, order="linear")}
    return {
        "step": step,
        "views": 32,
        "tried": {"static_skip": 0.5, TABLE: 0.004},
        "measure": MEASURE_VERSION,
        TABLE: {"spec": spec, "info": info},
    }


def test_a_record_of_another_step_is_not_trusted():
    step = {"now": 99}
    decision = SwitchDecision(lambda: step["now"])
    config, cpu = RenderSettings(), torch.device("cpu")
    decision.record = _record(99)
    assert decision.settings(config, False, cpu).time_table and decision.table_spec().intervals == 8
    line = decision.line(config, False, cpu)
    assert "time_table (12 keys, linear, 10 MB, 3 of 100 Gaussians on the network)" in line
    assert "time_table 0.0040 dB" in line
    step["now"] = 2000  # a resumed run went on training: the record describes an earlier model
    assert not decision.settings(config, False, cpu).time_table and decision.table_spec() is None
    assert "measured at step 99, the model is at step 2000" in decision.line(config, False, cpu)


def test_a_recorded_table_over_the_memory_budget_is_not_used_and_says_why():
    decision = SwitchDecision(lambda: 99)
    decision.record = _record(99, table_mb=3000.0)
    config, cpu = RenderSettings(time_table_budget_mb=2048), torch.device("cpu")
    assert not decision.settings(config, False, cpu).time_table
    assert "3000 MB exceed time_table_budget_mb 2048" in decision.line(config, False, cpu)
    assert decision.settings(RenderSettings(time_table_budget_mb=4096), False, cpu).time_table


def test_a_recorded_table_from_before_the_anchors_is_not_used_and_says_why():
    decision = SwitchDecision(lambda: 99)
    decision.record = _record(99)
    del decision.record[TABLE]["spec"]["anchor_every"]  # measured with whole int16 residuals: another table
    config, cpu = RenderSettings(), torch.device("cpu")
    assert not decision.settings(config, False, cpu).time_table
    assert "table layout before anchors" in decision.line(config, False, cpu)


def test_a_linear_models_table_measured_before_tables_held_its_own_scale_offsets_is_not_used_and_says_why():
    """Such a table held the offsets made log-scale offsets and left most Gaussians to the network: a load builds
    another table now. A table recorded with its composition, or a `log` model's, is used."""

    @dataclass
    class LinearSettings(RenderSettings):
        deform_scale_offset: str = "linear"

    decision = SwitchDecision(lambda: 99)
    decision.record = _record(99)
    cpu = torch.device("cpu")
    assert decision.settings(RenderSettings(), False, cpu).time_table  # `log`: the table it measured
    assert not decision.settings(LinearSettings(), False, cpu).time_table
    assert "linear scale offsets as log-scale offsets" in decision.line(LinearSettings(), False, cpu)
    decision.record = _record(99)
    decision.record[TABLE]["info"]["scale_offset"] = "linear"  # written by a build that holds them as they are
    assert decision.settings(LinearSettings(), False, cpu).time_table


class LadderModel:
    """What `table_ladder` reads of a model: its training times, its count of Gaussians and its scene extent."""

    def __init__(self, frames=200, gaussians=34_000):
        self.train_times = torch.linspace(0, 1, frames)
        self.num_points = gaussians
        self.scene_extent = 5.0


def test_the_ladder_goes_on_in_int8_only_where_the_budget_caps_int16():
    model = LadderModel()
    # A budget that holds every int16 rung: 2, 4, ..., 64 keys per frame, no int8.
    roomy = table_ladder(model, RenderSettings(time_table_budget_mb=1e6))[0]
    assert [s.intervals for s in roomy] == [k * 199 for k in (2, 4, 8, 16, 32, 64)]
    assert {s.precision for s in roomy} == {"int16"}
    # 6 GB at 60k Gaussians caps int16 below 32 keys per frame: int8 rungs follow, up to about 1.8x the keys.
    config, model = RenderSettings(), LadderModel(gaussians=60_000)
    capped = table_ladder(model, config)[0]
    int16 = [s for s in capped if s.precision == "int16"]
    int8 = [s for s in capped if s.precision == "int8"]
    assert int16 and int8 and capped == int16 + int8
    assert int16[-1].intervals < 32 * 199 and 1.7 * int16[-1].intervals < int8[-1].intervals < 64 * 199
    assert all(a.intervals < b.intervals for a, b in zip(capped, capped[1:]))  # sparsest first
    for spec in capped:  # every rung's build within the budget (the table and the copies its build makes)
        assert build_bytes(spec.intervals, model.num_points, spec.precision) <= config.time_table_budget_mb * 2**20
    assert rung_name(int16[-1], config) == str(int16[-1].intervals)
    assert rung_name(int8[0], config) == f"{int8[0].intervals} int8"
    # 34k Gaussians: int16 capped at 4202 intervals (a build of 4202 int16 keys holds about 5.6 GB), int8 follows.
    last_three = table_ladder(LadderModel(), config)[0][-3:]
    assert [(s.precision, s.intervals) for s in last_three] == [("int16", 4202), ("int8", 32 * 199), ("int8", 7565)]
    # Turned off, or another precision asked for: no int8 rungs.
    assert table_ladder(model, RenderSettings(time_table_try_int8=False))[0] == int16
    assert {s.precision for s in table_ladder(model, RenderSettings(time_table_precision="fp16"))[0]} == {"fp16"}
    # No budget for any table: none, and why.
    specs, why = table_ladder(model, RenderSettings(time_table_budget_mb=1e-3))
    assert specs == [] and "memory budget" in why


def test_a_trimmed_rung_aims_at_the_margin_by_the_fit_through_its_two_neighbours():
    """Standup's fp32 rungs: 2384 intervals changed the training views by 0.0125 dB, over the 0.01 margin, and the next
    rung, 4350, by 0.0034. The fit through the two asks for about 2,900 intervals to reach 0.8 of the margin."""
    over, within = TableSpec(0.0, 1.0, 2384), TableSpec(0.0, 1.0, 4350)
    trim = trimmed_rung(over, 0.0125, within, 0.0034, margin=0.01)
    assert trim is not None and trim == TableSpec(0.0, 1.0, trim.intervals)  # only the intervals change
    slope = math.log(0.0125 / 0.0034) / math.log(4350 / 2384)
    fitted = 0.0125 * (2384 / trim.intervals) ** slope  # the fit's change at the trimmed rung
    assert fitted == pytest.approx(0.008, rel=1e-3) and 2384 < trim.intervals <= 4350 * 5 / 6
    assert trimmed_rung(over, 0.0125, within, 0.0034, margin=0.004) is None  # the fit asks for more than 4350
    # No trim where the two do not bracket the margin, where the saving is under a sixth, across precisions, or
    # where the denser rung changed nothing (no slope to fit).
    assert trimmed_rung(over, 0.009, within, 0.0034, margin=0.01) is None
    assert trimmed_rung(over, 0.0125, within, 0.011, margin=0.01) is None
    assert trimmed_rung(TableSpec(0.0, 1.0, 100), 0.0101, TableSpec(0.0, 1.0, 110), 0.0099, margin=0.01) is None
    assert trimmed_rung(over, 0.0125, TableSpec(0.0, 1.0, 4350, precision="int8"), 0.0034, margin=0.01) is None
    assert trimmed_rung(over, 0.0125, within, 0.0, margin=0.01) is None


def test_a_record_of_other_parameter_values_at_the_same_step_is_not_trusted():
    """A record names the fingerprint of the values it measured: a compact file's fp16 rounding (or any edit) at the
    same step leaves the approximate switches off, said on the line, until measured again."""
    params = [torch.linspace(0, 1, 1000), torch.ones(4, 3)]
    decision = SwitchDecision(lambda: 99, lambda: params)
    config, cpu = RenderSettings(), torch.device("cpu")
    decision.record = {**_record(99), "params": decision.fingerprint()}
    assert decision.settings(config, False, cpu).time_table  # the values measured: trusted
    with torch.no_grad():
        params[0].copy_(params[0].half().float())  # as load_compact puts a compact file's values back
    decision.parameters_changed()  # what load_compact and a checkpoint's load say
    assert not decision.settings(config, False, cpu).time_table and decision.table_spec() is None
    assert "the parameters changed since they were measured" in decision.line(config, False, cpu)
    old = _record(99)  # a record written before fingerprints: trusted by its step, as before
    decision.record = old
    assert decision.settings(config, False, cpu).time_table


def test_the_load_line_names_the_table_built_where_it_differs_from_the_record():
    decision = SwitchDecision(lambda: 99)
    config, cpu = RenderSettings(), torch.device("cpu")
    decision.record = _record(99)
    info = decision.record[TABLE]["info"]
    assert "3 of 100 Gaussians on the network)" in decision.line(config, False, cpu)  # not built yet: the record
    built = {**info, "network": 40, "spec": {**info["spec"], "order": "cubic"}}  # rebuilt on another device
    decision.table_built = lambda spec: built if spec == decision.table_spec() else None
    line = decision.line(config, False, cpu)
    assert "time_table (12 keys, cubic, 10 MB, 40 of 100 Gaussians on the network; measured as linear with 3" in line


def test_the_fingerprint_is_hashed_again_only_when_a_parameter_changes(monkeypatch):
    params = [torch.nn.Parameter(torch.ones(10)), torch.nn.Parameter(torch.zeros(3))]
    decision = SwitchDecision(lambda: 1, lambda: params)
    hashes = []
    real = hashlib.sha1
    monkeypatch.setattr(hashlib, "sha1", lambda *a: hashes.append(1) or real(*a))
    first = decision.fingerprint()
    assert decision.fingerprint() == first and len(hashes) == 1  # a frame asks every time: no hash again
    with torch.no_grad():
        params[1].add_(1.0)
    assert decision.fingerprint() != first and len(hashes) == 2


def test_one_frame_takes_the_parameters_versions_once_and_still_sees_a_change_between_frames():
    """Inside `one_frame` the decision reads the versions the frame took instead of listing the parameters again
    (three times a frame before); a parameter changed between two frames is still seen by the next one."""
    params = [torch.nn.Parameter(torch.ones(10)), torch.nn.Parameter(torch.zeros(3))]
    listed = []
    decision = SwitchDecision(lambda: 99, lambda: listed.append(1) or params)
    config, cpu = RenderSettings(), torch.device("cpu")
    decision.record = {**_record(99), "params": decision.fingerprint()}
    listed.clear()
    with decision.one_frame(params):
        assert decision.settings(config, False, cpu).time_table and decision.table_spec() is not None
        assert decision.table_spec() is decision.table_spec()  # the record's spec made once
    assert listed == []  # the frame's versions served: the parameters were not listed again
    with torch.no_grad():
        params[0].mul_(2.0)
    with decision.one_frame(params):
        assert decision.table_spec() is None and not decision.settings(config, False, cpu).time_table
    assert decision.distrust() is not None and "parameters changed" in decision.distrust()
