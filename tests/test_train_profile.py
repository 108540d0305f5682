"""The training-step profile: its arithmetic on marks with known times, and a short CPU run through nerfstudio."""

from __future__ import annotations

import json

import pytest
import torch

from garo_ns.bench.profile_docs import markdown_table
from garo_ns.bench.step_phases import PHASES, Mark, StepMarks, phase_times, summarise_window


def _mark(t_ms: float) -> Mark:
    m = Mark(cuda=False)
    m.host = t_ms / 1e3
    return m


def _step(offset: float = 0.0) -> StepMarks:
    """A step of known phases (ms): 0-100 the step; forward parts, a backward cut at 40 / 45 / 60, optimizers
    from 60, the after-step part from 75 with the strategy inside it."""
    s = StepMarks()
    at = lambda t: _mark(offset + t)  # noqa: E731
    s.add("step", at(0), at(100))
    s.add("optimizers", at(1), at(2))  # zero_grad, before the forward
    s.add("data", at(2), at(5))
    s.add("deformation_forward", at(5), at(15))
    s.add("rasterization_forward", at(15), at(25))
    s.add("metrics", at(25), at(27))
    s.add("loss_forward", at(27), at(38))
    s.points.update(backward_start=at(40), render_grad=at(45), splats_grad=at(60), optimizer_step=at(62))
    s.add("optimizers", at(62), at(70))
    s.points["after_start"] = at(75)
    s.add("strategy", at(80), at(90))
    return s


def test_phase_times_cut_the_backward_and_subtract_nested_phases():
    t = phase_times(_step(), _mark(104))["host"]
    assert t["loss_backward"] == pytest.approx(5)
    assert t["rasterization_backward"] == pytest.approx(15)
    assert t["deformation_backward"] == pytest.approx(2)  # to the optimizer step, not to zero_grad
    assert t["optimizers"] == pytest.approx(9)  # zero_grad and the step together
    assert t["strategy"] == pytest.approx(10)
    assert t["after_step_other"] == pytest.approx(15)  # 75..100 less the strategy
    assert t["loop_between_steps"] == pytest.approx(4)
    assert t["step"] == pytest.approx(100)
    # Without a CUDA event the device column is the host clock.
    assert phase_times(_step(), None)["device"]["deformation_forward"] == pytest.approx(10)


def test_window_means_and_unlabelled_share():
    out = summarise_window([_step(0), _step(110)])
    assert out["host_ms"]["loop_between_steps"] == pytest.approx(10)  # only between the two steps
    labelled = 3 + 10 + 10 + 2 + 11 + 5 + 15 + 2 + 9 + 10 + 15
    assert out["device_ms_unlabelled_in_step"] == pytest.approx(100 - labelled)
    table = markdown_table({"windows": [{"step": 10, "gaussians": 5, **out}]})
    assert "| deformation_forward | 10.00 (10.00) |" in table


