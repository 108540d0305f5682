"""GARO's stages one at a time, on constructed inputs whose answers are known exactly.

Activity (OAA) on a real, non-square image size seen by several cameras; normals from known
rotations; curvature (GCA) on a flat plane with normals of both signs (exactly 0) and on a sphere
(exactly the value its neighbour spacing implies); kNN against brute force, including hypothesis
property tests on clouds with duplicates and NaNs. These are the fast tests the mutation run uses.
"""

from __future__ import annotations

import math
import os

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import garo_ns.redundancy.knn as knn_module
from garo_ns.garo_strategy import GaroStrategy
from garo_ns.redundancy.activity import activity_candidates, mean_activity, record
from garo_ns.redundancy.curvature import curvature
from garo_ns.redundancy.knn import knn, knn_brute, knn_grid
from garo_ns.redundancy.normals import normals, shortest_axis

W, H, C = 800, 600, 3  # a real image size, not square, seen by three cameras at once
NAN, INF = float("nan"), float("inf")
# Examples per property test; scripts/mutation.sh lowers it to keep each mutant's run short.
EXAMPLES = int(os.environ.get("GARO_PROPERTY_EXAMPLES", "100"))


# --- activity -------------------------------------------------------------------------------------


def pixel_grad(ndc_xy: torch.Tensor) -> torch.Tensor:
    """The means2d gradient (pixels) whose NDC gradient, in DefaultStrategy's units, is ndc_xy."""
    return ndc_xy / torch.tensor([W / 2 * C, H / 2 * C], dtype=ndc_xy.dtype)


def info_for(grad: torch.Tensor, radii: torch.Tensor, packed_ids=None) -> dict:
    m2d = torch.zeros_like(grad, requires_grad=True)
    m2d.grad = grad.clone()
    return {"means2d": m2d, "radii": radii, "width": W, "height": H, "n_cameras": C, "gaussian_ids": packed_ids}


def gradient_norms(info: dict, n: int, packed: bool = False):
    """This iteration's per-Gaussian norm sums and counts, as the strategy reads them from gsplat."""
    return GaroStrategy().gradient_norms({"means": torch.zeros(n, 3)}, info, packed)


def test_activity_is_the_ndc_gradient_on_an_800x600_image_seen_by_three_cameras():
    # NDC gradients (3, 4), (6, 8), (5, 12), (8, 15): norms 5, 10, 13, 17 exactly. In pixels the x
    # and y parts differ (width and height differ), so a swapped or missing scale changes the norm.
    ndc = torch.tensor(
        [
            [[3.0, 4.0], [6.0, 8.0], [1.0, 1.0]],
            [[5.0, 12.0], [8.0, 15.0], [1.0, 1.0]],
            [[0.0, 1.0], [1.0, 0.0], [1.0, 1.0]],
        ]
    )
    radii = torch.tensor([[2, 1, 0], [0, 3, 0], [4, 0, 0]], dtype=torch.int32)  # camera 1 misses 0, 2 misses 1
    info = info_for(pixel_grad(ndc), radii)
    before = info["means2d"].grad.clone()
    step_sums, step_counts = gradient_norms(info, 3)
    torch.testing.assert_close(step_sums, torch.tensor([5.0 + 1.0, 10.0 + 17.0, 0.0]), rtol=1e-6, atol=0)
    assert step_counts.tolist() == [2.0, 2.0, 0.0]  # one count per camera that sees it
    assert torch.equal(info["means2d"].grad, before)  # the model's gradient is left as it was

    sums, counts = torch.zeros(3), torch.zeros(3)
    record(sums, counts, step_sums, step_counts)
    record(sums, counts, step_sums, step_counts)
    assert counts.tolist() == [4.0, 4.0, 0.0]
    g = mean_activity(sums, counts)
    torch.testing.assert_close(g[:2], torch.tensor([3.0, 13.5]), rtol=1e-6, atol=0)
    assert math.isnan(g[2])  # never seen: no estimate


def test_packed_activity_takes_the_ids_from_the_rasterizer():
    ndc = torch.tensor([[3.0, 4.0], [6.0, 8.0], [5.0, 12.0]])
    ids = torch.tensor([4, 0, 4])
    info = info_for(pixel_grad(ndc), torch.tensor([1, 1, 1]), packed_ids=ids)
    step_sums, step_counts = gradient_norms(info, 5, packed=True)
    torch.testing.assert_close(step_sums, torch.tensor([10.0, 0.0, 0.0, 0.0, 18.0]), rtol=1e-6, atol=0)
    assert step_counts.tolist() == [1.0, 0.0, 0.0, 0.0, 2.0]


