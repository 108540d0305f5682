"""GARO's joint selection and GaroStrategy's own logic, with exact expected outcomes.

Every strategy test takes one Adam step on the parameters first (as training does) and only then
injects its hard case, so that zero quaternions stay zero and -inf log-scales stay -inf when the
strategy reads them. Geometry: Gaussians on a plane (curvature exactly 0) or a sphere (curvature
clearly above the thresholds used), so the right answer is a count, not a range.
"""

from __future__ import annotations

import math
import os

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from garo_ns.garo_strategy import GaroStrategy, restrict_info
from garo_ns.redundancy.activity import record
from garo_ns.redundancy.curvature import curvature
from garo_ns.redundancy.normals import normals
from garo_ns.redundancy.select import least_contributing, select_redundant

NAN, INF = float("nan"), float("inf")
# Examples per property test; scripts/mutation.sh lowers it to keep each mutant's run short.
EXAMPLES = int(os.environ.get("GARO_PROPERTY_EXAMPLES", "100"))
THIN = torch.tensor([0.02, 0.02, 0.001])  # flat Gaussians: the third axis is the normal
W, H = 800, 600


def quat_from_normal(n: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z) quaternions rotating z onto each unit vector n."""
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(n)
    axis = torch.cross(z, n, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    half = torch.atan2(s, (z * n).sum(-1, keepdim=True)) / 2
    axis = torch.where(s > 1e-8, axis / s.clamp_min(1e-12), torch.tensor([1.0, 0.0, 0.0]))
    return torch.cat([half.cos(), axis * half.sin()], -1)


def yaw_quats(n: int, seed: int = 0) -> torch.Tensor:
    """Rotations about z by random angles: the normal stays z exactly, the in-plane axes turn."""
    yaw = torch.rand(n, generator=torch.Generator().manual_seed(seed)) * 2 * math.pi
    return torch.stack([(yaw / 2).cos(), torch.zeros(n), torch.zeros(n), (yaw / 2).sin()], -1)


def plane(n: int, seed: int = 0, z: float = 0.0) -> torch.Tensor:
    pts = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed + 1)) * 2 - 1
    pts[:, 2] = z
    return pts


def sphere(n: int, r: float = 0.3, center=(0.0, 0.0, 5.0)) -> tuple[torch.Tensor, torch.Tensor]:
    i = torch.arange(n, dtype=torch.float32) + 0.5
    zc = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    rho = (1 - zc * zc).sqrt()
    nrm = torch.stack([rho * phi.cos(), rho * phi.sin(), zc], -1)
    return nrm * r + torch.tensor(center), quat_from_normal(nrm)


def make_params(points, quats, log_scales):
    """Parameters and Adam optimizers after one real optimizer step (hard cases are injected after it)."""
    n = len(points)
    params = {
        "means": torch.nn.Parameter(points.clone()),
        "quats": torch.nn.Parameter(quats.clone()),
        "scales": torch.nn.Parameter(log_scales.clone()),
        "opacities": torch.nn.Parameter(torch.arange(n, dtype=torch.float32)),  # row ids
    }
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for p in params.values():
        p.grad = torch.ones_like(p)
    for o in optimizers.values():
        o.step()
    with torch.no_grad():  # back to the exact geometry and row ids (Adam moved them by 1e-3)
        params["means"].copy_(points)
        params["quats"].copy_(quats)
        params["scales"].copy_(log_scales)
        params["opacities"].copy_(torch.arange(n, dtype=torch.float32))
    return params, optimizers


def fake_info(n: int, ndc=None, radii=None, **geometry) -> dict:
    """The rasterizer's info for one 800x600 camera; `ndc` are the NDC gradient norms along x."""
    m2d = torch.zeros(1, n, 2, requires_grad=True)
    g = torch.zeros(n) if ndc is None else torch.as_tensor(ndc, dtype=torch.float32).expand(n)
    m2d.grad = torch.stack([g / (W / 2), torch.zeros(n)], -1)[None].clone()
    info = {
        "means2d": m2d,
        "radii": torch.ones(1, n, dtype=torch.int32) if radii is None else radii,
        "width": W,
        "height": H,
        "n_cameras": 1,
        "gaussian_ids": None,
    }
    info.update(geometry)
    return info


def garo(**kw) -> GaroStrategy:
    """A strategy that runs GARO at step 1 only and never densifies (refine_start_iter is far away); its
    activity record is not restarted by the GARO step (window "training"), so tests can read it after."""
    args = dict(
        garo_start_iter=1, garo_stop_iter=2, garo_every=1, refine_start_iter=10_000, tau_activity=1.0,
        activity_window="training",
    )  # fmt: skip
    args.update(kw)
    return GaroStrategy(**args)


def run_step(strategy, params, optimizers, info, step=1, state=None):
    state = strategy.initialize_state() if state is None else state
    strategy.step_post_backward(params, optimizers, state, step, info)
    return state


