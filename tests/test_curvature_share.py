"""The curvature gate's share of a model (benchmarks/curvature_share.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from garo_ns.redundancy.curvature import curvature

_spec = importlib.util.spec_from_file_location(
    "curvature_share", Path(__file__).resolve().parents[1] / "benchmarks" / "curvature_share.py"
)
curvature_share = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(curvature_share)  # type: ignore[union-attr]


def test_stats_count_the_finite_curvatures_under_tau():
    c = torch.tensor([0.1, 0.2, 0.6, 0.9, float("inf")])  # inf: a Gaussian that cannot be measured
    stats = curvature_share.curvature_stats(c, 0.5)
    assert stats["count"] == 4
    assert stats["share_under_tau"] == pytest.approx(0.5)
    assert stats["mean"] == pytest.approx(0.45)
    assert stats["quantiles"]["0.5"] == pytest.approx(0.4)


def test_normals_pointing_every_which_way_sit_at_the_default_tau():
    """The reading tau = 0.5 rests on: random directions give curvature 0.5 on average; a flat sheet gives 0."""
    g = torch.Generator().manual_seed(0)
    points = torch.rand(4000, 3, generator=g)
    random_normals = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1)
    ids = torch.arange(4000)
    mean = curvature_share.curvature_stats(curvature(points, random_normals, ids, 10), 0.5)["mean"]
    assert mean == pytest.approx(0.5, abs=0.02)
    flat = torch.tensor([0.0, 0.0, 1.0]).expand(4000, 3)
    assert curvature_share.curvature_stats(curvature(points, flat, ids, 10), 0.5)["share_under_tau"] == 1.0