def test_non_finite_gradients_are_dropped_not_spread():
    ndc = torch.tensor([[[3.0, 4.0], [NAN, 1.0], [INF, 0.0], [0.0, 0.0]]])
    info = info_for(pixel_grad(ndc), torch.ones(1, 4, dtype=torch.int32))
    info["n_cameras"] = 1
    sums, counts = torch.zeros(4), torch.zeros(4)
    record(sums, counts, *gradient_norms(info, 4))
    torch.testing.assert_close(sums, torch.tensor([5.0 / C, 0.0, 0.0, 0.0]), rtol=1e-6, atol=0)
    assert counts.tolist() == [1.0, 0.0, 0.0, 1.0]


def test_activity_without_a_gradient_is_an_error():
    info = info_for(torch.zeros(1, 2, 2), torch.ones(1, 2))
    info["means2d"].grad = None
    with pytest.raises(ValueError, match=r"^info\['means2d'\] has no gradient: call retain_grad\(\) before backward$"):
        gradient_norms(info, 2)


def test_mean_activity_divides_by_the_visible_count():
    sums = torch.tensor([6.0, 6.0, 0.0, 0.0])
    counts = torch.tensor([1.0, 3.0, 2.0, 0.0])
    g = mean_activity(sums, counts)
    assert g[:3].tolist() == [6.0, 2.0, 0.0] and math.isnan(g[3])
    sums, counts = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
    record(sums, counts, torch.tensor([0.0, 0.0, 0.75]), torch.tensor([0.0, 0.0, 2.0]))  # float32 into float64
    assert sums.tolist() == [0.0, 0.0, 0.75] and counts.tolist() == [0.0, 0.0, 2.0]


def test_activity_candidates_are_strictly_below_tau_lowest_first_at_most_n_max():
    g = torch.tensor([3.0, 1.0, NAN, 2.0, 1.0, 5.0, INF, 0.0])
    assert activity_candidates(g, 3.0, 100).tolist() == [7, 1, 4, 3]  # 3.0 itself is not below tau
    assert activity_candidates(g, 3.0, 2).tolist() == [7, 1]  # ties keep index order
    assert activity_candidates(g, 3.0, 0).tolist() == []
    assert activity_candidates(g, 3.0, -3).tolist() == []
    assert activity_candidates(g, INF, 100).tolist() == [7, 1, 4, 3, 0, 5]  # never NaN or inf
    assert activity_candidates(g, 0.0, 100).tolist() == []


# --- normals --------------------------------------------------------------------------------------

# (0.5, 0.5, 0.5, 0.5): 120 degrees about (1, 1, 1), which maps x -> y, y -> z, z -> x.
CYCLE = torch.tensor([0.5, 0.5, 0.5, 0.5])


def test_shortest_axis_uses_magnitudes_ties_and_non_finite_scales():
    s = torch.tensor(
        [
            [0.3, 0.2, 0.1],
            [0.1, 0.2, 0.3],
            [-5.0, 1.0, 2.0],  # magnitudes
            [0.2, 0.1, 0.1],  # tie: the first of the smallest
            [0.1, 0.1, 0.1],
            [NAN, 1.0, 2.0],  # non-finite counts as infinitely large
            [INF, NAN, 3.0],
            [NAN, NAN, NAN],
            [0.0, 0.0, 1.0],
        ]
    )
    assert shortest_axis(s).tolist() == [2, 0, 1, 1, 0, 1, 2, 0, 0]


def test_normal_is_the_rotation_column_of_the_smallest_axis():
    scales = torch.tensor([[0.01, 1.0, 1.0], [1.0, 0.01, 1.0], [1.0, 1.0, 0.01]])
    want = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    for q in (CYCLE, 7 * CYCLE):  # quaternions need not be unit
        torch.testing.assert_close(normals(q.expand(3, 4), scales), want, atol=1e-7, rtol=0)


