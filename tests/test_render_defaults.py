"""A finished model renders with the switches its training measured; a training model renders plain."""

import math
from typing import Any, Dict

import pytest
import torch

from garo_ns.render.frame import FrameSettings


def train_short(scene: Any, out: Any) -> Dict[str, Any]:
    from garo_ns.tools.train import QuickSchedule, make_config, train

    config = make_config(
        "garo-deform",
        scene,
        out,
        schedule=QuickSchedule(
            steps=60, num_random=600, deform_width=16, deform_depth=2, deform_skip=0, extra={"sh_degree": 1}
        ),
        experiment_name="switches",
    )
    config.pipeline.model.rasterizer = "reference"
    config.pipeline.model.compact_guard_views = 3
    return {"trainer": train(config), "config": config}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from garo_ns.tools.scene import SceneSpec, generate_scene

    scene = generate_scene(tmp_path_factory.mktemp("scene"), SceneSpec(resolution=24, n_train=8, n_val=2, n_test=2))
    return train_short(scene, tmp_path_factory.mktemp("runs"))


@pytest.mark.slow
def test_training_measures_the_switches_and_its_own_renders_stay_plain(trained):
    model = trained["trainer"].pipeline.model
    record = model.switches.record
    # Every training view (8, fewer than switch_views), not compaction's 3: measured with the current check.
    assert record is not None and record["views"] == 8 and record["step"] == 59
    assert record["measure"] == "view_change_db"
    # On a CPU the static skip and the time table are measured (no CUDA precision), as finite changes.
    assert set(record["tried"]) == {"static_skip", "time_table"}
    assert all(0 <= v < math.inf for v in record["tried"].values())
    assert model.training_run
    assert model.render_settings() == FrameSettings()  # a viewer attached to training sees what trains


@pytest.mark.slow
def test_a_loaded_model_follows_the_record_and_flags_override(trained, capsys):
    from garo_ns.tools.eval import load_run

    config_path = trained["config"].get_base_dir() / "config.yml"
    _, pipeline, _, _ = load_run(config_path)
    model = pipeline.model
    # Loading says, in one line, which switches are in use and what each approximate one was measured to change.
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("Render switches:")]
    loss = model.switches.record["tried"]["static_skip"]
    assert len(lines) == 1 and f"static_skip {loss:.4f} dB" in lines[0] and "render_precision" not in lines[0]
    assert "8 training views at step 59" in lines[0]
    assert not model.training_run
    assert model.switches.record == trained["trainer"].pipeline.model.switches.record  # through the checkpoint
    loss = model.switches.record["tried"]["static_skip"]
    settings = model.render_settings()
    assert not settings.cuda_graph and not settings.lean_raster  # CPU
    # The record decides against the bound, inclusive: a change at, under or over it (not the one measured
    # here, which could fall on either side and so check nothing).
    record, bound = model.switches.record, model.config.switch_bound_db
    for measured, skip in ((bound / 2, True), (bound, True), (bound * 2, False)):
        model.switches.record = {**record, "tried": {"static_skip": measured}}
        assert model.render_settings().static_skip is skip, (measured, bound)
    model.switches.record = record
    # The bound decides: a looser one turns the skip on, a stricter one off.
    model.config.switch_bound_db = max(loss, 0.0) + 1.0
    assert model.render_settings().static_skip
    model.switches.record = {**model.switches.record, "tried": {"static_skip": 2.0}}
    model.config.switch_bound_db = 1.0
    assert not model.render_settings().static_skip
    # A flag set by the user wins over the record.
    model.config.switch_bound_db = 5.0
    model.config.static_skip = False
    assert not model.render_settings().static_skip
    # Rendering a test camera goes through the decided switches without error.
    model.config.static_skip = None
    camera = pipeline.datamanager.train_dataset.cameras[0:1].to(model.device)
    with torch.no_grad():
        out = model.get_outputs(camera)
    assert torch.isfinite(out["rgb"]).all()


@pytest.mark.slow
@pytest.mark.parametrize("measured, skip", [(0.01, True), (0.03, False)])
def test_garo_eval_records_the_switches_it_rendered_with(trained, tmp_path, monkeypatch, measured, skip):
    """The checkpoint's record, given a static-skip change under or over the 0.02 dB bound as it loads: the
    JSON says what was measured and which switches rendered (fixed expectations, whatever this tiny
    training measured)."""
    import json

    from garo_ns.garo_model import GaroModel
    from garo_ns.tools.eval import EvalArgs, run

    load = GaroModel.set_extra_state

    def with_measured(self, state):
        record = {**state["render_switches"], "tried": {"static_skip": measured}}
        load(self, {**state, "render_switches": record})

    monkeypatch.setattr(GaroModel, "set_extra_state", with_measured)
    out = tmp_path / "eval.json"
    run(EvalArgs(load_config=trained["config"].get_base_dir() / "config.yml", split="test", output_path=out))
    switches = json.loads(out.read_text())["render_switches"]
    assert switches["measured_db"] == {"static_skip": measured}
    assert switches["measured_views"] == 8 and switches["measured_at_step"] == 59 and switches["bound_db"] == 0.02
    in_use = switches["in_use"]
    assert "render_precision" not in in_use and not in_use["cuda_graph"]  # a CPU
    assert in_use["static_skip"] is skip
