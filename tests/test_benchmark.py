"""The benchmark command end to end on a CPU (tiny scene, few steps, reference rasterizer), so it cannot rot."""

from __future__ import annotations

import json

import pytest
import torch

from garo_ns.bench.benchmark import SPEED_ROWS, BenchArgs, psnr_difference, run, split_variant
from garo_ns.tools.scene import SceneSpec, generate_scene


@pytest.mark.slow
def test_benchmark_smoke_writes_json_table_and_plot(tmp_path):
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    out = tmp_path / "results" / "smoke.json"
    args = BenchArgs(
        scene=scene,
        split="val",
        output=out,
        work_dir=tmp_path / "runs",
        variants=["deform-splatfacto", "garo-deform", "garo-prune0.3", "garo-deform+lean+static", "garo-deform+auto"],
        speed=True,
        iterations=40,
        device="cpu",
        quick=True,
        warmup_views=1,
        timing_repeats=1,
    )
    run(args)
    result = json.loads(out.read_text())
    from garo_ns.tools.eval import load_split

    _, images = load_split(scene, "val", torch.zeros(3))  # what a model that draws nothing scores
    blank_psnr = sum(float(-10 * torch.log10((img**2).mean())) for img in images) / len(images)
    trained = ["deform-splatfacto", "garo-deform", "garo-prune0.3"]
    rows = ["", *SPEED_ROWS]
    assert "+graph" in rows and "+lean" in rows and "+static+graph+lean+fp16" in rows
    expected = [t + r for t in trained for r in rows]
    assert list(result["variants"]) == expected + ["garo-deform+lean+static", "garo-deform+auto"]
    # Render-time rows reuse their variant's training: one run per trained variant.
    assert sorted(p.name for p in (tmp_path / "runs").glob("*.record.json")) == sorted(
        f"{t}.record.json" for t in trained
    )
    # Each trained variant's rows are also written as soon as they are measured.
    for t in trained:
        landed = json.loads((tmp_path / "runs" / f"{t}.eval.json").read_text())
        assert set(landed) == {n for n in result["variants"] if n.split("+")[0] == t}
        assert landed[t]["psnr"] == result["variants"][t]["psnr"]
    for v in result["variants"].values():
        for key in (
            "psnr",
            "ssim",
            "lpips",
            "fps",
            "num_gaussians",
            "peak_memory_mb",
            "model_size_mb",
            "train_seconds",
            "iterations",
        ):
            assert key in v
        assert v["iterations"] == 40 and v["shortened"] is True and v["fps"] > 0
        assert v["psnr"] > blank_psnr + 1, (v["psnr"], blank_psnr)  # better than rendering the background
        assert v["static_fraction"] is not None and v["ms_per_view_same_time"] > 0
        profile = v["profile"]
        stages = ("deformation", "projection", "color", "sorting", "compositing")
        assert all(profile[f"ms_{s}"] > 0 for s in stages + ("frame",)), profile  # each stage ran and was timed
        overhead = profile["ms_frame"] - sum(profile[f"ms_{s}"] for s in stages)
        assert profile["ms_python_overhead"] == pytest.approx(max(0.0, overhead), abs=1e-9)
        assert profile["backend"] == "reference"
    variants = result["variants"]
    settings = {n: v["render_settings"] for n, v in variants.items()}
    default = settings["garo-deform"]["static_threshold"]
    assert settings["garo-deform+static+graph+lean+fp16"] == {
        "static_skip": True,
        "cuda_graph": True,
        "lean_raster": True,
        "time_table": False,
        "frame_graph": False,
        "static_threshold": default,
        "storage_fp16": True,
    }
    assert settings["garo-deform"] == {
        "static_skip": False,
        "cuda_graph": False,
        "lean_raster": False,
        "time_table": False,
        "frame_graph": False,
        "static_threshold": default,
        "storage_fp16": False,
    }
    # The static classification of the trained parameters again after the fp16 row (they were put back).
    assert variants["garo-deform+lean+static"]["static_fraction"] == variants["garo-deform+static"]["static_fraction"]
    # +auto leaves every switch to the finished model: on a CPU no graph, no lean path, fp32 field.
    used = variants["garo-deform+auto"]["render_switches_used"]
    assert settings["garo-deform+auto"]["static_skip"] is None and settings["garo-deform+auto"]["cuda_graph"] is None
    assert (used["cuda_graph"], used["lean_raster"]) == (False, False) and "render_precision" not in used
    assert variants["garo-deform"]["render_switches_used"]["static_skip"] is False  # an explicit row as set
    assert variants["garo-deform+static"]["render_switches_used"]["static_skip"] is True
    for t in trained:
        plain, half = variants[t + "+static+graph+lean"], variants[t + "+static+graph+lean+fp16"]
        assert half["model_size_mb"] < 0.6 * plain["model_size_mb"] and half["storage"].startswith("fp16")
        assert abs(half["psnr"] - plain["psnr"]) < 0.1  # rounding to half precision costs ~nothing
        for row in ("+graph", "+lean"):  # no CUDA: the eager fp32 path, reference raster
            assert variants[t + row]["psnr"] == variants[t]["psnr"]
            assert variants[t + row]["psnr_vs_plain"]["max_abs_db"] == 0.0
        assert "psnr_vs_plain" not in variants[t]  # the plain row is the reference
        assert len(variants[t + "+static"]["psnr_vs_plain"]["per_view_db"]) == len(images)
    # Pruning the least contributing 30% at step 28 leaves fewer Gaussians than GARO alone.
    assert variants["garo-prune0.3"]["num_gaussians"] < variants["garo-deform"]["num_gaussians"]
    # The exact switches on top of the static skip change no pixel (no CUDA: the graph is the eager path).
    assert variants["garo-deform+static+graph"]["psnr"] == variants["garo-deform+static"]["psnr"]
    for key in ("gpu", "torch", "git_commit", "scene", "split", "background"):
        assert key in result
    assert result["split"] == "val" and "fps_ratio" in result["garo_vs_baseline"]
    # Phase 3: the trained variants' plain renders timed again in alternating passes, render rows not.
    for t in trained:
        paired = variants[t]["fps_paired"]
        assert paired["passes"] == 6 and len(paired["pass_ms_per_view"]) == 6 and paired["fps"] > 0
        assert "fps_paired" not in variants[t + "+static"]
    ratio = variants["garo-deform"]["fps_paired"]["fps"] / variants["deform-splatfacto"]["fps_paired"]["fps"]
    assert result["garo_vs_baseline"]["fps_ratio_paired"] == pytest.approx(ratio)
    assert "alternating passes" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".md").read_text().count("|") > 20
    assert out.with_suffix(".png").stat().st_size > 1000