@pytest.mark.slow
def test_profile_of_a_short_cpu_training(tmp_path):
    from garo_ns.bench.train_profile import main
    from garo_ns.tools.scene import SceneSpec, generate_scene

    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=24, n_train=10, n_val=2, n_test=2))
    out = tmp_path / "profile.json"
    args = ["--scene", str(scene), "--quick", "--steps", "24", "--windows", "2", "14", "40", "--device", "cpu"]
    args += ["--plain-steps", "2", "--phase-steps", "3", "--host-op-steps", "2", "--score", "--split", "val"]
    args += ["--timeline-every", "8"]
    args += ["--set", "deform_cuda_graph=True", "loss_cuda_graph=True"]  # on the CPU: the eager path
    main(args + ["--work-dir", str(tmp_path / "runs"), "--output", str(out)])
    result = json.loads(out.read_text())
    assert [w["step"] for w in result["windows"]] == [2, 14]  # 40 is past the end
    late = result["windows"][1]  # after the deformation warm-up (a quarter of the steps)
    for phase in PHASES:
        if phase != "strategy":  # the strategy may have nothing to do in 3 steps
            assert late["host_ms"][phase] >= 0, phase
    assert late["host_ms"]["deformation_forward"] > 0 and late["host_ms"]["deformation_backward"] > 0
    inside = sum(v for k, v in late["host_ms"].items() if k not in ("step", "loop_between_steps"))
    assert inside <= late["host_ms"]["step"] + 1e-6
    assert late["plain_ms_per_step"] > 0 and result["steps_per_second"] > 0
    assert "| rasterization_backward |" in out.with_suffix(".md").read_text()
    # The host's pass: on a CPU no launches, and its costliest operations named with their calls per step.
    host = late["host_ops"]
    assert host["launches_per_step"] == 0 and host["ms_per_step"] > 0
    top = host["top_host_ops"]
    assert 0 < len(top) <= 12 and all(op["calls_per_step"] > 0 and op["self_ms_per_step"] >= 0 for op in top)
    assert [op["self_ms_per_step"] for op in top] == sorted((op["self_ms_per_step"] for op in top), reverse=True)
    assert sum(op["self_ms_per_step"] for op in top) <= host["ms_per_step"]  # own times: within the steps' wall
    assert result["score"]["psnr"] > 10  # the scored model renders the scene, not noise
    assert result["cuda_memory_mib"] is None  # a CPU run has no CUDA allocator to report
    assert result["score"]["split"] == "val" and result["score"]["background"] == "black"
    assert result["model_settings"] == {"deform_cuda_graph": True, "loss_cuda_graph": True}
    timeline = result["timeline"]
    assert [row["step"] for row in timeline] == [8, 16, 24]
    seconds = [row["seconds"] for row in timeline]
    assert 0 < seconds[0] < seconds[1] < seconds[2] <= result["train_seconds"]
    assert 0 <= result["seconds_before_first_step"] < result["train_seconds"]
    # The finished model's render choice runs in the last step's callback and is timed apart from the steps.
    assert 0 < result["render_choice_seconds"] < seconds[2] - seconds[1]
    assert "time_table" in result["render_choice_record"]["tried_db"]  # what it measured comes with it


def test_model_overrides_are_literals_of_known_settings():
    from garo_ns.tools.eval import model_overrides

    assert model_overrides(["rho_max=0.05", "time_table=None", "rasterizer=reference"]) == {
        "rho_max": 0.05,
        "time_table": None,
        "rasterizer": "reference",
    }
    for bad in (["no_such_setting=1"], ["rho_max"]):
        with pytest.raises(SystemExit, match="NAME=VALUE"):
            model_overrides(bad)


def test_the_docs_profile_block_is_written_from_the_committed_files(tmp_path):
    from pathlib import Path

    from garo_ns.bench.profile_docs import DOCS_BEGIN, DOCS_END, docs_block

    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "benchmarks.md").read_text()
    block = text.split(DOCS_BEGIN, 1)[1].split(DOCS_END, 1)[0]
    files = sorted((root / "benchmarks" / "results").glob("train_profile_*.json"))
    files = [f for f in files if f.name in block]  # the block names each file it shows
    assert files and block.strip() == docs_block(files).strip()


def _profile(path, seconds, steps=40_000, psnr=37.0, scene="jj", extra=None):
    import json

    path.write_text(
        json.dumps(
            {
                "scene": scene,
                "environment": {"gpu": "GPU X", "git_commit": "abc"},
                "steps": steps,
                "train_seconds": seconds,
                "steps_per_second": steps / seconds,
                "score": {"psnr": psnr, "lpips": 0.01},
                "gaussians_final": 10,
                **(extra or {}),
            }
        )
    )
    return path


def test_train_speed_compares_the_mean_of_each_side(tmp_path):
    from garo_ns.bench.train_speed import main

    old = _profile(tmp_path / "old.json", 600.0, psnr=37.0)
    new1 = _profile(tmp_path / "new1.json", 300.0, psnr=37.2)
    new2 = _profile(tmp_path / "new2.json", 200.0, steps=20_000, psnr=37.4)  # a half-length run: 400 s per 40k
    out = tmp_path / "speed.json"
    result, table = main(["--before", f"m={old}", "--after", f"m={new1}", f"m={new2}", "--output", str(out)])
    m = result["methods"]["m"]
    assert m["before"]["minutes_per_40k"] == 10.0 and abs(m["after"]["minutes_per_40k"] - 350.0 / 60) < 1e-9
    assert abs(m["speedup"] - 600 / 350) < 1e-9 and abs(m["psnr_change_db"] - 0.3) < 1e-9
    assert "1.71x faster, PSNR +0.30 dB" in table and out.with_suffix(".md").read_text() == table
    with pytest.raises(SystemExit, match="METHOD=FILE"):
        main(["--after", str(new1), "--output", str(out)])


