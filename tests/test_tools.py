"""The plugin inside nerfstudio's tools: PLY export over time, renders over time, resume, errors."""

from __future__ import annotations

import copy
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from garo_ns.errors import GaroInputError
from garo_ns.tools.export import export_times, read_ply

ENV = {**os.environ, "TORCHDYNAMO_DISABLE": "1"}
BIN = Path(sys.executable).parent


def _cli(*args, cwd=None, timeout=600):
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=timeout)


def _splatfacto_property_names(sh_rest: int) -> list:
    """The vertex properties, in order, of nerfstudio's `ns-export gaussian-splat` (sh_coeffs mode)."""
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(sh_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


@pytest.mark.slow
def test_export_round_trip_matches_the_model_at_each_time(garo_run, tmp_path):
    model = garo_run["trainer"].pipeline.model
    model.eval()
    written = export_times(model, tmp_path, [0.0, 0.5, 1.0])
    assert set(written) == {"canonical.ply", "time_0.0000.ply", "time_0.5000.ply", "time_1.0000.ply"}
    opac = model.opacities.detach().reshape(-1)
    keep = (opac >= np.log((1 / 255) / (1 - 1 / 255))).cpu()  # the exporter drops near-transparent ones
    rest = model.features_rest.shape[1] * 3
    positions = {}
    for name, t in (("canonical.ply", None), ("time_0.5000.ply", 0.5), ("time_1.0000.ply", 1.0)):
        ply = read_ply(tmp_path / name)
        assert list(ply) == _splatfacto_property_names(rest)
        with torch.no_grad():
            means, quats, log_scales = (
                (model.means, model.quats, model.scales)
                if t is None
                else (lambda s: (s.means, s.quats, torch.log(s.scales)))(model.gaussians_at(t))
            )
            means, quats, log_scales = means.detach(), quats.detach(), log_scales.detach()
        n = int(keep.sum())
        assert written[name] == n and len(ply["x"]) == n
        xyz = np.stack([ply["x"], ply["y"], ply["z"]], -1)
        assert np.allclose(xyz, means[keep].cpu().numpy(), atol=1e-6)
        assert np.allclose(np.stack([ply[f"scale_{i}"] for i in range(3)], -1), log_scales[keep].cpu().numpy())
        assert np.allclose(np.stack([ply[f"rot_{i}"] for i in range(4)], -1), quats[keep].cpu().numpy(), atol=1e-6)
        assert np.allclose(ply["opacity"], opac[keep].cpu().numpy())
        assert np.allclose(
            np.stack([ply[f"f_dc_{i}"] for i in range(3)], -1), model.features_dc[keep].detach().cpu().numpy()
        )
        rest_ply = np.stack([ply[f"f_rest_{i}"] for i in range(rest)], -1).reshape(n, 3, -1)
        assert np.allclose(rest_ply, model.features_rest[keep].transpose(1, 2).detach().cpu().numpy())
        positions[name] = xyz
    # The deformation moves things: the exported scene differs over time and from the canonical one.
    assert np.abs(positions["time_0.5000.ply"] - positions["time_1.0000.ply"]).max() > 1e-3
    assert np.abs(positions["canonical.ply"] - positions["time_1.0000.ply"]).max() > 1e-3


@pytest.mark.slow
def test_export_drops_non_finite_gaussians_and_never_overwrites(garo_run, tmp_path):
    model = garo_run["trainer"].pipeline.model
    export_times(model, tmp_path, [0.25], canonical=False)
    target = tmp_path / "time_0.2500.ply"
    before = target.read_bytes()
    with pytest.raises(GaroInputError, match="exists"):
        export_times(model, tmp_path, [0.25], canonical=False)
    assert target.read_bytes() == before
    with pytest.raises(GaroInputError, match=r"\[0, 1\]"):
        export_times(model, tmp_path / "other", [1.5])
    assert not (tmp_path / "other").exists()
    saved = model.means.detach().clone()
    try:
        with torch.no_grad():
            model.means[:3] = float("nan")
        written = export_times(model, tmp_path / "nan", [0.25], canonical=False)
        ply = read_ply(tmp_path / "nan" / "time_0.2500.ply")
        assert np.isfinite(np.stack(list(ply.values()), -1)).all()
        assert written["time_0.2500.ply"] <= model.num_points - 3
    finally:
        with torch.no_grad():
            model.means.copy_(saved)


@pytest.mark.slow
def test_export_command_and_its_errors(garo_run, tmp_path):
    cfg = garo_run["config_path"]
    out = _cli(BIN / "garo-export", "--load-config", cfg, "--output-dir", tmp_path / "ply", "--num-times", "3")
    assert out.returncode == 0, out.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "ply").iterdir()) == [
        "canonical.ply",
        "time_0.0000.ply",
        "time_0.5000.ply",
        "time_1.0000.ply",
    ]
    # A run of another method: one line naming the file, no traceback, nothing written.
    other = tmp_path / "other" / "config.yml"
    other.parent.mkdir()
    other.write_text(cfg.read_text().replace("method_name: garo-deform", "method_name: splatfacto"))
    bad = _cli(BIN / "garo-export", "--load-config", other, "--output-dir", tmp_path / "none")
    assert bad.returncode != 0
    assert "Traceback" not in bad.stderr and str(other) in bad.stderr and "splatfacto" in bad.stderr
    assert not (tmp_path / "none").exists()
    # A time out of range is refused before anything is loaded.
    bad = _cli(BIN / "garo-export", "--load-config", cfg, "--output-dir", tmp_path / "t", "--times", "2.0")
    assert bad.returncode != 0 and "Traceback" not in bad.stderr and "[0, 1]" in bad.stderr