def log_thin(n: int) -> torch.Tensor:
    return THIN.log().expand(n, 3).clone()


# --- select_redundant -----------------------------------------------------------------------------


def plane_and_sphere_layout():
    """60 plane Gaussians (curvature 0) and 40 sphere Gaussians (curvature > 0.01), far apart."""
    pp = plane(60)
    sp, sq = sphere(40)
    points = torch.cat([pp, sp])
    nrm = normals(torch.cat([yaw_quats(60), sq]), THIN.expand(100, 3))
    return points, nrm


def test_full_mode_prunes_the_flat_inactive_ones_flattest_then_least_active_first():
    points, nrm = plane_and_sphere_layout()
    c = curvature(points, nrm, torch.arange(100), 10)
    assert torch.equal(c[:60], torch.zeros(60)) and c[60:].min() > 0.01
    # Plane 0-29 active; plane 30-59 inactive, the later ones less so; the sphere least active of all.
    activity = torch.cat([torch.full((30,), 2.0), torch.linspace(0.9, 0.3, 30), torch.linspace(0.0, 0.1, 40)])
    counts = torch.ones(100)
    out = select_redundant(activity, counts, points, nrm, "full", 1.0, 10_000, 0.01, 0.2, 10)
    assert (out["candidates"], out["redundant"]) == (70, 30)
    assert out["prune"].tolist() == list(range(59, 39, -1))  # 20 = floor(0.2 * 100), least active first
    # n_max = 50 keeps the 50 least active as candidates: the sphere and plane 50-59 only.
    out = select_redundant(activity, counts, points, nrm, "full", 1.0, 50, 0.01, 0.2, 10)
    assert (out["candidates"], out["redundant"]) == (50, 10)
    assert out["prune"].tolist() == list(range(59, 49, -1))
    # Never-seen Gaussians (NaN activity) are no candidates, whatever their geometry.
    activity[30:60] = NAN
    out = select_redundant(activity, counts, points, nrm, "full", 1.0, 10_000, 0.01, 0.2, 10)
    assert (out["candidates"], out["redundant"], out["prune"].numel()) == (40, 0, 0)


def test_flattest_first_among_candidates():
    points, nrm = plane_and_sphere_layout()
    activity = torch.zeros(100)
    out = select_redundant(activity, torch.ones(100), points, nrm, "full", 1.0, 10_000, 1.0, 0.7, 10)
    c = curvature(points, nrm, torch.arange(100), 10)
    assert out["redundant"] == 100 and out["prune"].numel() == 70
    assert out["prune"][:60].tolist() == list(range(60))  # the plane (curvature 0) first
    assert torch.equal(c[out["prune"][60:]], c[60:].sort().values[:10])  # then the flattest of the sphere


def test_a_curvature_equal_to_the_threshold_is_not_flat():
    # Two far-apart pairs whose normals are orthogonal: curvature exactly 1.
    points = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [9.0, 0, 0], [9.1, 0, 0]])
    nrm = torch.tensor([[1.0, 0, 0], [0.0, 1, 0], [0.0, 0, 1], [1.0, 0, 0]])
    act, cnt = torch.zeros(4), torch.ones(4)
    assert select_redundant(act, cnt, points, nrm, "full", 1.0, 10, 1.0, 1.0, 1)["redundant"] == 0
    assert select_redundant(act, cnt, points, nrm, "full", 1.0, 10, 1.0 + 1e-6, 1.0, 1)["redundant"] == 4


@pytest.mark.parametrize(("rho", "pruned"), [(-0.5, 0), (0.0, 0), (0.019, 1), (0.5, 50), (0.999, 60), (3.0, 60)])
def test_rho_max_is_clamped_to_zero_one_and_floored(rho, pruned):
    points, nrm = plane_and_sphere_layout()
    out = select_redundant(torch.zeros(100), torch.ones(100), points, nrm, "full", 1.0, 10_000, 0.01, rho, 10)
    assert out["redundant"] == 60 and out["prune"].numel() == pruned


def test_oaa_mode_uses_activity_alone():
    points, _ = plane_and_sphere_layout()
    activity = torch.linspace(1.0, 0.0, 100)
    activity[10] = NAN
    broken = torch.full((100, 3), NAN)  # no normals are read
    out = select_redundant(activity, torch.ones(100), points, broken, "oaa", 0.5, 10_000, 0.0, 0.1, 10)
    assert (out["candidates"], out["redundant"]) == (50, 50)  # below 0.5: indices 50..99
    assert out["prune"].tolist() == list(range(99, 89, -1))