def test_auto_row_leaves_every_switch_to_the_model():
    base, render = split_variant("garo-compact+auto")
    assert base == "garo-compact"
    assert all(render[k] is None for k in ("static_skip", "cuda_graph", "lean_raster", "time_table"))
    assert "render_precision" not in render
    assert render["storage"] == "fp32"


def test_the_frame_graph_row_adds_one_switch_to_the_models_choice():
    assert split_variant("garo-compact")[1]["frame_graph"] is False
    base, render = split_variant("garo-compact+auto+framegraph")
    assert base == "garo-compact" and render["frame_graph"] is True
    assert render == {**split_variant("garo-compact+auto")[1], "frame_graph": True}


def test_a_render_row_selects_its_switches_and_is_compared_view_by_view():
    base, render = split_variant("garo-deform+static+graph+lean")
    assert base == "garo-deform" and render["storage"] == "fp32" and not render["time_table"]
    assert render["static_skip"] and render["cuda_graph"] and render["lean_raster"]
    diff = psnr_difference([30.0, 31.5, 29.99], [30.01, 31.5, 29.98])
    assert diff["per_view_db"] == pytest.approx([-0.01, 0.0, 0.01])
    assert diff["max_abs_db"] == pytest.approx(0.01) and diff["mean_db"] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("deleted", ["tf32", "half"])
def test_a_deleted_precision_row_is_refused_and_no_speed_row_names_it(deleted):
    """tf32 (issue 31) and the fp16 field (`+half`) were deleted as render paths (benchmarks/HISTORY.md): their
    suffixes are unknown switches."""
    assert not any(deleted in row for row in SPEED_ROWS)
    assert len(set(SPEED_ROWS)) == len(SPEED_ROWS)  # no row twice (without tf32, "+graph+tf32" was "+graph")
    with pytest.raises(ValueError, match=rf"unknown render switch '\+{deleted}'"):
        split_variant(f"garo-deform+static+graph+{deleted}")