def test_the_gpu_busy_share_counts_each_kernel_once():
    """torch's profiler lists a kernel twice: as a GPU event and inside the device time of the CPU event that
    launched it (a user annotation's GPU range spans kernels too). The share and the top list read GPU events only."""
    from types import SimpleNamespace

    from garo_ns.bench.kernel_table import kernel_share, top_kernels

    cpu, cuda = torch.autograd.DeviceType.CPU, torch.autograd.DeviceType.CUDA

    def event(key, device_type, us, count=2, annotation=False):
        return SimpleNamespace(
            key=key, device_type=device_type, self_device_time_total=us, count=count, is_user_annotation=annotation
        )

    events = [
        event("aten::mm", cpu, 3000.0),  # its kernel's time, which the GPU event below holds again
        event("gemm_kernel", cuda, 3000.0),
        event("relu_kernel", cuda, 1000.0, count=4),
        event("phase: loss", cuda, 4000.0, annotation=True),
    ]
    prof = SimpleNamespace(key_averages=lambda: events)
    assert abs(kernel_share(prof, wall_ms=8.0) - 0.5) < 1e-12  # 4 ms of kernels in 8 ms, not 7 or 11
    top = top_kernels(prof, steps=2)
    assert [k["name"] for k in top] == ["gemm_kernel", "relu_kernel"]
    assert top[0]["ms_per_step"] == 1.5 and top[1]["calls_per_step"] == 2.0
    table = markdown_table({"windows": [{"step": 5, "gaussians": 1, "gpu_kernel_share": 0.6}]})
    assert "| GPU busy share | 0.60 |" in table  # an older file's key, the same measure
    window = {"step": 30_000, "gaussians": 1, "gpu_busy_share": 0.5, "top_kernels": top}
    table = markdown_table({"windows": [window]})
    assert "| GPU busy share | 0.50 |" in table and "GPU events at step 30,000" in table
    assert "| `gemm_kernel` | 1.500 | 1.0 |" in table


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: kernels")
def test_on_a_gpu_the_busy_share_reads_the_gpus_own_events():
    """Where the profiler records the CPU too, every kernel's time sits once under the aten op that launched it and
    once as the GPU's own event (the profiler's own events add theirs): the share must sum the GPU's alone."""
    from garo_ns.bench.kernel_table import kernel_share

    a = torch.randn(2048, 2048, device="cuda")
    for _ in range(2):  # warm: a first call's lazy module loading shows as events of its own
        torch.relu(a @ a)
    torch.cuda.synchronize()
    with torch.profiler.profile(
        activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    ) as prof:
        for _ in range(5):
            a = torch.relu(a @ a) * 1e-3
        torch.cuda.synchronize()
    events = prof.key_averages()
    launched = sum(float(e.self_device_time_total or 0.0) for e in events if e.key.startswith("aten::"))
    every = sum(float(e.self_device_time_total or 0.0) for e in events)
    share = kernel_share(prof, wall_ms=1e-3)  # kernel microseconds, per this wall
    assert share > 0 and launched == pytest.approx(share, rel=0.01) and every >= 1.99 * share


def test_a_run_without_windows_shows_its_timeline_not_an_empty_table():
    timeline = [{"step": 1000 * k, "seconds": 2.0 * k, "gaussians": 1} for k in range(1, 13)]
    table = markdown_table({"windows": [], "steps": 12_000, "timeline": timeline})
    assert "| step | 5,000 | 10,000 | 12,000 |" in table and "| seconds | 10 | 20 | 24 |" in table
    assert "phase" not in table
    assert "no timeline" in markdown_table({"windows": [], "steps": 10})


def test_train_speed_weighs_each_scene_once_in_a_sides_means(tmp_path):
    from garo_ns.bench.train_speed import main

    runs = [
        _profile(tmp_path / "a1.json", 300.0, psnr=40.0, scene="a"),
        _profile(tmp_path / "a2.json", 360.0, psnr=41.0, scene="a"),  # scene a run twice: its mean counts once
        _profile(tmp_path / "b.json", 240.0, psnr=36.0, scene="b"),
    ]
    result, _ = main(["--after"] + [f"m={p}" for p in runs] + ["--output", str(tmp_path / "speed.json")])
    side = result["methods"]["m"]["after"]
    assert abs(side["minutes_per_40k"] - (330.0 + 240.0) / 2 / 60) < 1e-9
    assert abs(side["psnr"] - 38.25) < 1e-9 and side["slowest_minutes_per_40k"] == 6.0
    assert abs(side["steps_per_second"] - (40_000 / 300 + 40_000 / 360 + 2 * 40_000 / 240) / 4) < 1e-9


