"""The demo's code path on a shortened schedule: both arms trained, figures side by side, picture and plot."""

from __future__ import annotations

import json

import pytest
from PIL import Image


@pytest.mark.slow
def test_demo_writes_side_by_side_figures_strip_and_plot(tmp_path, capfd):
    from garo_ns.tools.demo import DemoArgs, run

    args = DemoArgs(output_dir=tmp_path, steps=30, resolution=24, n_train=6, n_test=3, strip_frames=3, num_random=800)
    summary = run(args)
    saved = json.loads((tmp_path / "demo_results.json").read_text())
    assert saved == summary
    assert [a["method"] for a in saved["arms"]] == ["garo-deform", "deform-splatfacto"]
    for arm in saved["arms"]:
        assert arm["iterations"] == 30 and arm["n_images"] == 3
        assert 5 < arm["psnr"] < 60 and arm["num_gaussians"] > 0
        assert arm["model_mb"] > 0 and arm["render_ms"] > 0
        assert (tmp_path / arm["method"]).is_dir()
        assert json.loads((tmp_path.joinpath(*arm["run_dir"].split("/")[-2:]) / "eval_test.json").read_text())
    floor = saved["arms"][0]["floor"]
    assert floor is not None and "floor_gaussians" in floor
    if floor["floor_gaussians"]:
        assert 0 <= floor["floor_static_fraction"] <= 1 and floor["static_threshold"] > 0
    assert saved["wall_seconds"] > 0 and saved["peak_rss_mb"] > 0 and saved["args"]["steps"] == 30
    if saved["parallel"]:  # the second arm trained beside the first, its progress in its run folder
        assert "Step" in (tmp_path / "deform-splatfacto" / "train.log").read_text()
        assert saved["peak_rss_mb"] > max(a["peak_rss_mb"] for a in saved["arms"])
    table = (tmp_path / "demo_results.md").read_text()
    assert "garo-deform" in table and "deform-splatfacto" in table and "render ms/view" in table
    assert "garo-deform floor:" in table
    strip = Image.open(tmp_path / "demo_strip.png")
    plot = Image.open(tmp_path / "demo_speed_error.png")
    assert strip.width > strip.height > 100 and plot.width > 100
    out = capfd.readouterr().out  # the first arm's process writes to the terminal's descriptor
    assert "demo_strip.png" in out and "ns-viewer --load-config" in out
    assert "Step" in out or "ETA" in out  # nerfstudio's progress lines were shown


def test_demo_config_scales_rates_and_sets_the_scene(tmp_path):
    """The demo's settings reach the trainer config and the scene (no training)."""
    from garo_ns.config import optimizers
    from garo_ns.tools.demo import DemoArgs, scene_spec
    from garo_ns.tools.scene import GROUND_HALF, SceneSpec
    from garo_ns.tools.train import DemoSchedule, make_config

    args = DemoArgs()
    spec = scene_spec(args)
    assert spec.checks_per_unit * 2 * GROUND_HALF == pytest.approx(args.ground_squares)
    assert spec.sphere_stripes == args.sphere_stripes and spec.resolution == args.resolution
    assert SceneSpec().checks_per_unit == 4.0 and SceneSpec().sphere_stripes == 8  # the tests' scene unchanged
    # The demo's motions are ones its schedule learns: the box slides without turning, the stripes stay.
    assert (spec.box_turns, spec.box_slide, spec.ball_turns) == (args.box_turns, args.box_slide, args.ball_turns)
    assert args.box_turns == 0 and args.box_slide > 0 and args.ball_turns == 0
    assert (SceneSpec().box_turns, SceneSpec().box_slide, SceneSpec().ball_turns) == (0.5, 0.0, 1.25)
    schedule = DemoSchedule(
        steps=100, lr_scale={"means": 20.0, "features_dc": 4.0}, extra={"deform_head_init": "default"}
    )
    config = make_config("garo-deform", tmp_path, tmp_path, schedule=schedule)
    ref = optimizers()
    assert config.optimizers["means"]["optimizer"].lr == pytest.approx(20 * ref["means"]["optimizer"].lr)
    assert config.optimizers["means"]["scheduler"].lr_final == pytest.approx(20 * ref["means"]["scheduler"].lr_final)
    assert config.optimizers["features_dc"]["optimizer"].lr == pytest.approx(4 * ref["features_dc"]["optimizer"].lr)
    assert config.optimizers["opacities"]["optimizer"].lr == ref["opacities"]["optimizer"].lr
    assert config.pipeline.model.deform_head_init == "default"
    with pytest.raises(ValueError, match="not a parameter group"):
        make_config("garo-deform", tmp_path, tmp_path, schedule=DemoSchedule(steps=100, lr_scale={"mean": 2.0}))