@pytest.mark.parametrize("bad", [0.0, NAN, INF, -INF])
def test_zero_and_non_finite_quaternions_give_the_identity_rotation(bad):
    quats = CYCLE.repeat(4, 1)
    quats[1:3] = bad
    quats[3, 2] = bad  # one bad component is enough (a zero one is just another rotation)
    scales = torch.tensor([[1.0, 0.01, 1.0]]).expand(4, 3)
    n = normals(quats, scales)
    assert torch.equal(n[1], torch.tensor([0.0, 1.0, 0.0])) and torch.equal(n[2], n[1])
    if bad != 0.0:
        assert torch.equal(n[3], n[1])
    torch.testing.assert_close(n[0], torch.tensor([0.0, 0.0, 1.0]), atol=1e-7, rtol=0)


# --- curvature ------------------------------------------------------------------------------------


def test_flat_plane_with_normals_of_both_signs_has_curvature_exactly_zero():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 3, generator=g)
    pts[:, 2] = 0.5
    sign = torch.where(torch.rand(300, 1, generator=g) < 0.5, -1.0, 1.0)
    nrm = torch.tensor([0.0, 0.0, 1.0]) * sign
    assert (sign < 0).sum() > 100 and (sign > 0).sum() > 100
    c = curvature(pts, nrm, torch.arange(300), 10)
    assert torch.equal(c, torch.zeros(300))


def test_curvature_never_goes_below_zero_for_slightly_long_normals():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    nrm = torch.tensor([[0.0, 0.0, 1.0 + 1e-3], [0.0, 0.0, -(1.0 + 1e-3)], [0.0, 0.0, 1.0]])
    assert torch.equal(curvature(pts, nrm, torch.arange(3), 2), torch.zeros(3))


def fibonacci_sphere(n: int, r: float) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    rho = (1 - z * z).sqrt()
    return r * torch.stack([rho * phi.cos(), rho * phi.sin(), z], -1)


@pytest.mark.parametrize("r", [0.5, 3.0])
def test_sphere_curvature_is_what_its_neighbour_spacing_implies(r):
    # Radial normals at chord distance d meet at angle t with d = 2 r sin(t / 2), so
    # 1 - cos t = d^2 / (2 r^2): the curvature is the mean of d^2 / (2 r^2) over the k neighbours.
    k = 8
    pts = fibonacci_sphere(500, r)
    nrm = pts / r
    q = torch.arange(0, 500, 7)
    d2 = torch.cdist(pts[q], pts) ** 2
    d2[torch.arange(len(q)), q] = INF
    nearest = torch.topk(d2, k, largest=False).values
    want = nearest.mean(-1) / (2 * r * r)
    got = curvature(pts, nrm, q, k)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=0)
    assert (nearest.amax(-1) / (2 * r * r) > 1.2 * want).all()  # the mean, not the largest neighbour
    # The spacing of 500 points on the sphere: about sqrt(4 pi / 500) r apart, curvature ~ 1/500 * const.
    assert 0.002 < float(got.mean()) < 0.02


def test_orthogonal_neighbours_give_one_and_fewer_than_k_uses_all_others():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    nrm = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    c = curvature(pts, nrm, torch.tensor([0, 3, 2]), 10)  # k = 10 > N - 1 = 3
    assert c.tolist() == [1.0, 2.0 / 3.0, 2.0 / 3.0]  # query 3: neighbours 0, 1 orthogonal, 2 antiparallel
    one = curvature(pts[:1], nrm[:1], torch.tensor([0]), 10)
    assert one.tolist() == [INF] and one.dtype == torch.float64  # nothing to compare with
    none = curvature(pts, nrm, torch.tensor([], dtype=torch.long), 10)
    assert none.shape == (0,) and none.dtype == torch.float64
    two = curvature(pts[[0, 3]], -nrm[[0, 0]], torch.tensor([0, 1]), 10)  # two Gaussians: each other's neighbour
    assert two.tolist() == [0.0, 0.0]


def test_non_finite_normals_give_infinite_curvature():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    nrm = torch.tensor([[0.0, 0.0, 1.0], [NAN, 0.0, 1.0], [0.0, 0.0, 1.0]])
    assert curvature(pts, nrm, torch.arange(3), 1).tolist() == [INF, INF, INF]


# --- kNN ------------------------------------------------------------------------------------------


def reference_distances(pts: torch.Tensor, q: torch.Tensor, k: int) -> torch.Tensor:
    """Sorted squared distances of the k nearest others (non-finite points at infinity), in float64."""
    fin = torch.isfinite(pts).all(-1)
    p = torch.where(fin[:, None], pts, 0).double()
    d = ((p[q][:, None, :] - p[None]) ** 2).sum(-1)
    d[:, ~fin] = INF
    d[torch.arange(len(q)), q] = INF
    return torch.topk(d, k, largest=False).values


