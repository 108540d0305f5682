"""A trained model's time table: measured at the end of training, used on load, and what it changes."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from garo_ns.render.switches import TABLE, trimmed_rung, worst_view_change_db
from garo_ns.render.time_table import TableSpec


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from garo_ns.tools.scene import SceneSpec, generate_scene
    from garo_ns.tools.train import QuickSchedule, make_config, train

    scene = generate_scene(tmp_path_factory.mktemp("scene"), SceneSpec(resolution=24, n_train=8, n_val=2, n_test=2))
    schedule = QuickSchedule(steps=60, num_random=600, deform_width=16, deform_depth=2, deform_skip=0)
    config = make_config("garo-deform", scene, tmp_path_factory.mktemp("runs"), schedule=schedule)
    config.pipeline.model.rasterizer = "reference"
    return {"trainer": train(config), "config": config}


def _load(trained, settings=None):
    from garo_ns.compaction.guard import TrainingViewGuard
    from garo_ns.tools.eval import load_run

    _, pipeline, _, _ = load_run(trained["config"].get_base_dir() / "config.yml", settings=settings)
    return pipeline.model, TrainingViewGuard.from_datamanager(pipeline.datamanager, 32)


class RowCounter:
    """Counts the rows the deformation MLP is run on."""

    def __init__(self, field):
        self.rows = []
        field.register_forward_hook(lambda module, args, out: self.rows.append(args[0].shape[0]))


@pytest.mark.slow
def test_training_records_the_table_and_a_loaded_model_renders_the_recorded_change(trained, capsys):
    record = trained["trainer"].pipeline.model.switches.record
    table = record[TABLE]
    assert 0 <= record["tried"][TABLE] < math.inf
    info = table["info"]
    # 8 training times, 2, 4, 8, 16, 32 or 64 intervals per gap (the fewest within the ladder's margin, else the one
    # that changed the views least) or a trimmed rung between two of them; two padding keys at each end; built from
    # the trained field.
    doubling = (14, 28, 56, 112, 224, 448)
    intervals = info["spec"]["intervals"]
    assert 14 <= intervals <= 448 and info["keys"] == intervals + 4
    assert info["gaussians"] > 0 and info["mb"] > 0 and info["build_s"] >= 0
    previews, ladder = table.get("intervals_previewed_db", {}), table.get("intervals_tried_db", {})
    if previews or ladder:  # a rung previewed is built only if its preview came within the margin
        margin = 0.02 * trained["trainer"].pipeline.model.config.time_table_margin
        assert set(table["build_s"]) == set(ladder) and set(table["preview_s"]) == set(previews)
        assert all(0 <= v < math.inf for v in [*table["build_s"].values(), *table["preview_s"].values()])
        assert all(previews[k] <= margin for k in set(ladder) & set(previews))
        measured = {**previews, **ladder}
        rungs = sorted(measured, key=lambda k: int(k.split()[0]))  # "<intervals>" [+ " int8"]
        trimmed = [k for k in rungs if int(k.split()[0]) not in doubling]
        plain = [k for k in rungs if k not in trimmed]
        # Denser tables were tried only while the sparser missed the margin, as previewed or as built.
        losses = [measured[k] for k in plain]
        assert all(v > margin for v in losses[:-1])
        if trimmed:  # tried between the last rung over the margin and the first within it; taken if within too
            (trim,) = trimmed
            at = {k: int(k.split()[0]) for k in rungs}
            assert losses[-1] <= margin and at[plain[-2]] < at[trim] < at[plain[-1]]
            assert intervals == (at[trim] if measured[trim] <= margin else at[plain[-1]])
        elif losses[-1] <= margin:
            assert int(plain[-1].split()[0]) == intervals
        else:
            assert intervals in doubling and measured[str(intervals)] == min(losses)
    model, guard = _load(trained)
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("Render switches:")][0]
    assert f"time_table {record['tried'][TABLE]:.4f} dB" in line
    model.config.switch_bound_db = record["tried"][TABLE] + 1.0  # whatever it measured: on
    assert model.render_settings().time_table
    assert f"time_table ({info['keys']} keys" in model.switches.line(model.config, False, model.device)
    # The loaded model's table renders the training views, each halfway between keys, with the recorded change.
    model.frame.halfway = True
    with torch.no_grad():
        plain = torch.stack([guard.render(model, i) for i in range(len(guard.indices))])
        tabled = torch.stack([guard.render(model, i, model.render_settings()) for i in range(len(guard.indices))])
    model.frame.halfway = False
    targets = torch.stack(guard.targets(model))
    assert worst_view_change_db(plain, tabled, targets) == pytest.approx(record["tried"][TABLE], abs=1e-4)


@pytest.mark.slow
def test_a_table_frame_runs_the_network_only_on_the_gaussians_the_table_cannot_follow(trained):
    model, _ = _load(trained)
    model.config.time_table = True
    counter = RowCounter(model.deformation)
    with torch.no_grad():
        for t in (0.1, 0.35, 0.8):
            model.gaussians_at(t)
    network = model.frame.table.network.numel()
    if network:  # each frame ran the MLP on the network's Gaussians only
        assert counter.rows[-3:] == [network] * 3
    else:  # building ran the MLP; the frames did not
        rows = len(counter.rows)
        with torch.no_grad():
            model.gaussians_at(0.55)
        assert len(counter.rows) == rows
    # The network's own frame, for comparison: every Gaussian through the MLP.
    model.config.time_table = False
    with torch.no_grad():
        model.gaussians_at(0.2)
    assert counter.rows[-1] == model.num_points


@pytest.mark.slow
def test_a_table_over_the_bound_or_the_budget_stays_off_and_says_why(trained):
    model, guard = _load(trained)
    record = model.switches.record
    model.switches.record = {**record, "tried": {**record["tried"], TABLE: 5.0}}
    assert not model.render_settings().time_table
    assert "time table off: its change 5.0000 dB is over the bound" in model.switches.line(
        model.config, False, model.device
    )
    # Measured again with a budget too small for any table: off, with the reason in the record.
    model.train_times = torch.linspace(0, 1, 8)
    model.config.time_table_budget_mb = 1e-3
    line = model.switches.measure_on_training_views(model, guard, model.step)
    assert "time_table inf dB" in line
    assert "memory budget" in model.switches.record[TABLE]["off"]
    assert not model.render_settings().time_table


@pytest.mark.slow
def test_the_ladder_builds_a_dense_table_only_where_its_preview_comes_within_the_margin(trained):
    model, guard = _load(trained)
    model.train_times = torch.linspace(0, 1, 8)  # the scene's 8 training times (a loaded model has none)
    model.config.time_table_keys_per_frame, model.config.time_table_max_keys_per_frame = 32, 128
    # 7 gaps: 224 intervals (built: fewer field passes than a preview), 448 and 896 (previewed first).
    model.config.switch_bound_db = 1e-9  # no table comes within: the least change is taken
    model.switches.measure_on_training_views(model, guard, model.step)
    table = model.switches.record[TABLE]
    previews, built = table["intervals_previewed_db"], table["intervals_tried_db"]
    assert set(built) == {"224"} and set(previews) == {"448", "896"}  # no preview within the margin: none built
    losses = {**previews, **built}
    assert table["info"]["spec"]["intervals"] == int(min(losses, key=losses.get))
    assert model.switches.record["tried"][TABLE] < math.inf  # the table taken was built and measured as built
    # A margin between the sparsest rung as built and the first denser rung whose preview comes below it: that rung is
    # built and taken, the rungs between previewed and skipped, the denser ones untried. (Changes this small, 1e-4 dB,
    # need not fall with every rung: on this scene 448's preview came above 224 as built with one composition.)
    margin = model.config.time_table_margin
    rungs = ["448", "896"]
    taken = next(r for r in rungs if previews[r] < built["224"])  # the densest rung's preview is far below
    model.config.switch_bound_db = 0.5 * (built["224"] + previews[taken]) / margin
    model.switches.measure_on_training_views(model, guard, model.step)
    table = model.switches.record[TABLE]
    tried, previewed = table["intervals_tried_db"], table["intervals_previewed_db"]
    assert set(previewed) - {"224"} >= set(rungs[: rungs.index(taken) + 1])
    # The rung before `taken` and `taken` bracket the margin: a trimmed rung between them is tried where their fit
    # says it saves a sixth of the keys (`trimmed_rung`), and taken where it comes within the margin too.
    measured = {**previewed, **tried}
    before = rungs[rungs.index(taken) - 1] if taken != rungs[0] else "224"
    spec = TableSpec(**table["info"]["spec"])
    trim = trimmed_rung(
        replace(spec, intervals=int(before)),
        measured[before],
        replace(spec, intervals=int(taken)),
        measured[taken],
        model.config.switch_bound_db * margin,
    )
    assert set(tried) - ({str(trim.intervals)} if trim else set()) == {"224", taken}
    within = trim is not None and measured[str(trim.intervals)] <= model.config.switch_bound_db * margin
    assert table["info"]["spec"]["intervals"] == (trim.intervals if within else int(taken))
    # The built table's change is its preview's plus the int16 keys' rounding: close to it.
    assert tried[taken] == pytest.approx(previews[taken], rel=0.05, abs=1e-5)


@pytest.mark.slow
def test_a_table_that_cannot_be_built_is_reported_off_and_never_measured_as_passing(trained, monkeypatch, capsys):
    from garo_ns.render.time_table import TimeTable

    def out_of_memory(*args, **kwargs):
        raise RuntimeError("CUDA out of memory. Tried to allocate 6.10 GiB")

    monkeypatch.setattr(TimeTable, "build", out_of_memory)
    monkeypatch.setattr(TimeTable, "preview", out_of_memory)
    model, guard = _load(trained, {"time_table_cache": False})  # the record says the table; its build at load fails
    said = capsys.readouterr().out
    assert "could not be built (RuntimeError: CUDA out of memory" in said and "through the network" in said
    model.config.switch_bound_db = 1e9  # whatever was measured: the table would be on, were it built
    assert not model.render_settings().time_table
    summary = model.render_switch_summary()
    assert not summary["in_use"]["time_table"] and "could not be built" in summary[TABLE]["off"]
    assert "time_table (" not in model.switches.line(model.config, False, model.device)
    # Measured again at the end of training: the table's trial is an infinite change, not the network's 0.0.
    model.config.switch_bound_db = 0.02
    model.train_times = torch.linspace(0, 1, 8)
    line = model.switches.measure_on_training_views(model, guard, model.step)
    assert "time_table inf dB" in line, line
    assert "could not be built" in model.switches.record[TABLE]["off"]
    assert not model.render_settings().time_table


@pytest.mark.slow
def test_a_trial_that_fails_turns_off_its_switch_only_and_a_bug_is_not_swallowed(trained):
    model, guard = _load(trained)
    model.train_times = torch.linspace(0, 1, 8)
    model.config.switch_bound_db = 1e9  # every switch that renders passes
    plain_render = guard.render

    def failing(error):
        def render(m, i, switches=None):
            if switches is not None and switches.time_table:
                raise error
            return plain_render(m, i, switches)

        return render

    guard.render = failing(RuntimeError("CUDA error: an illegal memory access was encountered"))
    line = model.switches.measure_on_training_views(model, guard, model.step)
    record = model.switches.record
    assert record["tried"][TABLE] == math.inf and "time_table (RuntimeError: CUDA error" in line, line
    assert 0 <= record["tried"]["static_skip"] < math.inf  # the other switch's trial is kept
    assert model.render_settings().static_skip and not model.render_settings().time_table
    guard.render = failing(TypeError("a bug"))
    with pytest.raises(TypeError, match="a bug"):
        model.switches.measure_on_training_views(model, guard, model.step)


@pytest.mark.slow
def test_a_table_forced_on_for_training_is_recorded_and_used_on_load(trained):
    model, guard = _load(trained)
    model.train_times = torch.linspace(0, 1, 8)
    model.config.time_table = True  # --pipeline.model.time-table True
    model.switches.measure_on_training_views(model, guard, model.step)
    table = model.switches.record[TABLE]
    assert table.get("forced") and table["spec"]["intervals"] > 0
    spec = model.switches.table_spec()
    assert spec is not None and spec.to_dict() == table["spec"]
    assert model.render_settings().time_table and "no table recorded" not in str(model.render_switch_summary())


@pytest.mark.slow
def test_on_a_cpu_a_dense_recorded_table_is_put_off_and_said(trained):
    from garo_ns.render.switches import CPU_TABLE_EVALUATIONS

    model, _ = _load(trained)
    record = model.switches.record
    gaussians = record[TABLE]["info"]["gaussians"]
    dense = {**record[TABLE]["spec"], "intervals": int(CPU_TABLE_EVALUATIONS / gaussians) + 1}  # as a GPU's table
    model.switches.record = {**record, TABLE: {**record[TABLE], "spec": dense}}
    model.config.switch_bound_db = 1e9  # measured within the bound: only the device turns it off
    assert not model.render_settings().time_table  # on this CPU
    line = model.switches.line(model.config, False, torch.device("cpu"))
    assert "on a CPU its build would run the deformation field" in line and "time-table True" in line, line
    assert model.switches.settings(model.config, False, torch.device("cuda")).time_table  # a GPU builds it
    model.switches.record = record  # the table this CPU trained: small enough to build here
    assert model.render_settings().time_table


@pytest.mark.slow
def test_a_loaded_model_trusts_its_record_until_its_values_are_rounded_to_storage(trained, capsys):
    """torch restores the record before the parameters: the load line is decided once all are in (it once said
    "the parameters changed" of a model loaded unchanged). Rounding to the compact file's fp16 then distrusts the
    fp32 record; putting the trained values back trusts it again."""
    from garo_ns.state import storage

    model, _ = _load(trained)
    record = trained["trainer"].pipeline.model.switches.record
    assert model.switches.fingerprint() == record["params"]
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("Render switches:")][0]
    assert "changed since they were measured" not in line and "measured on" in line
    original = storage.snapshot(model)
    storage.round_to_storage(model)
    assert "the parameters changed since they were measured" in model.switches.line(model.config, False, model.device)
    assert not model.render_settings().time_table
    storage.restore(model, original)
    assert model.switches.distrust() is None


@pytest.mark.slow
def test_a_model_under_a_window_budget_holds_a_window_of_its_table_and_renders_the_same_frames(trained):
    from garo_ns.render.time_table import build_bytes

    model, _ = _load(trained)
    model.config.time_table = True  # whatever was measured
    spec = model.switches.table_spec()
    times = (0.05, 0.3, 0.55, 0.95)
    with torch.no_grad():
        whole = {t: model.gaussians_at(t).means.clone() for t in times}
    assert model.frame.table.spec == spec
    window = spec.intervals // 3
    model.config.time_table_window_mb = build_bytes(window, model.num_points, spec.precision) / 2**20
    model.frame.configure(model.config)
    with torch.no_grad():
        for t in times:
            got = model.gaussians_at(t).means
            table = model.frame.table
            assert table.spec.intervals == window and table.spec.t_lo <= t <= table.spec.t_hi
            assert table.nbytes() <= model.config.time_table_window_mb * 2**20
            assert torch.allclose(got, whole[t], atol=1e-4 * float(whole[t].abs().max()))
    line = model.switches.line(model.config, False, model.device)
    assert f"a window of {window} of {spec.intervals} intervals" in line, line
    # Set when loading (garo-eval --model-set, the benchmark's): the load builds the first window, not the whole table.
    from garo_ns.tools.eval import load_run

    config = trained["config"].get_base_dir() / "config.yml"
    settings = {"time_table": True, "time_table_window_mb": model.config.time_table_window_mb}
    loaded = load_run(config, settings=settings)[1].model
    assert loaded.frame.table.spec.intervals == window and loaded.frame.table.spec.t_lo == spec.t_lo


@pytest.mark.slow
def test_a_loaded_model_writes_its_table_beside_the_run_and_reads_it_at_the_next_load(trained, monkeypatch, capsys):
    import shutil

    from garo_ns.render.time_table import TimeTable

    folder = trained["config"].get_base_dir() / "time_tables"
    shutil.rmtree(folder, ignore_errors=True)  # written by this module's earlier loads
    settings = {"time_table": True}
    first, _ = _load(trained, settings)
    (written,) = folder.iterdir()
    assert first.frame.table_info["file"] == {"path": str(written), "read": False, "written": True}
    assert f"written to {written}" in capsys.readouterr().out
    times = (0.05, 0.4, 0.95)
    with torch.no_grad():
        want = [first.gaussians_at(t).means.clone() for t in times]

    def no_build(*args, **kwargs):
        raise AssertionError("the table was built, not read")

    monkeypatch.setattr(TimeTable, "build", no_build)
    second, _ = _load(trained, settings)
    assert second.frame.table_info["file"]["read"] and f"read from {written}" in capsys.readouterr().out
    with torch.no_grad():
        for t, means in zip(times, want):
            assert torch.equal(second.gaussians_at(t).means, means)
    assert list(folder.iterdir()) == [written]
    # Other values (rounded to the compact file's fp16) hash to another file: built, not read.
    monkeypatch.undo()
    from garo_ns.state import storage

    storage.round_to_storage(second)
    second.switches.parameters_changed()
    second.switches.table_override = second.switches.table_spec() or TableSpec(**first.frame.table.spec.to_dict())
    with torch.no_grad():
        second.gaussians_at(0.3)
    assert not second.frame.table_info["file"]["read"] and len(list(folder.iterdir())) == 2
    # Off: nothing read or written.
    shutil.rmtree(folder)
    third, _ = _load(trained, {**settings, "time_table_cache": False})
    assert "file" not in third.frame.table_info and not folder.exists()


@pytest.mark.slow
def test_a_finished_run_writes_its_table_and_a_window_is_cut_from_that_file(trained, monkeypatch, capsys):
    import shutil

    from garo_ns.render import table_cache
    from garo_ns.render.time_table import TimeTable, build_bytes

    folder = trained["config"].get_base_dir() / "time_tables"
    shutil.rmtree(folder, ignore_errors=True)
    model = trained["trainer"].pipeline.model
    assert model.final_checkpoint.is_file()  # the checkpoint the run ended with: the table is named after it
    bound = model.config.switch_bound_db
    model.config.switch_bound_db = 1e9  # the render choice took the table, whatever it measured
    try:
        spec = model.switches.table_spec()
        with torch.no_grad():
            model.frame.time_table(model.deformation, model.canonical(), spec)  # as the measurement leaves it built
        said = table_cache.keep_trained_table(model, model.final_checkpoint)
        model.config.switch_bound_db = 0.0  # not taken: nothing to write
        assert table_cache.keep_trained_table(model, model.final_checkpoint) is None
    finally:
        model.config.switch_bound_db = bound
    (written,) = folder.iterdir()
    assert said == f"Time table written to {written} for the finished model's loads"

    def no_build(*args, **kwargs):
        raise AssertionError("the table was built, not read")

    monkeypatch.setattr(TimeTable, "build", no_build)
    whole, _ = _load(trained, {"time_table": True})  # the first load reads what training wrote
    assert whole.frame.table_info["file"]["read"]
    times = (0.02, 0.3, 0.61, 0.97)
    with torch.no_grad():
        want = {t: whole.gaussians_at(t).means.clone() for t in times}
    # A window of a third of the table: cut from the file, each window the whole table's frames.
    mb = build_bytes(spec.intervals // 3, whole.num_points, spec.precision) / 2**20
    windowed, _ = _load(trained, {"time_table": True, "time_table_window_mb": mb})
    with torch.no_grad():
        for t in times:
            got = windowed.gaussians_at(t).means
            info = windowed.frame.table_info
            assert info["file"]["read"] and info["window"]["of_intervals"] == spec.intervals
            assert windowed.frame.table.spec.t_lo <= t <= windowed.frame.table.spec.t_hi
            assert torch.allclose(got, want[t], rtol=0, atol=1e-6 * float(want[t].abs().max()))
    assert list(folder.iterdir()) == [written]  # a window writes nothing