@pytest.mark.slow
def test_time_sweep_renders_with_ns_render(garo_run, tmp_path):
    """garo-camera-path writes keyframes with render_time; ns-render camera-path renders them, and the
    picture changes with time although the camera stays put."""
    cfg = garo_run["config_path"]
    path = tmp_path / "sweep.json"
    out = _cli(BIN / "garo-camera-path", "--load-config", cfg, "--output", path, "--frames", "5", "--seconds", "1")
    assert out.returncode == 0, out.stderr[-2000:]
    data = json.loads(path.read_text())
    assert [c["render_time"] for c in data["camera_path"]] == [0.0, 0.25, 0.5, 0.75, 1.0]
    if shutil.which("ffmpeg") is None:
        pytest.skip("ns-render needs ffmpeg (scripts/test.sh installs it)")
    frames = tmp_path / "frames"
    out = _cli(
        BIN / "ns-render",
        "camera-path",
        "--load-config",
        cfg,
        "--camera-path-filename",
        path,
        "--output-format",
        "images",
        "--output-path",
        frames,
    )
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    images = sorted(frames.glob("*.jpg")) + sorted(frames.glob("*.png"))
    assert len(images) == 5
    import imageio.v2 as imageio

    first, last = (imageio.imread(images[0]).astype(float), imageio.imread(images[-1]).astype(float))
    assert np.abs(first - last).mean() > 1.0  # 8-bit levels: the scene moved
    video = tmp_path / "sweep.mp4"
    out = _cli(
        BIN / "ns-render",
        "camera-path",
        "--load-config",
        cfg,
        "--camera-path-filename",
        path,
        "--output-path",
        video,
    )
    assert out.returncode == 0 and video.stat().st_size > 1000, (out.stdout + out.stderr)[-3000:]


@pytest.mark.slow
def test_ns_render_interpolate_without_times_uses_the_default_time(garo_run, tmp_path):
    if shutil.which("ffmpeg") is None:
        pytest.skip("ns-render needs ffmpeg (scripts/test.sh installs it)")
    out = _cli(
        BIN / "ns-render",
        "interpolate",
        "--load-config",
        garo_run["config_path"],
        "--output-format",
        "images",
        "--interpolation-steps",
        "1",
        "--output-path",
        tmp_path / "interp",
        "--pose-source",
        "train",
    )
    text = out.stdout + out.stderr
    assert out.returncode == 0, text[-3000:]
    assert text.count("rendering at default_time") == 1
    assert len(list((tmp_path / "interp").glob("*"))) >= 2