def distances_of(pts: torch.Tensor, q: torch.Tensor, got: torch.Tensor) -> torch.Tensor:
    fin = torch.isfinite(pts).all(-1)
    p = torch.where(fin[:, None], pts, 0).double()
    d = ((p[got] - p[q][:, None, :]) ** 2).sum(-1)
    return torch.where(fin[got], d, torch.full_like(d, INF)).sort(-1).values


@st.composite
def clouds(draw):
    """Point clouds on a coarse lattice (exact duplicates and ties) plus jitter, with some NaN rows."""
    n = draw(st.integers(2, 60))
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    lattice = draw(st.sampled_from([2, 4, 1000]))
    pts = torch.randint(0, lattice, (n, 3), generator=g).float() / lattice
    if draw(st.booleans()):
        pts = pts + torch.rand(n, 3, generator=g) * draw(st.sampled_from([1e-3, 1.0]))
    n_dup = draw(st.integers(0, n - 1))
    pts[1 : 1 + n_dup] = pts[0]
    bad = torch.rand(n, generator=g) < draw(st.sampled_from([0.0, 0.2]))
    pts[bad, draw(st.integers(0, 2))] = draw(st.sampled_from([NAN, INF]))
    fin = torch.nonzero(torch.isfinite(pts).all(-1)).squeeze(1)
    if fin.numel() == 0:
        pts[0] = 0.0
        fin = torch.tensor([0])
    k = draw(st.integers(1, n - 1)) if n > 1 else 1
    q = fin[torch.randperm(fin.numel(), generator=g)[: draw(st.integers(1, fin.numel()))]]
    return pts, q, k


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(clouds(), st.integers(1, 7), st.integers(1, 70))
def test_knn_brute_equals_brute_force(cloud, query_chunk, point_chunk):
    pts, q, k = cloud
    got = knn_brute(pts, q, k, query_chunk=query_chunk, point_chunk=point_chunk)
    assert got.shape == (len(q), k) and not (got == q[:, None]).any()
    assert (got.sort(-1).values.diff(dim=-1) != 0).all()  # k distinct neighbours
    torch.testing.assert_close(distances_of(pts, q, got), reference_distances(pts, q, k), rtol=1e-5, atol=1e-9)


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(clouds(), st.sampled_from([0.1, 0.5, 0.9]), st.sampled_from([4, 16, 4096]))
def test_knn_grid_equals_brute_force(cloud, quantile, max_candidates):
    pts, q, k = cloud
    got = knn_grid(pts, q, k, cell_quantile=quantile, sample_size=5, max_candidates=max_candidates)
    assert got.shape == (len(q), k) and not (got == q[:, None]).any()
    assert (got.sort(-1).values.diff(dim=-1) != 0).all()
    torch.testing.assert_close(distances_of(pts, q, got), reference_distances(pts, q, k), rtol=1e-5, atol=1e-9)


def test_knn_grid_on_a_dense_surface_answers_from_the_grid():
    # Many points on a sheet: the grid path (not the brute-force fallback) must answer exactly.
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(4000, 3, generator=g)
    pts[:, 2] = torch.randint(0, 2, (4000,), generator=g).float() * 0.01
    q = torch.arange(0, 4000, 13)
    got = knn_grid(pts, q, 10)
    torch.testing.assert_close(distances_of(pts, q, got), reference_distances(pts, q, 10), rtol=1e-5, atol=1e-9)
    assert torch.equal(knn(pts, q, 10).sort(-1).values, knn_brute(pts, q, 10).sort(-1).values)


@pytest.mark.parametrize("method", [knn, knn_brute, knn_grid])
def test_knn_rejects_k_outside_one_to_n_minus_one(method):
    pts = torch.rand(5, 3)
    for k in (0, 5, 6):
        with pytest.raises(ValueError, match="k must be in 1..4"):
            method(pts, torch.tensor([0]), k)
    assert method(pts, torch.tensor([0]), 4).sort().values.tolist() == [[1, 2, 3, 4]]
    none = method(pts, torch.tensor([], dtype=torch.long), 2)
    assert none.shape == (0, 2) and none.dtype == torch.long  # indices, even when there are none