def test_model_settings_reach_a_loaded_model_and_its_frame_path_and_an_unknown_one_stops_the_run(tmp_path):
    from types import SimpleNamespace

    from garo_ns.garo_model import GaroModelConfig
    from garo_ns.render.frame import FramePath
    from garo_ns.tools.eval import apply_model_settings

    changed = []
    model = SimpleNamespace(
        config=GaroModelConfig(),
        frame=FramePath(),
        switches=SimpleNamespace(parameters_changed=lambda: changed.append(True)),
    )
    model.frame.configure(model.config)
    assert model.frame.table_tf32 is False and model.frame.table_budget_mb == model.config.time_table_budget_mb
    apply_model_settings(model, ["time_table_budget_mb=1024", "time_table_tf32=True"])
    assert model.config.time_table_budget_mb == 1024 and model.config.time_table_tf32 is True
    assert model.frame.table_budget_mb == 1024 and model.frame.table_tf32 is True and changed == [True]
    model.config.time_table_tf32 = False
    apply_model_settings(model, [])  # nothing asked: nothing touched
    assert model.frame.table_tf32 is True and changed == [True]
    scene = tmp_path / "no-scene"  # refused before the scene is read or anything trains
    with pytest.raises(SystemExit, match="NAME=VALUE"):
        run(BenchArgs(scene=scene, work_dir=tmp_path / "runs", model_set=["no_such_setting=1"], device="cpu"))
    assert not (tmp_path / "runs").exists()


def tiny_run(scene, tmp_path, name: str, **settings) -> BenchArgs:
    """A few quick CPU steps on `scene`, no profile, results under tmp_path/<name>."""
    defaults = dict(split="val", iterations=30, device="cpu", quick=True, warmup_views=1, timing_repeats=1)
    return BenchArgs(
        scene=scene,
        output=tmp_path / f"{name}.json",
        work_dir=tmp_path / name,
        profile=False,
        **{**defaults, **settings},
    )