def test_gca_mode_takes_every_visible_gaussian_whatever_its_activity():
    points, nrm = plane_and_sphere_layout()
    activity = torch.full((100,), 1e9)
    counts = torch.ones(100)
    counts[:5] = 0  # never visible: never pruned
    out = select_redundant(activity, counts, points, nrm, "gca", 0.0, 3, 0.01, 1.0, 10)
    assert (out["candidates"], out["redundant"]) == (95, 55)
    assert out["prune"].tolist() == list(range(5, 60))


# --- GaroStrategy ---------------------------------------------------------------------------------


def flat_plane_params(n=100, seed=0):
    return make_params(plane(n, seed), yaw_quats(n, seed), log_thin(n))


def test_strategy_prunes_exactly_floor_rho_n_of_a_flat_inactive_plane():
    params, optimizers = flat_plane_params()
    strategy = garo(rho_max=0.07, tau_curvature=1e-6)
    state = run_step(strategy, params, optimizers, fake_info(100, ndc=0.5))  # activity 0.5 < tau 1
    assert state["garo_last"] == {**state["garo_last"], "step": 1, "candidates": 100, "redundant": 100, "pruned": 7}
    assert state["garo_last"]["num_gaussians"] == 93 == len(params["means"])
    assert 0 <= state["garo_last"]["seconds"] < 60
    # All tie at curvature 0 and activity 0.5: the first seven by index go.
    assert params["opacities"].detach().tolist() == list(range(7, 100))


def test_log_scales_are_exponentiated_before_choosing_the_normal_axis():
    # log(0.02) = -3.9 and log(0.001) = -6.9: read as sizes, the thin axis would be an in-plane one,
    # whose direction turns from Gaussian to Gaussian (random yaw), and nothing would look flat.
    params, optimizers = flat_plane_params()
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(100))
    assert (state["garo_last"]["redundant"], state["garo_last"]["pruned"]) == (100, 50)


def test_deformed_geometry_decides_not_the_canonical_one():
    n = 100
    # Canonical: two separate flat patches, normals z (x < 0) and x (x > 5). Every Gaussian is flat.
    pts = plane(n)
    pts[50:, 0] += 7.0
    quats = torch.cat([yaw_quats(50), quat_from_normal(torch.tensor([[1.0, 0.0, 0.0]])).expand(50, 4)])
    # Deformed positions: the two patches on top of each other, so neighbours' normals are orthogonal.
    mixed = pts.clone()
    mixed[50:, 0] -= 7.0
    mixed[50:, 1] += 1e-3
    curved_pts, curved_quats = sphere(n, r=0.2)
    cases = {
        "canonical": ({}, 50),
        "wrong size: canonical": ({"means3d": mixed[:-1], "quats3d": quats[:-1]}, 50),
        "deformed positions": ({"means3d": mixed}, 0),
        "deformed rotations": ({"quats3d": curved_quats}, 0),
        "both, flat again": ({"means3d": plane(n, seed=5), "quats3d": yaw_quats(n, 9)}, 50),
    }
    for name, (geometry, pruned) in cases.items():
        params, optimizers = make_params(pts, quats, log_thin(n))
        state = run_step(garo(rho_max=0.5, tau_curvature=0.1), params, optimizers, fake_info(n, **geometry))
        assert state["garo_last"]["pruned"] == pruned, name
    # And the other way: a curved canonical sphere deformed flat is pruned.
    params, optimizers = make_params(curved_pts, curved_quats, log_thin(n))
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(n))
    assert state["garo_last"]["pruned"] == 0
    info = fake_info(n, means3d=plane(n), quats3d=yaw_quats(n))
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, info)
    assert state["garo_last"]["pruned"] == 50


def test_schedule_starts_at_start_stops_before_stop():
    s = GaroStrategy(refine_start_iter=500, refine_stop_iter=2000, refine_every=100)
    assert s.garo_schedule() == (501, 2000, 100)
    assert [t for t in range(3000) if s.is_garo_step(t)] == list(range(600, 2000, 100))
    s = GaroStrategy(garo_start_iter=300, garo_stop_iter=900, garo_every=300, refine_start_iter=500)
    assert [t for t in range(3000) if s.is_garo_step(t)] == [300, 600]
    s = GaroStrategy(garo_start_iter=3, garo_stop_iter=7, garo_every=0)  # every 0 means every step
    assert s.garo_schedule() == (3, 7, 1) and [t for t in range(10) if s.is_garo_step(t)] == [3, 4, 5, 6]


def test_no_garo_step_and_no_activity_at_garo_stop():
    params, optimizers = flat_plane_params(40)
    strategy = GaroStrategy(
        garo_start_iter=4, garo_stop_iter=8, garo_every=4, refine_start_iter=10_000, tau_activity=1.0, rho_max=0.5
    )
    state = strategy.initialize_state()
    for step in range(1, 9):
        strategy.step_post_backward(params, optimizers, state, step, fake_info(len(params["means"])))
    assert state["garo_last"]["step"] == 4 and len(params["means"]) == 20  # pruned at 4 only, not at 8
    assert state["garo_count"].tolist() == [3.0] * 20  # steps 5-7 counted (window since step 4), 8 (= stop) not