def spy_on_knn_brute(monkeypatch) -> list:
    """Records the number of queries of every knn_brute call that knn_grid makes (the sample, the fallback)."""
    calls, real = [], knn_module.knn_brute

    def spy(points, query_ids, k, **kw):
        calls.append(query_ids.numel())
        return real(points, query_ids, k, **kw)

    monkeypatch.setattr(knn_module, "knn_brute", spy)
    return calls


def test_knn_grid_answers_exactly_the_queries_whose_kth_neighbour_is_within_one_cell(monkeypatch):
    # A 14 x 12 x 10 lattice, spacing 0.5, corner at -3 (exact in binary). k = 6: an interior point has
    # its 6 face neighbours at 0.5; the 720 points on the faces have only 3 to 5, so their 6th lies at
    # 0.5 * sqrt(2). The median 6th distance (960 of 1680 are interior) gives cells of exactly 0.5, one
    # per lattice point: an interior query's 27 cells hold 27 points and its 6th neighbour is within
    # one cell, so the grid answers it; a face query goes to the brute-force fallback.
    dims = (14, 12, 10)
    pts = torch.stack(torch.meshgrid(*[torch.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3) * 0.5 - 3.0
    q = torch.arange(len(pts))
    interior = ((pts > -3.0) & (pts < torch.tensor(dims) * 0.5 - 3.5)).all(-1)
    calls = spy_on_knn_brute(monkeypatch)
    got = knn_grid(pts, q, 6, cell_quantile=0.5, sample_size=4096, max_candidates=27)
    assert calls == [1680, 720]  # the sample (every query), then the face queries only
    assert int(interior.sum()) == 960
    steps = (pts[got[interior]] - pts[interior][:, None, :]).abs().sum(-1)
    assert torch.equal(steps, torch.full_like(steps, 0.5))  # exactly the 6 face neighbours
    torch.testing.assert_close(distances_of(pts, q, got), reference_distances(pts, q, 6), rtol=0, atol=0)
    calls.clear()
    again = knn_grid(pts, q, 6, cell_quantile=0.5, sample_size=4096, max_candidates=26)
    assert calls == [1680, 1680]  # 27 candidates exceed 26: every query falls back
    torch.testing.assert_close(distances_of(pts, q, again), reference_distances(pts, q, 6), rtol=0, atol=0)


def test_knn_grid_leaves_too_few_finite_points_to_brute_force(monkeypatch):
    nan_pts = torch.full((4, 3), NAN)
    none_finite = knn_grid(nan_pts, torch.tensor([0, 2]), 2)  # no finite point at all: padding only, no error
    assert none_finite.shape == (2, 2) and 0 not in none_finite[0] and 2 not in none_finite[1]
    assert (none_finite.sort(-1).values.diff(dim=-1) != 0).all() and (none_finite < 4).all()
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [NAN, 0.0, 0.0], [0.0, INF, 0.0], [0.0, 0.0, NAN]])
    calls = spy_on_knn_brute(monkeypatch)
    got = knn_grid(pts, torch.tensor([0, 1]), 2)  # 2 finite points, k = 2: no grid (and no sample) at all
    assert calls == [2]
    assert got[:, 0].tolist() == [1, 0] and (got[:, 1] >= 2).all()


def test_knn_grid_when_squared_distances_overflow_float32():
    # Points 4e19 apart: every squared distance is inf in float32, so no finite k-th distance sizes the
    # cells; the grid falls back to its extent-based size instead of failing.
    pts = torch.zeros(20, 3)
    pts[:, 0] = torch.arange(20.0) * 4e19
    q = torch.arange(20)
    got = knn_grid(pts, q, 2)
    assert got.sort(-1).values.tolist() == [[1, 2]] + [[i - 1, i + 1] for i in range(1, 19)] + [[17, 18]]


def test_knn_takes_the_grid_above_two_to_the_26_query_point_pairs(monkeypatch):
    used = []
    monkeypatch.setattr(knn_module, "knn_grid", lambda p, q, k: used.append("grid"))
    monkeypatch.setattr(knn_module, "knn_brute", lambda p, q, k: used.append("brute"))
    for n, q in [(2**13, 2**13), (2**13, 2**13 + 1), (2**13 + 1, 2**13), (2**26, 1), (2**26, 0), (2**26 + 1, 0)]:
        knn(torch.zeros(1, 3).expand(n, 3), torch.arange(q), 5)  # only the shapes matter here
    assert used == ["brute", "grid", "grid", "brute", "brute", "grid"]