@pytest.mark.parametrize("steps", [2000, 4000])
def test_demo_schedule_scales_every_phase_with_the_step_count(tmp_path, steps):
    """Densification, opacity resets, GARO's cadence, the deformation switch-on and every learning-rate decay
    sit at the same fractions of the run whatever its length (no phase is left at a fixed step count)."""
    from garo_ns.tools.demo import DemoArgs
    from garo_ns.tools.train import DemoSchedule, make_config

    schedule = DemoSchedule(steps=steps, deform_warmup_frac=DemoArgs().deform_warmup_frac)
    config = make_config("garo-deform", tmp_path, tmp_path, schedule=schedule)
    m = config.pipeline.model
    assert config.max_num_iterations == steps
    assert m.stop_split_at == int(0.6 * steps) and m.deform_warmup == int(0.25 * steps)
    assert m.warmup_length == steps // 20 and m.refine_every == steps // 30
    # one opacity reset, a third of the way in, before densification stops
    assert m.refine_every * m.reset_alpha_every == pytest.approx(steps / 3, rel=0.02)
    assert m.garo_every is None and m.garo_start is None and m.garo_stop is None  # GARO follows densification
    for name, opt in config.optimizers.items():
        sched = opt.get("scheduler")
        if sched is not None and hasattr(sched, "max_steps"):
            assert sched.max_steps == steps, name
    assert config.optimizers["deformation"]["scheduler"].warmup_steps == int(0.25 * steps)


def test_the_demo_trains_both_arms_with_one_scale_composition(tmp_path):
    """The demo compares GARO with the same model without it: `deform-splatfacto`'s own composition (`linear`) is
    set back to the demo's (benchmarks/results/demo_scale_term_cpu.json says why)."""
    from garo_ns.tools.demo import DemoArgs, demo_config

    for method in ("garo-deform", "deform-splatfacto"):
        config = demo_config(DemoArgs(), method, tmp_path / "scene", tmp_path / "out", "cpu")
        assert config.pipeline.model.deform_scale_offset == "log", method
    config = demo_config(DemoArgs(deform_scale_offset="linear"), "garo-deform", tmp_path, tmp_path / "out", "cpu")
    assert config.pipeline.model.deform_scale_offset == "linear"


def test_the_printed_resume_command_builds_the_arm_s_model(tmp_path):
    """The demo's arms train a smaller field than their method's: the resume command it prints passes the settings
    that shape the checkpoint's tensors (and no other), so ns-train builds a model the checkpoint fits."""
    import shlex

    import tyro
    import yaml
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from garo_ns.state.checkpoints import expected_state, shape_settings
    from garo_ns.tools.demo import DemoArgs, demo_config, resume_command

    args = DemoArgs()
    config = demo_config(args, "garo-deform", tmp_path / "scene", tmp_path, "cpu")
    config.set_timestamp()
    config.save_config()
    config_path = config.get_base_dir() / "config.yml"
    command = resume_command("garo-deform", config_path, tmp_path / "scene", steps=7)
    words = shlex.split(command)
    assert words[1] == "garo-deform" and words[words.index("--load-dir") + 1] == str(config.get_checkpoint_dir())
    flags = {w: words[i + 1] for i, w in enumerate(words) if w.startswith("--pipeline.model.")}
    depth, width, skip = str(args.deform_depth), str(args.deform_width), str(args.deform_skip)
    assert flags == {
        "--pipeline.model.deform-depth": depth,
        "--pipeline.model.deform-width": width,
        "--pipeline.model.deform-skip": skip,
    }
    parsed = tyro.cli(AnnotatedBaseConfigUnion, args=words[1:])
    trained = yaml.load(config_path.read_text(), Loader=yaml.Loader).pipeline.model
    assert parsed.max_num_iterations == 7 and shape_settings(trained, parsed.pipeline.model) == {}
    shapes = {k: v.shape for k, v in expected_state(trained).items()}
    assert {k: v.shape for k, v in expected_state(parsed.pipeline.model).items()} == shapes