def test_activity_state_restarts_when_the_count_of_gaussians_changed_outside_it():
    params, optimizers = flat_plane_params(10)
    strategy = garo(garo_start_iter=100, garo_stop_iter=200)
    state = strategy.initialize_state()
    state["garo_grad"], state["garo_count"] = torch.full((12,), 5.0), torch.full((12,), 5.0)
    strategy.step_post_backward(params, optimizers, state, 1, fake_info(10, ndc=0.25))
    assert state["garo_count"].tolist() == [1.0] * 10
    torch.testing.assert_close(state["garo_grad"], torch.full((10,), 0.25))


def test_after_a_garo_step_densification_bookkeeping_sees_the_kept_rows():
    # The rasterizer's info is filtered to the kept Gaussians before DefaultStrategy counts gradients.
    n = 50
    params, optimizers = flat_plane_params(n)
    strategy = garo(rho_max=0.2, tau_curvature=0.01, refine_stop_iter=10_000, refine_scale2d_stop_iter=10_000)
    ndc = torch.arange(n, dtype=torch.float32) / 100  # distinct per row, all below tau 1
    info = fake_info(n, radii=torch.arange(1, n + 1, dtype=torch.int32)[None])
    info["means2d"].grad = torch.stack([ndc / (W / 2), torch.zeros(n)], -1)[None].clone()
    state = run_step(strategy, params, optimizers, info)
    kept = params["opacities"].detach().long()
    assert kept.tolist() == list(range(10, 50))  # the 10 least active
    torch.testing.assert_close(state["grad2d"], ndc[kept])
    assert state["count"].tolist() == [1.0] * 40
    torch.testing.assert_close(state["radii"], (kept + 1).float() / W)


def test_garo_step_window_restarts_the_mean():
    params, optimizers = flat_plane_params(20)
    strategy = garo(activity_window="garo_step", tau_activity=0.0)  # no candidate: nothing pruned
    state = run_step(strategy, params, optimizers, fake_info(20, ndc=0.3))
    assert state["garo_last"]["pruned"] == 0 and state["garo_count"].tolist() == [0.0] * 20
    state = run_step(garo(tau_activity=0.0), params, optimizers, fake_info(20, ndc=0.3))
    assert state["garo_count"].tolist() == [1.0] * 20


def test_the_last_garo_step_is_reported_in_the_state():
    params, optimizers = flat_plane_params(30)
    strategy = garo(rho_max=0.1, tau_curvature=0.01)
    state = run_step(strategy, params, optimizers, fake_info(30))
    last = state["garo_last"]
    assert last["step"] == 1
    assert {k: last[k] for k in ("candidates", "redundant", "pruned", "num_gaussians")} == {
        "candidates": 30,
        "redundant": 30,
        "pruned": 3,
        "num_gaussians": 27,
    }


# --- hard cases, injected after the optimizer step ------------------------------------------------


def sphere_params(n=100, r=0.3):
    pts, quats = sphere(n, r)
    return make_params(pts, quats, log_thin(n))


def test_a_sphere_is_not_pruned_at_this_threshold():
    params, optimizers = sphere_params()
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(100))
    assert (state["garo_last"]["candidates"], state["garo_last"]["redundant"]) == (100, 0)


@pytest.mark.parametrize("bad", [0.0, NAN, INF])
def test_zero_and_non_finite_quaternions_read_as_identity(bad):
    # Every rotation reads as the identity, so every normal is z: the sphere turns flat and exactly
    # floor(rho N) of its Gaussians go (the intact sphere loses none, see the test above).
    params, optimizers = sphere_params()
    with torch.no_grad():
        params["quats"][:] = bad
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(100))
    assert (state["garo_last"]["redundant"], state["garo_last"]["pruned"]) == (100, 50)


def test_minus_infinite_log_scales():
    # -inf on the thin axis: size 0, still the thin axis; the decision is the finite one.
    params, optimizers = flat_plane_params()
    with torch.no_grad():
        params["scales"][:, 2] = -INF
    state = run_step(garo(rho_max=0.3, tau_curvature=0.01), params, optimizers, fake_info(100))
    assert (state["garo_last"]["redundant"], state["garo_last"]["pruned"]) == (100, 30)
    # -inf on an in-plane axis of half the Gaussians: their normal lies in the plane (random yaw),
    # so they and their neighbours are no longer flat.
    params, optimizers = flat_plane_params()
    with torch.no_grad():
        params["scales"][::2, 0] = -INF
    state = run_step(garo(rho_max=1.0, tau_curvature=0.01), params, optimizers, fake_info(100))
    assert state["garo_last"]["redundant"] == 0


