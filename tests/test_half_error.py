"""Where the fp16 field's error comes from (benchmarks/half_error.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from garo_ns.deformation import DeformationField
from garo_ns.render.half_field import FieldWeights, PositionCache, time_features

_spec = importlib.util.spec_from_file_location(
    "half_error", Path(__file__).resolve().parents[1] / "benchmarks" / "half_error.py"
)
half_error = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(half_error)  # type: ignore[union-attr]


def _field_and_points():
    torch.manual_seed(0)
    field = DeformationField(depth=4, width=64, skip=2, time_net=8, head_init="default").eval()
    with torch.no_grad():  # offsets of a trained size, not of a freshly initialised head
        for head in (field.d_xyz, field.d_rot, field.d_scale):
            head.weight.normal_(0, 0.05)
    return field, torch.rand(500, 3) * 2 - 1


def test_the_mixed_forward_in_fp32_is_the_field_itself():
    field, xyz = _field_and_points()
    with torch.no_grad():
        ref = field(xyz, 0.4)
        w = FieldWeights.of(field, torch.float32)
        cache = PositionCache.build(field, xyz, torch.float32)
        got = half_error.mixed_forward(w, cache, time_features(field, 0.4, xyz.device), lambda i: torch.float32)
    for a, b in zip(got, ref):
        assert torch.allclose(a, b, atol=1e-5)


def test_fp16_has_an_error_that_keeping_every_layer_in_fp32_removes():
    field, xyz = _field_and_points()
    errors = half_error.offset_errors(field, xyz, [0.0, 0.5])
    assert set(errors) == set(half_error.configurations(len(field.layers)))
    today = errors["fp16 (the render path)"]
    assert 0 < today["xyz_of_extent_max"] < 1e-2 and today["xyz_of_extent_rms"] <= today["xyz_of_extent_max"]
    # With all four of this field's layers in fp32 only the cache's rounding is left: smaller than fp16's.
    assert errors["last 4 layers fp32"]["xyz_of_extent_rms"] < today["xyz_of_extent_rms"]
    assert errors["last 4 layers fp32"]["rotation_rms"] < today["rotation_rms"]