def test_train_speed_compares_the_scenes_both_sides_ran_and_the_render_choice(tmp_path):
    from garo_ns.bench.train_speed import main

    before = [_profile(tmp_path / f"b{s}.json", 100.0 * (k + 1), psnr=37.0 + k, scene=s) for k, s in enumerate("ab")]
    after = [
        _profile(tmp_path / "aa.json", 70.0, psnr=37.5, scene="a", extra={"render_choice_seconds": 30.0}),
        _profile(tmp_path / "ab.json", 100.0, psnr=38.0, scene="b"),  # a file from before the choice was timed
        _profile(tmp_path / "ac.json", 900.0, psnr=20.0, scene="c"),  # no "before" run: not compared
    ]
    out = tmp_path / "speed.json"
    args = ["--before"] + [f"m={p}" for p in before] + ["--after"] + [f"m={p}" for p in after]
    result, table = main(args + ["--output", str(out), "--date", "2026-01-01"])
    m = result["methods"]["m"]
    assert m["scenes_compared"] == ["a", "b"] and result["date"] == "2026-01-01"
    assert abs(m["speedup"] - 150 / 85) < 1e-9 and abs(m["psnr_change_db"] - 0.25) < 1e-9
    runs = {r["scene"]: r for r in m["after"]["runs"]}
    assert runs["a"]["render_choice_seconds"] == 30.0 and runs["b"]["render_choice_seconds"] is None
    assert abs(runs["a"]["minutes_per_40k_steps"] - 40 / 60) < 1e-9 and runs["c"]["minutes_per_40k_steps"] is None
    assert m["speedup_steps"] is None  # the "before" runs do not say what their render choice took
    assert "| m | after | a | abc | - | 1.17 | 30 | " in table and "| a, b | | | 1.76x faster, PSNR +0.25 dB" in table


def test_train_speed_states_the_ratio_over_the_fields_warm_up(tmp_path):
    """Steps 1k to 3k run the same code in two recipes that differ only in the field: their ratio there measures
    the machines, stated beside the recipes' ratio; a run whose timeline lacks those steps leaves it unknown."""
    from garo_ns.bench.train_speed import main

    def timeline(warmup_s):  # 1 s per 1000 steps, except steps 1k to 3k
        return [
            {"step": 1000, "seconds": 1.0},
            {"step": 3000, "seconds": 1.0 + warmup_s},
            {"step": 40_000, "seconds": 50},
        ]

    before = _profile(tmp_path / "b.json", 50.0, extra={"timeline": timeline(2.2)})
    after = _profile(tmp_path / "a.json", 50.0, extra={"timeline": timeline(2.0)})
    result, table = main(["--before", f"m={before}", "--after", f"m={after}", "--output", str(tmp_path / "s.json")])
    m = result["methods"]["m"]
    assert abs(m["after"]["runs"][0]["warmup_ms_per_step"] - 1.0) < 1e-9
    assert abs(m["speedup_warmup"] - 1.1) < 1e-9 and "1.10x over steps 1k to 3k" in table
    bare = _profile(tmp_path / "c.json", 50.0)
    result, table = main(["--before", f"m={bare}", "--after", f"m={after}", "--output", str(tmp_path / "s.json")])
    assert result["methods"]["m"]["speedup_warmup"] is None and "steps 1k to 3k" not in table


def test_the_committed_train_speed_is_its_files_summary():
    import json
    from pathlib import Path

    from garo_ns.bench.train_speed import summary

    results = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
    for committed in results.glob("train_speed_*.json"):
        data = json.loads(committed.read_text())
        sides = {
            side: {m: [results / r["file"] for r in e[side]["runs"]] for m, e in data["methods"].items() if side in e}
            for side in ("before", "after")
        }
        assert summary(sides["before"], sides["after"]) == {k: data[k] for k in ("gpus", "methods")}