def test_duplicate_positions_are_redundant_copies():
    # 10 sphere Gaussians, each repeated 11 times: the 10 nearest of every copy are its own copies
    # (distance 0, same normal), so all 110 are flat, where the 10 alone are not.
    pts, quats = sphere(10, r=0.3)
    params, optimizers = make_params(pts.repeat_interleave(11, 0), quats.repeat_interleave(11, 0), log_thin(110))
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(110))
    assert (state["garo_last"]["redundant"], state["garo_last"]["pruned"]) == (110, 55)


def test_fewer_gaussians_than_neighbours():
    params, optimizers = flat_plane_params(5)  # k = 10 > N - 1
    state = run_step(garo(rho_max=0.5, tau_curvature=0.01), params, optimizers, fake_info(5))
    assert (state["garo_last"]["redundant"], state["garo_last"]["pruned"], len(params["means"])) == (5, 2, 3)
    params, optimizers = flat_plane_params(1)  # nothing to compare with: never redundant
    state = run_step(garo(rho_max=1.0, tau_curvature=0.01), params, optimizers, fake_info(1))
    assert (state["garo_last"]["candidates"], state["garo_last"]["redundant"]) == (1, 0)


@pytest.mark.parametrize("case", ["all active", "none visible", "gca none visible"])
def test_empty_candidate_set_changes_nothing(case):
    params, optimizers = flat_plane_params(40)
    before = {k: v.detach().clone() for k, v in params.items()}
    objects = dict(params)
    moments = {k: o.state[o.param_groups[0]["params"][0]]["exp_avg"].clone() for k, o in optimizers.items()}
    radii = torch.zeros(1, 40, dtype=torch.int32) if "none visible" in case else None
    mode = "gca" if case.startswith("gca") else "full"
    state = run_step(garo(rho_max=1.0, mode=mode), params, optimizers, fake_info(40, ndc=2.0, radii=radii))
    assert (state["garo_last"]["candidates"], state["garo_last"]["pruned"]) == (0, 0)
    for k, p in params.items():
        assert p is objects[k], k  # nothing removed: the same tensors, not copies
        assert torch.equal(p.detach(), before[k]), k
        opt = optimizers[k]
        assert opt.param_groups[0]["params"][0] is p
        assert torch.equal(opt.state[p]["exp_avg"], moments[k]), k


def test_nan_gradients_make_no_candidate_and_spare_the_rest():
    params, optimizers = flat_plane_params(40)
    info = fake_info(40)
    info["means2d"].grad[0, 5:15, 1] = NAN
    state = run_step(garo(rho_max=1.0, tau_curvature=0.01), params, optimizers, info)
    assert (state["garo_last"]["candidates"], state["garo_last"]["pruned"]) == (30, 30)
    assert params["opacities"].detach().tolist() == list(range(5, 15))


# --- properties -----------------------------------------------------------------------------------