@pytest.mark.slow
def test_an_arm_trained_in_one_run_is_evaluated_in_another(tmp_path):
    """A pair that does not fit one machine hold: run 1 trains and exports the baseline, run 2 trains
    GARO and imports it, and scores both; the imported arm scores as it did where it trained."""
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    first = run(tiny_run(scene, tmp_path, "a", variants=["deform-splatfacto"], export_dir=tmp_path / "export"))
    export = tmp_path / "export" / "deform-splatfacto"
    assert sorted(p.name for p in export.iterdir()) == ["config.yml", "model.ckpt", "record.json"]
    assert "optimizers" not in torch.load(export / "model.ckpt", weights_only=False)

    second = run(tiny_run(scene, tmp_path, "b", variants=["deform-splatfacto", "garo-deform"], pretrained=[export]))
    # Only GARO trained in run 2.
    assert json.loads((tmp_path / "b" / "garo-deform.record.json").read_text()).get("trained_in") is None
    base, garo = second["variants"]["deform-splatfacto"], second["variants"]["garo-deform"]
    assert base["psnr"] == pytest.approx(first["variants"]["deform-splatfacto"]["psnr"], abs=1e-6)
    assert base["num_gaussians"] == first["variants"]["deform-splatfacto"]["num_gaussians"]
    assert base["checkpoint_step"] == first["variants"]["deform-splatfacto"]["checkpoint_step"]
    assert base["trained_in"]["git_commit"] == first["git_commit"] and garo["trained_in"] == "this run"
    assert "fps_ratio" in second["garo_vs_baseline"]
    assert "trained by an earlier run" in (tmp_path / "b.md").read_text()

    with pytest.raises(ValueError, match="steps"):  # a different schedule is no pair
        run(tiny_run(scene, tmp_path, "c", variants=["deform-splatfacto"], pretrained=[export], iterations=31))
    other = generate_scene(tmp_path / "other", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    with pytest.raises(ValueError, match="trained on scene 'scene'"):  # an arm of another scene is no pair
        run(tiny_run(other, tmp_path, "e", variants=["deform-splatfacto"], pretrained=[export]))
    (export / "model.ckpt").unlink()
    with pytest.raises(FileNotFoundError, match="not a benchmark export"):
        run(tiny_run(scene, tmp_path, "d", variants=["deform-splatfacto"], pretrained=[export]))


def test_paired_timing_alternates_and_takes_the_median_pass():
    """Passes run A B, B A, ...; a renderer's one stalled pass does not move its figure."""
    import time

    from garo_ns.bench.timing import paired_fps

    order = []

    def renderer(name, seconds):
        calls = {"n": 0}

        def frame():
            calls["n"] += 1
            order.append(name)
            time.sleep(0.2 if (name == "a" and calls["n"] == 3) else seconds)  # a's 2nd timed pass stalls
            return 2  # views per pass

        return frame

    out = paired_fps({"a": renderer("a", 0.01), "b": renderer("b", 0.02)}, torch.device("cpu"), passes=4, warmup=1)
    assert order == ["a", "b", "a", "b", "b", "a", "a", "b", "b", "a"]
    assert max(out["a"]["pass_ms_per_view"]) > 90  # the stall is recorded ...
    assert out["a"]["ms_per_view_median_pass"] < 10  # ... and does not move the median (5 ms per view)
    assert out["b"]["ms_per_view_median_pass"] == pytest.approx(10.0, rel=0.5)
    assert out["a"]["fps"] == pytest.approx(1000.0 / out["a"]["ms_per_view_median_pass"])


@pytest.mark.slow
def test_a_failing_re_timing_keeps_the_measured_rows(tmp_path, monkeypatch):
    import garo_ns.bench.benchmark as benchmark

    def broken(*args, **kwargs):
        raise RuntimeError("no memory left")

    monkeypatch.setattr(benchmark, "paired_timing", broken)
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    out = tmp_path / "r.json"
    result = run(tiny_run(scene, tmp_path, "r", variants=["deform-splatfacto"], iterations=20))
    assert result["paired_timing_error"] == "RuntimeError: no memory left"
    assert json.loads(out.read_text())["variants"]["deform-splatfacto"]["psnr"] > 0
    assert "fps_paired" not in result["variants"]["deform-splatfacto"]


def test_a_result_names_the_hosts_cpu(tmp_path):
    """Host-bound training runs are compared only where the CPU is known: its model name from the cpuinfo file
    (None where there is none) and its core count are in every result's environment."""
    from garo_ns.bench import benchmark
    from garo_ns.tools.fps import cpu_model

    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9654 96-Core Processor\n")
    assert cpu_model(info) == "AMD EPYC 9654 96-Core Processor"
    assert cpu_model(tmp_path / "absent") is None
    env = benchmark.environment("cpu")
    assert env["cpu_model"] == cpu_model() and env["cpu_count"] >= 1


@pytest.mark.parametrize("per_gpu, most_at_once", [(1, 1), (0, 2)])
def test_arms_wait_for_a_place_on_a_gpu_when_asked(tmp_path, monkeypatch, per_gpu, most_at_once):
    """`--arms-per-gpu 1` trains each arm alone on its GPU (the others wait for one to free up); 0 starts every
    arm at once, round-robin. A failed arm is named after the others have ended."""
    import garo_ns.bench.benchmark as bench

    running, most, placed = [], {}, []

    class Worker:  # ends on its second poll
        def __init__(self, cmd, env, stdout, stderr):
            self.name, self.gpu, self.polls = cmd[cmd.index("--worker") + 1], env["CUDA_VISIBLE_DEVICES"], 0
            self.returncode = None
            running.append(self)
            placed.append((self.name, self.gpu))
            on_gpu = sum(w.gpu == self.gpu for w in running)
            most[self.gpu] = max(most.get(self.gpu, 0), on_gpu)

        def poll(self):
            self.polls += 1
            if self.polls >= 2 and self.returncode is None:
                self.returncode = 3 if self.name == "garo-compact" else 0
                running.remove(self)
            return self.returncode

    monkeypatch.setattr(bench.subprocess, "Popen", Worker)
    monkeypatch.setattr(bench.time, "sleep", lambda s: None)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    args = BenchArgs(scene=tmp_path, work_dir=tmp_path, gpus=[0, 1], arms_per_gpu=per_gpu, device="cuda")
    names = ["deform-splatfacto", "garo-deform", "garo-compact"]
    with pytest.raises(RuntimeError, match="training garo-compact failed"):
        bench.train_arms(args, names, None)
    assert sorted(n for n, _ in placed) == sorted(names) and max(most.values()) == most_at_once
    if per_gpu == 0:
        assert [g for _, g in placed] == ["0", "1", "0"]
    assert bench.arms_per_gpu(args, 3) == most_at_once
