"""The benchmark command end to end on a CPU (tiny scene, few steps, reference rasterizer), so it cannot rot."""

from __future__ import annotations

import json

from garo_ns.benchmark import BenchArgs, run
from garo_ns.scene import SceneSpec, generate_scene


def test_benchmark_smoke_writes_json_table_and_plot(tmp_path):
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    out = tmp_path / "results" / "smoke.json"
    args = BenchArgs(
        scene=scene,
        split="val",
        output=out,
        work_dir=tmp_path / "runs",
        iterations=40,
        device="cpu",
        quick=True,
        warmup_views=1,
        timing_repeats=1,
    )
    run(args)
    result = json.loads(out.read_text())
    assert set(result["variants"]) == {"deform-splatfacto", "garo-deform"}
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
        assert v["iterations"] == 40 and v["shortened"] is True and v["fps"] > 0 and v["psnr"] > 5
    for key in ("gpu", "torch", "git_commit", "scene", "split", "background"):
        assert key in result
    assert result["split"] == "val" and "fps_ratio" in result["garo_vs_baseline"]
    assert out.with_suffix(".md").read_text().count("|") > 20
    assert out.with_suffix(".png").stat().st_size > 1000