@st.composite
def selections(draw):
    n = draw(st.integers(1, 80))
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    flat = draw(st.booleans())
    points = torch.rand(n, 3, generator=g)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    if flat:
        points[: n // 2, 2] = 0.0
        nrm[: n // 2] = torch.tensor([0.0, 0.0, 1.0])
    activity = torch.rand(n, generator=g)
    activity[torch.rand(n, generator=g) < 0.1] = NAN
    counts = torch.where(torch.isnan(activity), 0.0, 1.0)
    return dict(
        activity=activity,
        counts=counts,
        points=points,
        unit_normals=nrm,
        mode=draw(st.sampled_from(["full", "oaa", "gca"])),
        tau_activity=draw(st.floats(0.0, 1.1)),
        n_max=draw(st.integers(0, 100)),
        tau_curvature=draw(st.floats(0.0, 1.1)),
        rho_max=draw(st.floats(-1.0, 2.0)),
        k=draw(st.integers(1, 12)),
    )


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(selections())
def test_selection_prunes_min_of_cap_and_redundant_and_only_redundant_ones(args):
    out = select_redundant(**args)
    n = len(args["points"])
    cap = math.floor(min(max(args["rho_max"], 0.0), 1.0) * n)
    prune = out["prune"]
    assert prune.numel() == min(cap, out["redundant"]) <= math.floor(max(args["rho_max"], 0.0) * n)
    assert len(set(prune.tolist())) == prune.numel()
    assert out["redundant"] <= out["candidates"]
    if args["mode"] != "gca":
        assert out["candidates"] <= max(args["n_max"], 0)
        assert (args["activity"][prune] < args["tau_activity"]).all()
    assert (args["counts"][prune] > 0).all()
    if args["mode"] != "oaa" and prune.numel():
        c = curvature(args["points"], args["unit_normals"], prune, args["k"])
        assert (c < args["tau_curvature"]).all() and torch.equal(c, c.sort().values)


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.integers(2, 60),
    st.floats(0.0, 1.0),
    st.integers(0, 2**31 - 1),
    st.sampled_from(["full", "oaa", "gca"]),
)
def test_pruning_keeps_parameters_moments_and_state_rows_aligned(n, rho, seed, mode):
    g = torch.Generator().manual_seed(seed)
    pts = plane(n, seed)
    pts[: n // 2, 2] = torch.rand(n // 2, generator=g)  # half flat, half scattered
    params, optimizers = make_params(pts, torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g))
    ids = torch.arange(n, dtype=torch.float32)
    for key, opt in optimizers.items():  # distinct moments per row, tied to the row id
        st_ = opt.state[opt.param_groups[0]["params"][0]]
        shape = (n,) + (1,) * (st_["exp_avg"].dim() - 1)
        st_["exp_avg"] = ids.view(shape).expand_as(st_["exp_avg"]).clone() + 0.5
        st_["exp_avg_sq"] = ids.view(shape).expand_as(st_["exp_avg_sq"]).clone() * 2 + 1
    before = {k: v.detach().clone() for k, v in params.items()}
    strategy = garo(mode=mode, rho_max=rho, tau_activity=0.5, tau_curvature=0.3)
    state = strategy.initialize_state()
    state["garo_grad"] = torch.rand(n, generator=g) * ids  # activity varies by row
    state["garo_count"] = ids + 1
    grad0, count0 = state["garo_grad"].clone(), state["garo_count"].clone()
    strategy.step_post_backward(params, optimizers, state, 1, fake_info(n))
    kept = params["opacities"].detach().long()
    pruned = n - len(kept)
    assert pruned == state["garo_last"]["pruned"] <= math.floor(rho * n)
    assert torch.equal(kept, kept.sort().values) and len(set(kept.tolist())) == len(kept)
    for key, p in params.items():
        assert torch.equal(p.detach(), before[key][kept]), key
        st_ = optimizers[key].state[p]
        shape = (len(kept),) + (1,) * (p.dim() - 1)
        assert torch.equal(st_["exp_avg"], (kept.float().view(shape) + 0.5).expand_as(p)), key
        assert torch.equal(st_["exp_avg_sq"], (kept.float().view(shape) * 2 + 1).expand_as(p)), key
    assert torch.equal(state["garo_grad"], grad0[kept])  # this step's gradient was 0
    assert torch.equal(state["garo_count"], count0[kept] + 1)


def test_filtered_info_keeps_every_per_gaussian_entry_of_the_kept_rows():
    n, keep = 6, torch.tensor([True, False, True, True, False, True])
    rows = torch.arange(n, dtype=torch.float32)
    info = fake_info(n, radii=torch.arange(n)[None] + 1)
    info["means2d"].grad = rows.view(1, n, 1).expand(1, n, 2).clone()
    per_camera = {"depths": rows[None], "conics": rows.view(1, n, 1).expand(1, n, 3), "opacities": rows[None]}
    geometry = {"means3d": rows[:, None].expand(n, 3), "quats3d": rows[:, None].expand(n, 4)}
    info.update(per_camera, **geometry, scales3d=rows[:, None].expand(n, 3), width=W)
    out = restrict_info(info, keep)
    kept = rows[keep]
    assert torch.equal(out["radii"], (torch.arange(n)[None] + 1)[:, keep])
    assert torch.equal(out["means2d"].grad[0, :, 0], kept) and out["means2d"].shape == (1, 4, 2)
    for key in ("depths", "opacities"):
        assert torch.equal(out[key][0], kept), key
    assert torch.equal(out["conics"][0, :, 0], kept)
    for key in ("means3d", "quats3d", "scales3d"):
        assert torch.equal(out[key][:, 0], kept), key
    assert out["width"] == W and info["means2d"].shape == (1, n, 2)  # the original is left alone
    info["means2d"].grad = None
    assert restrict_info(info, keep)["means2d"].grad is None


def packed_from(info: dict) -> dict:
    """The packed form of an unpacked info: one row per (camera, Gaussian) pair with a positive radius."""
    sel = info["radii"] > 0
    camera_ids, gaussian_ids = torch.where(sel)
    m2d = info["means2d"].detach()[sel].clone().requires_grad_(True)
    m2d.grad = info["means2d"].grad[sel].clone()
    packed = {k: v for k, v in info.items() if not isinstance(v, torch.Tensor) or k in ("means3d",)}
    packed.update(means2d=m2d, radii=info["radii"][sel], depths=info["depths"][sel], conics=info["conics"][sel])
    packed.update(camera_ids=camera_ids, gaussian_ids=gaussian_ids)
    return packed


def test_filtered_packed_info_gives_the_unpacked_bookkeeping():
    """Packed info after GARO removed some Gaussians: the same gradient norms and counts per kept Gaussian
    as the unpacked info of the same render, through gsplat's own update."""
    g = torch.Generator().manual_seed(0)
    c, n = 2, 7
    keep = torch.tensor([True, False, True, True, False, True, True])
    radii = torch.randint(0, 3, (c, n), generator=g, dtype=torch.int32)  # zeros: not seen by that camera
    radii[:, 2] = 0  # a kept Gaussian no camera sees
    info = {"means2d": torch.zeros(c, n, 2, requires_grad=True), "radii": radii, "width": W, "height": H}
    info["means2d"].grad = torch.rand(c, n, 2, generator=g)
    info.update(n_cameras=c, gaussian_ids=None, depths=torch.rand(c, n, generator=g), conics=torch.rand(c, n, 3))
    info["means3d"] = torch.rand(n, 3, generator=g)
    strategy = GaroStrategy()
    params = {"means": torch.zeros(int(keep.sum()), 3)}
    want = strategy.gradient_norms(params, restrict_info(info, keep), packed=False)
    packed = restrict_info(packed_from(info), keep)  # packed: told by its gaussian_ids
    got = strategy.gradient_norms(params, packed, packed=True)
    torch.testing.assert_close(got, want)
    assert int(packed["gaussian_ids"].max()) < int(keep.sum()) and len(packed["camera_ids"]) == len(packed["radii"])
    assert torch.equal(packed["means3d"], info["means3d"][keep])


def test_strategy_modes_oaa_and_gca_decide_as_their_names_say():
    # A sphere of inactive Gaussians: activity alone (oaa) prunes the least active; the paper's
    # full rule prunes none (not flat). A flat plane of active Gaussians: only gca prunes it.
    params, optimizers = sphere_params(50)
    info = fake_info(50)
    info["means2d"].grad[0, :, 0] = torch.linspace(0.9, 0.0, 50) / (W / 2)  # row 49 least active
    for mode, pruned in (("full", []), ("oaa", [49, 48, 47, 46, 45])):
        p, o = make_params(*(params[k].detach() for k in ("means", "quats", "scales")))
        run_step(garo(mode=mode, rho_max=0.1, tau_curvature=0.01), p, o, info)
        assert sorted(set(range(50)) - set(p["opacities"].detach().long().tolist()), reverse=True) == pruned, mode
    for mode, pruned in (("full", 0), ("gca", 5)):
        p, o = flat_plane_params(50)
        state = run_step(garo(mode=mode, rho_max=0.1, tau_curvature=0.01), p, o, fake_info(50, ndc=2.0))
        assert state["garo_last"]["pruned"] == pruned == 50 - len(p["means"]), mode


def test_a_single_redundant_gaussian_is_removed():
    params, optimizers = flat_plane_params(40)
    state = run_step(garo(rho_max=1 / 40, tau_curvature=0.01), params, optimizers, fake_info(40))
    assert state["garo_last"]["pruned"] == 1 and params["opacities"].detach().tolist() == list(range(1, 40))


def test_initial_state_has_every_garo_entry_a_checkpoint_restores():
    # set_extra_state restores only the keys the fresh state has: all three must be there.
    state = GaroStrategy().initialize_state()
    assert (state["garo_grad"], state["garo_count"], state["garo_last"]) == (None, None, {})
    assert state["scene_scale"] == 1.0 and GaroStrategy().initialize_state(3.5)["scene_scale"] == 3.5


def test_packed_info_counts_by_the_rasterizer_ids():
    params, optimizers = flat_plane_params(6)
    strategy = garo(garo_start_iter=100, garo_stop_iter=200, refine_stop_iter=1000)
    ids = torch.tensor([4, 0, 4])
    m2d = torch.zeros(3, 2, requires_grad=True)
    m2d.grad = torch.tensor([[0.5, 0.0], [0.25, 0.0], [0.75, 0.0]]) / (W / 2)
    info = {"means2d": m2d, "radii": torch.ones(3), "width": W, "height": H, "n_cameras": 1, "gaussian_ids": ids}
    state = strategy.initialize_state()
    strategy.step_post_backward(params, optimizers, state, 1, info, packed=True)
    assert state["garo_count"].tolist() == [1.0, 0, 0, 0, 2.0, 0]
    torch.testing.assert_close(state["garo_grad"], torch.tensor([0.25, 0, 0, 0, 1.25, 0]))
    assert state["count"].tolist() == [1.0, 0, 0, 0, 2.0, 0]  # densification's own counts, packed too


def test_densification_after_garo_gets_the_optimizers():
    # At an opacity-reset step DefaultStrategy resets opacities and their Adam moments.
    params, optimizers = flat_plane_params(6)
    strategy = garo(garo_start_iter=100, garo_stop_iter=200, refine_stop_iter=1000, reset_every=2)
    state = strategy.initialize_state()
    strategy.step_post_backward(params, optimizers, state, 2, fake_info(6))
    cap = math.log(0.01 / 0.99)  # logit(2 * prune_opa)
    torch.testing.assert_close(params["opacities"].detach(), torch.full((6,), cap))
    opt = optimizers["opacities"]
    assert torch.equal(opt.state[opt.param_groups[0]["params"][0]]["exp_avg"], torch.zeros(6))


# --- pruning by contribution ----------------------------------------------------------------------


def test_least_contributing_marks_exactly_floor_ratio_n_smallest_ties_by_index():
    w = torch.tensor([3.0, 1.0, 2.0, 1.0, 5.0, 0.5, 1.0])
    assert least_contributing(w, 0.5).tolist() == [False, True, False, True, False, True, False]  # floor(3.5)
    assert least_contributing(w, 0.3).tolist() == [False, True, False, False, False, True, False]  # ties: index
    assert least_contributing(w, 0.2).tolist() == [False, False, False, False, False, True, False]  # floor(1.4)
    assert not least_contributing(w, 0.1).any()  # floor(0.7) = 0
    assert not least_contributing(w, 0.0).any()
    assert least_contributing(torch.zeros(0), 0.5).tolist() == []
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match=r"^prune ratio must be in \[0, 1\), got"):
            least_contributing(w, bad)