def _resume_config(scene, out, max_steps, name, load_dir=None):
    from garo_ns.tools.train import QuickSchedule, make_config

    config = make_config(
        "garo-deform",
        scene,
        out,
        schedule=QuickSchedule(steps=80, num_random=1500, deform_width=32, deform_depth=2, deform_skip=0),
        experiment_name=name,
    )
    config.max_num_iterations = max_steps  # the schedule (decays, phases) stays the 80-step one
    config.steps_per_save = 40
    config.load_dir = load_dir
    config.set_timestamp()
    return config


def _setup(config):
    from garo_ns.tools.train import seed_everything

    seed_everything(config.machine.seed)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


@pytest.mark.slow
def test_resume_continues_step_optimizers_and_strategy_state(scene_dir, tmp_path):
    from garo_ns.tools.eval import evaluate

    first = _setup(_resume_config(scene_dir, tmp_path, 40, "part1"))
    first.train()
    saved_state = copy.deepcopy(first.pipeline.model.strategy_state)  # every entry, tensors or not
    assert torch.is_tensor(saved_state["garo_grad"]) and saved_state["garo_count"].sum() > 0
    ckpt_dir = first.config.get_checkpoint_dir()
    assert (ckpt_dir / "step-000000039.ckpt").exists()

    # nerfstudio's max_num_iterations counts the iterations of this invocation: 40 more after resuming.
    resumed = _setup(_resume_config(scene_dir, tmp_path, 40, "part2", load_dir=ckpt_dir))
    model = resumed.pipeline.model
    assert resumed._start_step == 40 and model.step == 39  # the real step, not splatfacto's 30000
    assert model.strategy_state.keys() == saved_state.keys()
    for key, value in saved_state.items():  # GARO accumulators, last GARO step, static classification
        got = model.strategy_state[key]
        if torch.is_tensor(value):
            assert torch.equal(got.cpu(), value.cpu()), key
        else:
            assert got == value, key
    for name, param in model.gauss_params.items():  # optimizers hold the loaded tensors themselves
        assert resumed.optimizers.optimizers[name].param_groups[0]["params"][0] is param
    resumed.train()

    whole = _setup(_resume_config(scene_dir, tmp_path, 80, "whole"))
    whole.train()

    # Adam's step count of the deformation network continued across the resume (it only steps once
    # the deformation is on, from step 20): equal to the uninterrupted run's.
    def adam_steps(trainer):
        opt = trainer.optimizers.optimizers["deformation"]
        return int(opt.state[opt.param_groups[0]["params"][0]]["step"])

    assert adam_steps(resumed) == adam_steps(whole) == 60
    assert sorted(p.name for p in resumed.config.get_checkpoint_dir().iterdir())[-1] == "step-000000079.ckpt"
    # Same recipe, same number of steps; only the order of training images differs (nerfstudio does
    # not checkpoint its sampler), so quality agrees closely rather than bit for bit.
    a = evaluate(resumed.pipeline, scene_dir, "test")["psnr"]
    b = evaluate(whole.pipeline, scene_dir, "test")["psnr"]
    assert abs(a - b) < 1.5, (a, b)


