"""benchmarks/deform_mlp.py on the CPU: every CPU-capable deformation path against fp32 eager on a tiny field,
and the result file's fields. The GPU paths (CUDA graphs, torch.compile) are skipped with a reason."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import torch

from garo_ns.deformation import DeformationField

_spec = importlib.util.spec_from_file_location(
    "deform_mlp", Path(__file__).resolve().parents[1] / "benchmarks" / "deform_mlp.py"
)
dm = importlib.util.module_from_spec(_spec)
sys.modules["deform_mlp"] = dm  # its dataclasses look their module up
_spec.loader.exec_module(dm)  # type: ignore[union-attr]

# Largest position-offset difference from fp32 eager, relative to the extent (1.0), per CPU-capable path.
# The cached paths only reassociate float sums; fp16 keeps 11 mantissa bits.
BOUNDS = {
    "fp32": 0.0,
    "fp32_cached": 1e-5,
    "fp16": 2e-3,
    "fp16_cached": 2e-3,
    "render_fp16": 2e-3,
}
CUDA_ONLY = ("compile", "compile+graph") + tuple(f"{p}+graph" for p in BOUNDS)


def tiny_field(time_net: int = 8, depth: int = 4, skip: int = 1) -> DeformationField:
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=depth, width=32, skip=skip, time_net=time_net)
    return dm.trained_looking(field, seed=1)


def args(**kw):
    a = dm.parse_args(["--device", "cpu", "--warmup", "1", "--repeats", "2"])
    for k, v in kw.items():
        setattr(a, k, v)
    return a


def test_paths_against_fp32_and_result_file(tmp_path: Path) -> None:
    out = tmp_path / "deform_mlp_cpu.json"
    dm.run(tiny_field(), "cpu", [300, 100], args(), output=out)
    result = json.loads(out.read_text())
    assert result["gpu"] == "cpu" and result["extent"] == 1.0
    assert result["field"]["flops_per_gaussian"] > result["field"]["flops_per_gaussian_cached"] > 0
    assert list(result["results"]) == ["100", "300"]  # sorted by N
    for entry in result["results"].values():
        assert entry["max_abs_d_xyz"] > 1e-3  # the field moves the Gaussians
        rows = entry["paths"]
        for name, bound in BOUNDS.items():
            row = rows[name]
            assert {"ms", "relative_error", "tflops", "speedup"} <= set(row), (name, row)
            assert row["ms"] > 0 and row["tflops"] > 0
            assert row["relative_error"] <= bound, (name, row["relative_error"])
        for name in ("fp32_cached", "fp16_cached", "render_fp16"):
            assert rows[name]["cache_mb"] > 0 and rows[name]["prepare_ms"] >= 0
        for name in CUDA_ONLY:
            assert rows[name]["skipped"], name
        assert set(rows) == set(BOUNDS) | set(CUDA_ONLY)  # every path measured or skipped, nothing else
        assert rows["compile"]["skipped"].startswith("CUDA only")


@pytest.mark.parametrize("time_net,depth,skip", [(0, 4, 1), (8, 3, 2), (8, 3, 5)])
def test_cached_forward_is_the_field(time_net: int, depth: int, skip: int) -> None:
    """Position cache + per-frame time row = the field (no time network, skip at the last layer, no skip)."""
    field = tiny_field(time_net, depth, skip)
    xyz = torch.rand(50, 3, generator=torch.Generator().manual_seed(0))
    spec = next(s for s in dm.path_specs() if s.name == "fp32_cached")
    step, extra = spec.build(field, xyz)
    with torch.no_grad():
        for t in (0.0, 0.37, 1.0):
            ref = field(xyz, t)
            for got, want in zip(step(t), ref):
                assert (got - want).abs().max() <= 1e-5 * max(1.0, float(want.abs().max()))


def test_deleted_paths_are_not_offered() -> None:
    """bf16, the fused Triton kernel and tf32 were deleted as render paths (benchmarks/HISTORY.md, issue 31):
    the micro-benchmark no longer offers them, nor the peak rates only they were held against."""
    names = {s.name for s in dm.path_specs()}
    assert not any(n.startswith(("bf16", "fused", "tf32")) for n in names)
    assert {"fp32", "fp16", "fp16_cached", "render_fp16"} <= names
    modes = {s.mode for s in dm.path_specs()}
    assert all(set(row) == modes == {"fp32", "fp16"} for _, row in dm.PEAKS)


def test_flops_and_peaks() -> None:
    recipe = DeformationField(10, 6, 8, 256, 4, time_net=30)
    # 93 -> 256, six 256 -> 256, the skip layer (93 + 256) -> 256, heads 256 -> 10: about 1 MFLOP.
    assert dm.flops_per_gaussian(recipe) == 2 * (93 * 256 + 6 * 256 * 256 + 349 * 256 + 256 * 10)
    assert dm.flops_per_gaussian(recipe, cached=True) == dm.flops_per_gaussian(recipe) - 2 * 2 * 93 * 256
    assert dm.gpu_tag("NVIDIA H100 80GB HBM3") == "H100" and dm.gpu_tag("NVIDIA H200") == "H200"
    assert dm.peaks_for("NVIDIA H200")["fp16"] == pytest.approx(989.4)
    assert dm.peaks_for("NVIDIA H100 PCIe")["fp16"] < dm.peaks_for("NVIDIA H100 80GB HBM3")["fp16"]
    assert dm.peaks_for("cpu") is None


def test_layer_breakdown_covers_every_stage_of_the_half_path(tmp_path: Path) -> None:
    """The stage-by-stage breakdown names every layer once (the skip layer as its two parts), counts the
    matrix products' FLOPs from the shapes, and its limits need a GPU's peak table (none on a CPU)."""
    field = tiny_field(depth=4, skip=1)
    out = tmp_path / "deform_mlp_cpu.json"
    dm.run(field, "cpu", [200], args(layers=[200]), output=out, paths=["fp16_cached"])
    layers = json.loads(out.read_text())["results"]["200"]["layers"]
    names = [s["stage"] for s in layers["stages"]]
    assert names[:3] == ["time features (one row)", "layer 0: cached part + time row", "relu (in place)"]
    assert "layer 1: linear" in names and "layer 2: addmm (hidden columns)" in names and "layer 3: linear" in names
    assert names[-1] == "heads: linear in fp32"
    relu = next(s for s in layers["stages"] if s["stage"].startswith("relu"))
    assert relu["count"] == 4  # one per layer
    linear = next(s for s in layers["stages"] if s["stage"] == "layer 1: linear")
    assert linear["flops"] == 2 * 200 * 32 * 32 and linear["ms"] > 0
    assert "compute_limit_ms" not in linear and layers["bandwidth_tbs"] is None  # no peaks for a CPU
    assert layers["sum_ms"] == pytest.approx(sum(s["ms"] * s["count"] for s in layers["stages"]), rel=1e-6, abs=1e-6)
    dm.run(field, "cpu", [200], args(layers=[]), output=out, paths=["fp16_cached"])
    assert "layers" not in json.loads(out.read_text())["results"]["200"]


def test_bandwidth_table() -> None:
    assert dm.bandwidth_for("NVIDIA H200") == 4.8 and dm.bandwidth_for("NVIDIA H100 80GB HBM3") == 3.35
    assert dm.bandwidth_for("cpu") is None