def test_prune_by_contribution_removes_rows_everywhere_and_reports_the_count():
    params, optimizers = flat_plane_params(10)
    strategy = GaroStrategy()
    state = strategy.initialize_state()
    state["static"] = torch.arange(10) % 2 == 0
    state["static_offset"] = torch.arange(10, dtype=torch.float32)[:, None].expand(10, 10).clone()
    contribution = torch.tensor([5.0, 0.1, 4.0, 0.2, 3.0, 9.0, 8.0, 0.3, 7.0, 6.0])
    assert strategy.prune_by_contribution(params, optimizers, state, contribution, 0.3) == 3
    kept = [0, 2, 4, 5, 6, 8, 9]
    assert params["opacities"].detach().reshape(-1).tolist() == kept
    assert state["static"].tolist() == [k % 2 == 0 for k in kept]
    assert state["static_offset"][:, 0].tolist() == kept
    assert strategy.prune_by_contribution(params, optimizers, state, torch.ones(7), 0.1) == 0
    assert len(params["means"]) == 7


# --- the baseline's mode, and the gradient GARO reads ----------------------------------------------


def test_mode_off_is_plain_densification_with_the_strategy_owned_rows():
    off, full = GaroStrategy(mode="off"), GaroStrategy(mode="full")
    owned = {"static": None, "static_offset": None, "static_step": -1}
    state = off.initialize_state()
    assert {k: state[k] for k in owned} == owned
    assert not {"garo_grad", "garo_count", "garo_last"} & set(state)
    state = full.initialize_state()
    assert {k: state[k] for k in owned} == owned
    assert state["garo_grad"] is None and state["garo_count"] is None and state["garo_last"] == {}
    assert not any(GaroStrategy(mode="off", garo_start_iter=0, garo_every=1).is_garo_step(s) for s in range(50))
    assert full.is_garo_step(600) and not full.is_garo_step(601)
    # A step of the baseline: no activity record and no GARO, even at a step where GARO would prune.
    params, optimizers = flat_plane_params(20)
    strategy = GaroStrategy(mode="off", garo_start_iter=1, garo_stop_iter=2, garo_every=1, refine_start_iter=10_000)
    state = run_step(strategy, params, optimizers, fake_info(20, ndc=0.5))
    assert len(params["means"]) == 20 and "garo_grad" not in state and state["count"].tolist() == [1.0] * 20