@pytest.mark.slow
def test_truncated_checkpoint_is_one_line_and_left_alone(garo_run, tmp_path):
    import yaml

    config = yaml.load(garo_run["config_path"].read_text(), Loader=yaml.Loader)
    source = config.get_checkpoint_dir()
    config.output_dir = tmp_path / "copy"
    target = config.get_checkpoint_dir()
    target.mkdir(parents=True)
    ckpt = sorted(source.glob("*.ckpt"))[-1]
    data = ckpt.read_bytes()
    (target / ckpt.name).write_bytes(data[: len(data) // 2])  # a copy cut short, as by a full disk
    cfg = config.get_base_dir() / "config.yml"
    cfg.write_text(yaml.dump(config), encoding="utf-8")
    before = (target / ckpt.name).read_bytes()
    out = _cli(BIN / "garo-eval", "--load-config", cfg, "--split", "test", "--output-path", tmp_path / "e.json")
    assert out.returncode != 0
    assert "Traceback" not in out.stderr and "cannot load the checkpoint" in out.stderr, out.stderr[-2000:]
    assert len([line for line in out.stderr.splitlines() if "cannot load" in line]) == 1
    assert (target / ckpt.name).read_bytes() == before and not (tmp_path / "e.json").exists()
    assert ckpt.read_bytes() == data  # the original is untouched


def _config_with_scene(garo_run, tmp_path, datamanager_data, dataparser_data) -> Path:
    """The run's config.yml as `ns-train --data` writes it (the scene on the datamanager), saved elsewhere."""
    import yaml

    config = copy.deepcopy(garo_run["config"])
    config.pipeline.datamanager.data = datamanager_data
    config.pipeline.datamanager.dataparser.data = dataparser_data
    path = tmp_path / "cfg" / "config.yml"
    path.parent.mkdir(parents=True)
    path.write_text(yaml.dump(config))
    return path


def test_camera_path_reads_the_scene_the_run_was_trained_with(garo_run, tmp_path, monkeypatch):
    from garo_ns.tools import camera_path

    scene = garo_run["config"].pipeline.datamanager.dataparser.data
    cfg = _config_with_scene(garo_run, tmp_path, Path(scene), Path("data/dnerf/lego"))
    monkeypatch.chdir(tmp_path)  # where no data/dnerf/lego exists
    monkeypatch.setattr(sys, "argv", ["garo-camera-path", "--load-config", str(cfg), "--output", "p.json"])
    camera_path.main()
    first = json.loads((tmp_path / "p.json").read_text())["camera_path"][0]
    assert first["render_time"] == 0.0 and len(first["camera_to_world"]) == 16


def test_eval_data_replaces_a_scene_that_moved(garo_run, tmp_path):
    from garo_ns.tools.eval import EvalArgs, run

    scene = Path(garo_run["config"].pipeline.datamanager.dataparser.data)
    gone = tmp_path / "moved-away"
    cfg = _config_with_scene(garo_run, tmp_path, gone, gone)
    result = run(EvalArgs(load_config=cfg, split="test", output_path=tmp_path / "eval.json", data=scene))
    assert result["psnr"] == pytest.approx(garo_run["eval"]["psnr"], abs=1e-3)
    # What a viewer waits for: the load (the time table built there) and the first frame, each timed.
    assert 0 < result["load_seconds"] < 600 and 0 < result["first_frame_seconds"] < result["load_seconds"] + 600
    with pytest.raises(GaroInputError, match="not a folder"):
        run(EvalArgs(load_config=cfg, split="test", output_path=tmp_path / "e2.json", data=gone))


def test_along_capture_follows_the_cameras_in_time_and_shifts_them_sideways():
    from garo_ns.errors import GaroInputError
    from garo_ns.tools.camera_path import along_capture

    rng = np.random.default_rng(0)
    n = 7
    c2w = np.zeros((n, 3, 4))
    for k in range(n):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        c2w[k, :, :3] = q * np.sign(np.linalg.det(q))
        c2w[k, :, 3] = rng.normal(size=3) * 3
    times = rng.permutation(n) / (n - 1)
    order = np.argsort(times)
    path = along_capture(c2w, times, fy=50.0, width=80, height=60, frames=100, seconds=2.0)
    entries = path["camera_path"]
    assert [e["render_time"] for e in entries] == sorted(times.tolist())
    for e, k in zip(entries, order):  # shift 0: the captured poses themselves
        np.testing.assert_allclose(np.array(e["camera_to_world"]).reshape(4, 4)[:3], c2w[k])
    shifted = along_capture(c2w, times, 50.0, 80, 60, frames=100, seconds=2.0, shift=0.1)["camera_path"]
    for e, s, k in zip(entries, shifted, order):
        a, b = np.array(e["camera_to_world"]).reshape(4, 4), np.array(s["camera_to_world"]).reshape(4, 4)
        np.testing.assert_allclose(b[:3, :3], a[:3, :3])  # same orientation
        move = b[:3, 3] - a[:3, 3]
        np.testing.assert_allclose(move, 0.1 * np.linalg.norm(c2w[k, :, 3]) * c2w[k, :, 0], atol=1e-12)
    fewer = along_capture(c2w, times, 50.0, 80, 60, frames=3, seconds=1.0)["camera_path"]
    assert [e["render_time"] for e in fewer] == [0.0, 0.5, 1.0]  # first, middle and last in time
    for bad in ({"frames": 0}, {"seconds": 0.0}, {"shift": float("nan")}):
        with pytest.raises(GaroInputError):
            along_capture(c2w, times, 50.0, 80, 60, **{"frames": 5, "seconds": 1.0, **bad})


def test_camera_path_along_capture_reads_the_run_s_training_cameras(garo_run, tmp_path, monkeypatch):
    from garo_ns.tools import camera_path

    out = tmp_path / "along.json"
    argv = ["garo-camera-path", "--load-config", str(garo_run["config_path"]), "--output", str(out)]
    monkeypatch.setattr(sys, "argv", argv + ["--along-capture", "--frames", "1000", "--shift", "0.05"])
    camera_path.main()
    cams = garo_run["trainer"].pipeline.datamanager.train_dataset.cameras
    entries = json.loads(out.read_text())["camera_path"]
    assert len(entries) == len(cams)
    assert [e["render_time"] for e in entries] == pytest.approx(sorted(cams.times.reshape(-1).tolist()))


def test_eval_times_the_split_it_scores_by_the_fps_protocol(garo_run, tmp_path, monkeypatch, capsys):
    """Speed beside the error: garo-eval's JSON holds the FPS protocol's figures for the views it scored (on a CPU
    through the reference rasterizer), the model's size and the machine that timed them; `--no-fps` leaves them
    out, and `--model-set` scores the run with other settings (an unknown one refused before the run loads)."""
    from garo_ns.tools import eval as garo_eval
    from garo_ns.tools.fps import model_size_mb

    cfg, out = garo_run["config_path"], tmp_path / "eval.json"
    monkeypatch.setattr(
        sys, "argv", ["garo-eval", "--load-config", str(cfg), "--split", "test", "--output-path", str(out)]
    )
    garo_eval.main()
    assert "FPS " in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["fps"] == pytest.approx(1000.0 / result["ms_per_view"])
    assert result["views"] == result["n_images"] == 6 and result["repeats"] == 3
    assert min(result["ms_deformation"], result["ms_rasterization"], result["ms_per_view_same_time"]) > 0
    assert result["model_size_mb"] == pytest.approx(model_size_mb(garo_run["trainer"].pipeline.model))
    assert result["machine"]["torch"] == torch.__version__ and result["machine"]["cpu_count"] >= 1
    assert (
        result["machine"]["rasterizer"] in ("reference", "gsplat CUDA") and "5 warm-up views" in result["fps_protocol"]
    )
    assert result["model_settings"] == {}
    # --model-set: the run scored with other settings, here the plain render (no switch left to the model).
    plain_render = ["static_skip=False", "time_table=False", "cuda_graph=False", "lean_raster=False"]
    args = garo_eval.EvalArgs(load_config=cfg, output_path=tmp_path / "plain.json", fps=False, model_set=plain_render)
    plain = garo_eval.run(args)
    assert "fps" not in plain and "machine" not in plain and plain["psnr"] == pytest.approx(result["psnr"], abs=0.5)
    assert plain["model_settings"] == {
        "static_skip": False,
        "time_table": False,
        "cuda_graph": False,
        "lean_raster": False,
    }
    assert not any(plain["render_switches"]["in_use"][k] for k in ("static_skip", "time_table"))
    with pytest.raises(SystemExit, match="--model-set expects NAME=VALUE"):  # before the run is loaded
        garo_eval.run(garo_eval.EvalArgs(load_config=tmp_path / "absent.yml", model_set=["no_such_setting=1"]))