def test_the_harness_runs_none_of_the_loop_work_of_ns_train(tmp_path):
    from garo_ns.bench.train_profile import loop_work
    from garo_ns.tools.train import make_config

    config = make_config("garo-deform", tmp_path, tmp_path / "out")
    config.max_num_iterations = 40_000
    loop_work(config)
    assert config.steps_per_save == 40_000 and config.steps_per_eval_image > 40_000
    assert not config.logging.local_writer.enable


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the Adam graph is used on CUDA runs")
def test_a_cuda_run_replays_its_adam_graph_once_the_gaussians_settle(tmp_path):
    from garo_ns.bench.train_profile import main
    from garo_ns.tools.scene import SceneSpec, generate_scene

    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=12, n_val=2, n_test=2))
    args = ["--scene", str(scene), "--quick", "--steps", "600", "--windows", "100000", "--device", "cuda"]
    args += ["--score", "--split", "val", "--set", "adam_cuda_graph=True", "--work-dir", str(tmp_path / "runs")]
    result = main(args + ["--output", str(tmp_path / "profile.json")])
    counts = result["adam_graph"]
    # Densification stops at 60% of the steps (360), its last refinement at 340 (every 20 steps): stable 100 steps
    # later, replayed from then on (160 replays on an H100).
    assert counts["captures"] >= 1 and 100 <= counts["replays"] <= 600 - 340 - 100 + 1
    assert result["score"]["psnr"] > 10
    memory = result["cuda_memory_mib"]
    assert 0 < memory["peak_allocated"] <= memory["peak_reserved"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: kernel launches")
def test_a_cuda_runs_host_pass_counts_its_launches(tmp_path):
    from garo_ns.bench.train_profile import main
    from garo_ns.tools.scene import SceneSpec, generate_scene

    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=12, n_val=2, n_test=2))
    args = ["--scene", str(scene), "--quick", "--steps", "200", "--windows", "180", "--device", "cuda"]
    args += ["--plain-steps", "2", "--phase-steps", "2", "--profiler-steps", "2", "--host-op-steps", "2"]
    result = main(args + ["--work-dir", str(tmp_path / "runs"), "--output", str(tmp_path / "profile.json")])
    (window,) = result["windows"]
    host = window["host_ops"]
    # A step launches kernels (and graphs) by the dozen; the kernels themselves are not host operations.
    assert host["launches_per_step"] > 10 and "cudaLaunchKernel" in host["runtime_calls_per_step"]
    assert all(not op["name"].startswith("cuda") for op in host["top_host_ops"])
    assert 0 < window["gpu_busy_share"] <= 1
    top = window["top_kernels"]
    assert (
        top and sum(k["ms_per_step"] for k in top) <= window["gpu_busy_share"] * window["profiled_ms_per_step"] + 1e-6
    )


def test_train_speed_takes_a_benchmark_arm_only_where_it_trained_alone(tmp_path):
    """A benchmark result trained with `--arms-per-gpu 1` gives each arm's whole training as a run; one whose arms
    shared a GPU is refused, as is an arm it did not train."""
    import json

    import pytest

    from garo_ns.bench.train_speed import main

    arm = {
        "iterations": 40_000,
        "train_seconds": 240.0,
        "train_steps_per_second": 166.7,
        "psnr": 40.0,
        "lpips": 0.01,
        "num_gaussians": 50_000,
        "trained_in": "this run",
    }
    result = {
        "gpu": "GPU X",
        "git_commit": "abc",
        "scene": "s",
        "model_settings": ["time_table=False"],
        "arms_per_gpu": 1,
        "variants": {"garo-deform": arm},
    }
    lone = tmp_path / "table1_s_X.json"
    lone.write_text(json.dumps(result))
    out, _ = main(["--after", f"garo-deform={lone}", "--output", str(tmp_path / "t.json")])
    row = out["methods"]["garo-deform"]["after"]["runs"][0]
    assert row["minutes_per_40k"] == 4.0 and row["model_settings"] == {"time_table": "False"} and row["psnr"] == 40.0
    shared = tmp_path / "table1_s2_X.json"
    shared.write_text(json.dumps({**result, "arms_per_gpu": 3}))
    with pytest.raises(SystemExit, match="3 to a GPU at once"):
        main(["--after", f"garo-deform={shared}", "--output", str(tmp_path / "t.json")])
    with pytest.raises(SystemExit, match="no arm 'garo-compact'"):
        main(["--after", f"garo-compact={lone}", "--output", str(tmp_path / "t.json")])