def test_activity_reads_the_gradient_densification_reads():
    params = {"means": torch.zeros(3, 3)}
    m2d = torch.zeros(1, 3, 2, requires_grad=True)
    info = {"means2d": m2d, "radii": torch.ones(1, 3), "width": W, "height": H, "n_cameras": 1, "gaussian_ids": None}
    m2d.absgrad = torch.tensor([[[2.0 / (W / 2), 0.0], [0.0, 4.0 / (H / 2)], [0.0, 0.0]]])
    sums, counts = GaroStrategy(absgrad=True).gradient_norms(params, info)  # .grad is None: absgrad is read
    torch.testing.assert_close(sums, torch.tensor([2.0, 4.0, 0.0]))
    assert counts.tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match=r"^info\['means2d'\] has no gradient"):
        GaroStrategy().gradient_norms(params, info)  # the plain gradient is asked for and absent
    del m2d.absgrad
    with pytest.raises(ValueError, match=r"^info\['means2d'\] has no gradient"):
        GaroStrategy(absgrad=True).gradient_norms(params, info)


def test_an_iteration_that_did_not_see_a_gaussian_adds_nothing_to_its_record():
    sums, counts = torch.zeros(3), torch.zeros(3)
    record(sums, counts, torch.tensor([1.0, 2.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    assert sums.tolist() == [0.0, 2.0, 0.0] and counts.tolist() == [0.0, 1.0, 0.0]
