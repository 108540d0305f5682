"""GARO's pruning rule on known geometry and its bookkeeping inside gsplat's densification.

Hard cases with exact outcomes are in test_redundancy_strategy.py (injected after the optimizer step).
"""

from __future__ import annotations

import math

import pytest
import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import duplicate, remove, split

from garo_ns.garo_strategy import GaroSettings, GaroStrategy, garo_scalars
from garo_ns.redundancy.activity import activity_candidates, mean_activity, record
from garo_ns.redundancy.curvature import curvature
from garo_ns.redundancy.knn import knn_brute, knn_grid
from garo_ns.redundancy.normals import normals
from garo_ns.redundancy.select import select_redundant

# A quaternion (w, x, y, z) is the identity here, so a Gaussian's smallest axis is its normal.


def quat_from_normal(n: torch.Tensor) -> torch.Tensor:
    """Quaternions rotating z onto each unit vector n."""
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(n)
    axis = torch.cross(z, n, dim=-1)
    s = axis.norm(dim=-1, keepdim=True)
    c = (z * n).sum(-1, keepdim=True)
    half = torch.atan2(s, c) / 2
    axis = torch.where(s > 1e-8, axis / s.clamp_min(1e-12), torch.tensor([1.0, 0.0, 0.0]))
    return torch.cat([torch.cos(half), axis * torch.sin(half)], -1)


def plane_and_sphere(n_plane=600, n_sphere=400, seed=0):
    """Flat Gaussians on the plane z = 0 and on a small sphere above it, normals along the surface normal."""
    g = torch.Generator().manual_seed(seed)
    pp = torch.rand(n_plane, 3, generator=g) * 2 - 1
    pp[:, 2] = 0.0
    pn = torch.tensor([0.0, 0.0, 1.0]).expand(n_plane, 3)
    sn = torch.nn.functional.normalize(torch.randn(n_sphere, 3, generator=g), dim=-1)
    sp = sn * 0.15 + torch.tensor([0.0, 0.0, 0.6])
    points = torch.cat([pp, sp])
    quats = quat_from_normal(torch.cat([pn, sn]))
    scales = torch.tensor([0.02, 0.02, 0.001]).expand(len(points), 3).clone()
    return points, quats, scales


def test_normals_are_the_smallest_axis_and_follow_the_deformation():
    points, quats, scales = plane_and_sphere(10, 10)
    n = normals(quats, scales)
    torch.testing.assert_close(n[:10].abs(), torch.tensor([0.0, 0.0, 1.0]).expand(10, 3), atol=1e-6, rtol=0)
    # A deformation rotating everything by 90 degrees about x carries the plane's normal onto y.
    rot = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    w1, v1 = rot[0], rot[1:]
    w2, v2 = quats[:, :1], quats[:, 1:]
    composed = torch.cat(
        [w1 * w2 - (v2 * v1).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.cross(v1.expand_as(v2), v2, dim=-1)], -1
    )
    n2 = normals(composed, scales)  # canonical scales choose the axis, deformed rotation carries it
    torch.testing.assert_close(n2[:10].abs(), torch.tensor([0.0, 1.0, 0.0]).expand(10, 3), atol=1e-6, rtol=0)


def test_known_geometry_prunes_the_plane_not_the_sphere():
    points, quats, scales = plane_and_sphere()
    n = len(points)
    activity = torch.full((n,), 1e-5)  # every Gaussian inactive
    counts = torch.ones(n)
    for rho in (0.02, 0.1, 0.3):
        out = select_redundant(activity, counts, points, normals(quats, scales), "full", 5e-5, 10_000, 0.5, rho, 10)
        pruned = out["prune"]
        assert 0 < pruned.numel() <= math.floor(rho * n)
        assert (pruned < 600).all(), "only plane Gaussians are flat"
    # The plane's curvature is zero; every sphere Gaussian's is above it (neighbours' normals turn).
    c = curvature(points, normals(quats, scales), torch.arange(n), 10)
    assert c[:600].max() < 1e-5 and c[600:].min() > 1e-3 and c[600:].mean() > 0.01


def test_activity_filters_candidates_and_oaa_mode_ranks_by_activity():
    points, quats, scales = plane_and_sphere()
    n = len(points)
    activity = torch.linspace(0, 1e-4, n)  # the first half is below tau
    counts = torch.ones(n)
    out = select_redundant(activity, counts, points, normals(quats, scales), "full", 5e-5, 10_000, 0.5, 1.0, 10)
    # The candidates are exactly the inactive half; all lie on the flat plane, so rho_max 1 prunes every one.
    inactive = torch.nonzero(activity < 5e-5).squeeze(1)
    assert out["candidates"] == len(inactive) and 0 < len(inactive) < n
    assert sorted(out["prune"].tolist()) == inactive.tolist()
    oaa = select_redundant(activity, counts, points, points, "oaa", 5e-5, 10_000, 0.5, 0.01, 10)
    assert torch.equal(oaa["prune"], torch.arange(math.floor(0.01 * n)))  # lowest activity first
    few = select_redundant(activity, counts, points, normals(quats, scales), "full", 5e-5, 7, 0.5, 1.0, 10)
    assert few["candidates"] == 7


def test_gca_mode_ranks_every_visible_gaussian_flattest_first():
    # 12,000 visible Gaussians, more than any n_max = 10k sample: the flattest 100 sit on a plane
    # at the end of the index range, every other Gaussian has neighbours whose normals turn.
    g = torch.Generator().manual_seed(3)
    n_noise, n_flat = 11_900, 100
    noise_pts = torch.rand(n_noise, 3, generator=g) * 4 + torch.tensor([0.0, 0.0, 2.0])
    noise_nrm = torch.nn.functional.normalize(torch.randn(n_noise, 3, generator=g), dim=-1)
    flat_pts = torch.rand(n_flat, 3, generator=g) * 0.2
    flat_pts[:, 2] = 0.0
    sign = torch.where(torch.rand(n_flat, 1, generator=g) < 0.5, -1.0, 1.0)  # normals of both orientations
    flat_nrm = torch.tensor([0.0, 0.0, 1.0]).expand(n_flat, 3) * sign
    points, nrm = torch.cat([noise_pts, flat_pts]), torch.cat([noise_nrm, flat_nrm])
    n = len(points)
    activity, counts = torch.full((n,), 1.0), torch.ones(n)  # all active: only GCA can pick them
    counts[:50] = 0  # never seen: never candidates
    out = select_redundant(activity, counts, points, nrm, "gca", 5e-5, 10_000, 0.5, 100 / n + 1e-9, 10)
    assert out["candidates"] == n - 50  # every visible Gaussian, not a sample of n_max
    assert sorted(out["prune"].tolist()) == list(range(n_noise, n))  # exactly the flat ones
    c = curvature(points, nrm, out["prune"], 10)
    assert torch.equal(c, c.sort().values)  # flattest first


@pytest.mark.parametrize("method", [knn_brute, knn_grid])
def test_knn_methods_are_exact_on_clustered_data_with_outliers(method):
    g = torch.Generator().manual_seed(1)
    sheets = torch.rand(3000, 3, generator=g) * 2 - 1
    sheets[:, 2] = torch.randint(0, 3, (3000,), generator=g).float() * 0.5
    ball = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1) * 0.3
    far = torch.rand(30, 3, generator=g) * 40 - 20  # sparse outliers take the exact fallback
    pts = torch.cat([sheets, ball, far])
    pts[3] = float("nan")
    pts[10:15] = pts[9]
    q = torch.cat([torch.randperm(len(pts), generator=g)[:400], torch.arange(len(pts) - 30, len(pts))])
    q = q[q != 3]
    got = method(pts, q, 10)
    fin = torch.isfinite(pts).all(-1)
    d = torch.cdist(pts[q].double(), torch.where(fin[:, None], pts, 0).double()) ** 2
    d[torch.arange(len(q)), q] = float("inf")
    d[:, ~fin] = float("inf")
    ref = torch.topk(d, 10, largest=False).values
    torch.testing.assert_close(torch.gather(d, 1, got).sort(1).values, ref)  # same distances (ties may swap)


def test_knn_matches_brute_force_and_excludes_itself():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(3000, 3, generator=g)
    pts[5] = pts[6]  # duplicate positions
    q = torch.tensor([0, 5, 6, 2999])
    got = knn_brute(pts, q, 8, query_chunk=3, point_chunk=700)
    d = torch.cdist(pts[q].double(), pts.double())
    d[torch.arange(4), q] = float("inf")
    ref = torch.topk(d, 8, largest=False).indices
    assert torch.equal(torch.sort(got, 1).values, torch.sort(ref, 1).values)
    assert not (got == q[:, None]).any()
    assert 6 in got[1] and 5 in got[2]


def test_activity_accounting_ignores_invisible_iterations_and_nan():
    sums, counts = torch.zeros(4), torch.zeros(4)
    m2d = torch.zeros(1, 4, 2, requires_grad=True)
    (m2d * torch.tensor([[[1.0, 0.0], [0.0, 2.0], [3.0, 0.0], [float("nan"), 0.0]]])).sum().backward()
    info = {"means2d": m2d, "radii": torch.tensor([[1, 1, 0, 1]]), "width": 2, "height": 2, "n_cameras": 1}
    info["gaussian_ids"] = None
    strategy, params = GaroStrategy(), {"means": torch.zeros(4, 3)}
    for _ in range(3):
        record(sums, counts, *strategy.gradient_norms(params, info))
    info["radii"] = torch.tensor([[1, 0, 0, 0]])
    record(sums, counts, *strategy.gradient_norms(params, info))
    g = mean_activity(sums, counts)
    assert torch.equal(counts, torch.tensor([4.0, 3.0, 0.0, 0.0]))
    torch.testing.assert_close(g[:2], torch.tensor([1.0, 2.0]))  # invisible steps do not dilute the mean
    assert torch.isnan(g[2:]).all()  # never seen (or only NaN): no estimate
    assert activity_candidates(g, 10.0, 100).tolist() == [0, 1]


def make_params(points, quats, scales):
    n = len(points)
    params = {
        "means": torch.nn.Parameter(points.clone()),
        "quats": torch.nn.Parameter(quats.clone()),
        "scales": torch.nn.Parameter(scales.log()),
        "opacities": torch.nn.Parameter(torch.zeros(n, 1)),
    }
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for p in params.values():
        p.grad = torch.ones_like(p)
    for o in optimizers.values():
        o.step()
    return params, optimizers


def test_state_stays_aligned_through_clone_split_and_prune():
    points, quats, scales = plane_and_sphere(20, 10)
    params, optimizers = make_params(points, quats, scales)
    strategy = GaroStrategy()
    state = strategy.initialize_state()
    state["garo_grad"] = torch.arange(30.0)
    state["garo_count"] = torch.arange(30.0) + 1
    mask = torch.zeros(30, dtype=torch.bool)
    mask[[3, 7]] = True
    duplicate(params, optimizers, state, mask)
    assert state["garo_grad"][-2:].tolist() == [3.0, 7.0] and len(state["garo_count"]) == 32
    mask = torch.zeros(32, dtype=torch.bool)
    mask[0] = True
    split(params, optimizers, state, mask)
    assert len(state["garo_grad"]) == 33 and state["garo_grad"][-2:].tolist() == [0.0, 0.0]
    mask = torch.zeros(33, dtype=torch.bool)
    mask[:5] = True
    remove(params, optimizers, state, mask)
    assert len(state["garo_grad"]) == len(params["means"]) == 28
    assert torch.equal(state["garo_count"] - state["garo_grad"], torch.ones(28))  # pairs moved together


def fake_info(n, radii=None):
    m2d = torch.zeros(1, n, 2, requires_grad=True)
    m2d.grad = torch.full((1, n, 2), 1e-6)
    return {
        "means2d": m2d,
        "radii": torch.ones(1, n, dtype=torch.int32) if radii is None else radii,
        "width": 2,
        "height": 2,
        "n_cameras": 1,
        "gaussian_ids": None,
    }


def test_strategy_step_prunes_at_most_rho_and_keeps_everything_aligned():
    points, quats, scales = plane_and_sphere()
    params, optimizers = make_params(points, quats, scales)
    strategy = GaroStrategy(
        garo_start_iter=10, garo_every=10, refine_start_iter=1000, rho_max=0.05, activity_window="training"
    )
    state = strategy.initialize_state()
    for step in range(1, 11):
        strategy.step_post_backward(params, optimizers, state, step, fake_info(len(params["means"])))
    last = state["garo_last"]
    assert last["pruned"] == math.floor(0.05 * 1000) and last["candidates"] == 1000
    n = len(params["means"])
    assert n == 950 and all(len(p) == n for p in params.values())
    for key, opt in optimizers.items():
        assert opt.state[opt.param_groups[0]["params"][0]]["exp_avg"].shape[0] == n
    assert (params["means"][:, 2].abs() > 0.1).sum() == 400  # the sphere is intact
    assert torch.equal(state["garo_count"], torch.full((n,), 10.0))  # the "training" window: no restart


@pytest.mark.parametrize("window", ["training", "garo_step"])
def test_activity_is_the_mean_over_visible_steps_across_garo_steps(window):
    # 8 Gaussians on a line, far apart (curvature cannot matter: tau_curvature 2 accepts everyone,
    # and tau_activity 0 makes no candidate, so nothing is pruned and rows keep their identity).
    n, w, h = 8, 800, 600
    points = torch.stack([torch.arange(n, dtype=torch.float32), torch.zeros(n), torch.zeros(n)], -1)
    params, optimizers = make_params(points, torch.tensor([1.0, 0, 0, 0]).expand(n, 4), torch.full((n, 3), 0.01))
    strategy = GaroStrategy(
        garo_start_iter=5, garo_every=5, refine_start_iter=10_000, tau_activity=0.0, activity_window=window
    )
    state = strategy.initialize_state()
    g = torch.Generator().manual_seed(0)
    norms, seen = torch.zeros(24, n), torch.zeros(24, n, dtype=torch.bool)
    for step in range(1, 25):
        pix = torch.rand(1, n, 2, generator=g) * 1e-6  # gradient in pixels
        visible = torch.rand(1, n, generator=g) < 0.6
        m2d = torch.zeros(1, n, 2, requires_grad=True)
        m2d.grad = pix.clone()
        info = {"means2d": m2d, "radii": visible.int(), "width": w, "height": h, "n_cameras": 1, "gaussian_ids": None}
        strategy.step_post_backward(params, optimizers, state, step, info)
        ndc = pix[0] * torch.tensor([w / 2, h / 2])  # pixels to NDC, as 3DGS thresholds it
        norms[step - 1], seen[step - 1] = ndc.norm(dim=-1), visible[0]
    assert [strategy.is_garo_step(s) for s in (5, 10, 15, 20)] == [True] * 4
    since = 0 if window == "training" else 20  # the last GARO step was at step 20
    want = (norms[since:] * seen[since:]).sum(0) / seen[since:].sum(0)
    got = mean_activity(state["garo_grad"], state["garo_count"])
    torch.testing.assert_close(got, want, rtol=1e-5, atol=0, equal_nan=True)  # NaN: not seen in the window
    assert torch.isfinite(got).sum() >= 6


@pytest.mark.parametrize("mode", ["off", "full"])
def test_opacities_are_first_reset_at_reset_every_not_at_step_0(mode):
    """gsplat resets whenever step % reset_every == 0, step 0 included; 3DGS and D-3DGS first reset
    at reset_every. Step 0 still records the gradients densification will read."""
    n = 30
    points, quats, scales = plane_and_sphere(20, 10)
    params, optimizers = make_params(points, quats, scales)
    with torch.no_grad():
        params["opacities"].fill_(2.0)  # sigmoid 0.88, far above the reset value
    strategy = GaroStrategy(
        mode=mode, refine_start_iter=500, refine_stop_iter=15_000, reset_every=3000, prune_opa=0.005
    )
    state = strategy.initialize_state()
    strategy.step_post_backward(params, optimizers, state, 0, fake_info(n))
    assert torch.equal(params["opacities"].detach(), torch.full((n, 1), 2.0))
    assert torch.equal(state["count"], torch.ones(n))  # step 0's gradients are recorded
    strategy.step_post_backward(params, optimizers, state, 3000, fake_info(n))
    reset = torch.sigmoid(params["opacities"].detach())
    torch.testing.assert_close(reset, torch.full((n, 1), 0.01), rtol=1e-5, atol=0)  # min(p, 2 x prune_opa)
    # reset_at_start keeps gsplat's behaviour.
    params, optimizers = make_params(points, quats, scales)
    with torch.no_grad():
        params["opacities"].fill_(2.0)
    gsplat_like = GaroStrategy(mode=mode, refine_start_iter=500, reset_every=3000, reset_at_start=True)
    gsplat_like.step_post_backward(params, optimizers, gsplat_like.initialize_state(), 0, fake_info(n))
    assert torch.sigmoid(params["opacities"].detach()).max() < 0.011


def test_the_recipe_resets_opacity_where_the_official_code_does():
    from garo_ns.garo_model import GaroModelConfig

    strategy = GaroModelConfig().make_strategy()
    assert (strategy.reset_every, strategy.reset_at_start, strategy.refine_stop_iter) == (3000, False, 15_000)


def test_default_schedule_prunes_at_every_refinement_step_and_only_there():
    strategy = GaroStrategy(refine_start_iter=500, refine_stop_iter=15_000, refine_every=100)
    steps = [s for s in range(0, 20_000) if strategy.is_garo_step(s)]
    assert steps == list(range(600, 15_000, 100))  # gsplat refines at s > 500, s % 100 == 0, s < 15k
    custom = GaroStrategy(garo_start_iter=1000, garo_stop_iter=3000, garo_every=500)
    assert [s for s in range(0, 20_000) if custom.is_garo_step(s)] == [1000, 1500, 2000, 2500]


def test_model_config_declares_the_schedule_once():
    from garo_ns.garo_model import GaroModelConfig

    cfg = GaroModelConfig()
    assert (cfg.garo_start, cfg.garo_stop, cfg.garo_every) == (None, None, None)  # follow densification
    strategy = GaroStrategy(
        refine_start_iter=cfg.warmup_length, refine_stop_iter=cfg.stop_split_at, refine_every=cfg.refine_every
    )
    assert strategy.garo_schedule() == (cfg.warmup_length + 1, cfg.stop_split_at, cfg.refine_every)


def test_the_settings_reach_the_strategy_under_their_own_names():
    """Every GARO setting of the model config arrives in the strategy's field of the same meaning."""
    settings = GaroSettings(
        garo_mode="gca", tau_activity=1e-4, n_max=123, tau_curvature=0.25, rho_max=0.05, k_neighbors=7,
        garo_start=300, garo_stop=9000, garo_every=200, garo_activity_window="training",
    )  # fmt: skip
    strategy = GaroStrategy(**settings.garo_arguments())
    got = {k: getattr(strategy, k) for k in settings.garo_arguments()}
    assert got == {
        "mode": "gca", "tau_activity": 1e-4, "n_max": 123, "tau_curvature": 0.25, "rho_max": 0.05,
        "k_neighbors": 7, "garo_start_iter": 300, "garo_stop_iter": 9000, "garo_every": 200,
        "activity_window": "training",
    }  # fmt: skip
    assert strategy.garo_schedule() == (300, 9000, 200)


def test_garo_scalars_report_the_step_that_ran_and_nothing_else():
    state = {"garo_last": {"step": 600, "candidates": 40, "redundant": 12, "pruned": 3, "seconds": 0.25,
                           "num_gaussians": 997}}  # fmt: skip
    assert garo_scalars(state, 600) == {
        "garo/candidates": 40.0, "garo/redundant": 12.0, "garo/pruned": 3.0, "garo/seconds": 0.25,
        "garo/num_gaussians": 997.0,
    }  # fmt: skip
    assert garo_scalars(state, 700) == {}
    assert garo_scalars({"garo_last": {}}, 600) == {} and garo_scalars({}, 0) == {}


@pytest.mark.parametrize(
    "start, stop, kept, recorded",
    [
        (0, 15_000, True, True),  # refinement from step 0 on: step 0 itself never refines, so no reset
        (500, 1, True, True),  # refinement ends right after step 0: still no reset at step 0
        (-1, 15_000, False, True),  # refining at step 0 itself: gsplat's own step, which resets
        (500, 0, True, False),  # no refinement at all: gsplat's step does nothing, not even record gradients
    ],
)
def test_step_0_keeps_the_opacities_wherever_refinement_could_reset_them(start, stop, kept, recorded):
    n = 30
    points, quats, scales = plane_and_sphere(20, 10)
    params, optimizers = make_params(points, quats, scales)
    with torch.no_grad():
        params["opacities"].fill_(2.0)
    strategy = GaroStrategy(mode="off", refine_start_iter=start, refine_stop_iter=stop, reset_every=3000)
    state = strategy.initialize_state()
    strategy.step_post_backward(params, optimizers, state, 0, fake_info(n))
    untouched = params["opacities"].shape == (n, 1) and torch.equal(
        params["opacities"].detach(), torch.full((n, 1), 2.0)
    )
    assert untouched == kept
    assert (state["count"] is not None) == recorded


@pytest.mark.parametrize(
    "field, value",
    [
        ("rho_max", 1.5),  # would prune more than every candidate's cap allows
        ("rho_max", -0.1),
        ("rho_max", float("nan")),
        ("tau_activity", -1e-5),
        ("tau_curvature", float("inf")),
        ("n_max", -1),
        ("k_neighbors", 0),
        ("garo_every", 0),
        ("garo_start", -1),
        ("prune_contribution_ratio", 1.0),  # would prune everything
    ],
)
def test_garo_settings_out_of_range_fail_naming_the_flag(field, value):
    from garo_ns.errors import GaroConfigError
    from garo_ns.garo_model import GaroModelConfig

    flag = f"--pipeline.model.{field.replace('_', '-')}"
    with pytest.raises(GaroConfigError, match=f"^{flag} must be"):
        GaroModelConfig(**{field: value})  # what the command line builds


def test_garo_settings_at_their_limits_are_accepted():
    from garo_ns.garo_model import GaroModelConfig

    GaroModelConfig(rho_max=0.0, tau_activity=0.0, tau_curvature=1.0, n_max=0, k_neighbors=1, garo_every=1)
    GaroModelConfig(rho_max=1.0, garo_start=0, garo_stop=0, prune_contribution_ratio=0.5)


# --- the densification record, dense over [C, N] (gsplat's boolean indexing waits for the GPU) -------------


def _info(c, n, seed=0, packed=False):
    g = torch.Generator().manual_seed(seed)
    means2d = torch.zeros(c, n, 2, requires_grad=True)
    means2d.grad = torch.randn(c, n, 2, generator=g) * 1e-3
    radii = (torch.rand(c, n, generator=g) * 30).int() * (torch.rand(c, n, generator=g) > 0.4)
    means2d.grad[radii == 0] = torch.nan  # an invisible Gaussian's gradient must not count
    return {"width": 64, "height": 48, "n_cameras": c, "radii": radii, "means2d": means2d, "gaussian_ids": None}


@pytest.mark.parametrize("cameras", [1, 3])
@pytest.mark.parametrize("scale2d", [0, 1, 100])
def test_the_dense_densification_record_is_gsplats(cameras, scale2d):
    """Sums, counts and the largest screen radius (over cameras) as gsplat's boolean-indexed update gives them,
    accumulated over two steps; NaN gradients of unseen Gaussians stay out."""
    n = 50
    params = {"means": torch.zeros(n, 3)}
    ours = GaroStrategy(refine_scale2d_stop_iter=scale2d)
    theirs = DefaultStrategy(refine_scale2d_stop_iter=scale2d)
    s_ours = {"grad2d": None, "count": None, "radii": None}
    s_theirs = {"grad2d": None, "count": None, "radii": None}
    for seed in (0, 1):
        info = _info(cameras, n, seed)
        ours._update_state(params, s_ours, info)
        theirs._update_state(params, s_theirs, info)
    assert torch.isfinite(s_ours["grad2d"]).all()
    assert torch.allclose(s_ours["grad2d"], s_theirs["grad2d"], rtol=1e-6, atol=0)
    assert torch.equal(s_ours["count"], s_theirs["count"])
    if scale2d:
        # gsplat writes the last camera's radius where several cameras see a Gaussian; the record is the largest
        want = torch.zeros(n)
        for seed in (0, 1):
            info = _info(cameras, n, seed)
            want = torch.maximum(want, (info["radii"].float() / 64).amax(0))
        assert torch.equal(s_ours["radii"], want)
        if cameras == 1:
            assert torch.equal(s_ours["radii"], s_theirs["radii"])
    else:
        assert s_ours["radii"] is None


def test_a_step_computes_the_gradient_norms_once_for_both_records(monkeypatch):
    """Activity and densification records of a training step from one computation of the norms: the same as the
    densification record alone (gsplat's) and the activity record fed by `gradient_norms`."""
    n, cameras = 40, 2
    params = {"means": torch.zeros(n, 3)}
    strategy = GaroStrategy()
    state = strategy.initialize_state()
    calls = []
    computed = GaroStrategy._norm_sums
    monkeypatch.setattr(GaroStrategy, "_norm_sums", lambda self, info: calls.append(1) or computed(self, info))
    want = {"grad2d": None, "count": None, "radii": None}
    sums, counts = torch.zeros(n), torch.zeros(n)
    for step, seed in ((1, 0), (2, 1)):  # before refinement starts: only the records change
        info = _info(cameras, n, seed)
        strategy.step_post_backward(params, {}, state, step, info)
        DefaultStrategy()._update_state(params, want, info)
        record(sums, counts, *computed(strategy, info))
    assert len(calls) == 2
    assert torch.allclose(state["grad2d"], want["grad2d"], rtol=1e-6, atol=0)
    assert torch.equal(state["count"], want["count"])
    assert torch.equal(state["garo_grad"], sums) and torch.equal(state["garo_count"], counts)
    assert "garo_step_sums" not in info  # the caller's info is left as it was


def test_the_record_reads_absgrad_when_asked_and_names_a_missing_key():
    n = 20
    info = _info(1, n)
    info["means2d"].absgrad = info["means2d"].grad.abs() * 2
    state = {"grad2d": None, "count": None, "radii": None}
    GaroStrategy(absgrad=True)._update_state({"means": torch.zeros(n, 3)}, state, info)
    want = {"grad2d": None, "count": None, "radii": None}
    DefaultStrategy(absgrad=True)._update_state({"means": torch.zeros(n, 3)}, want, info)
    assert torch.allclose(state["grad2d"], want["grad2d"], rtol=1e-6)
    del info["radii"]
    with pytest.raises(KeyError, match="radii"):
        GaroStrategy()._update_state({"means": torch.zeros(n, 3)}, state, info)


# --- GARO's settings: each range's edges, named by flag ---------------------------------------------------------

GARO_EDGES = [  # (setting, accepted at the edge, refused just past it, the range in words)
    ("rho_max", [0.0, 1.0], [-1e-9, 1.0 + 1e-9, float("nan")], "in [0, 1]"),
    ("tau_activity", [0.0], [-1e-12, float("nan"), float("inf")], "a number >= 0"),
    ("tau_curvature", [0.0], [-1e-12, float("nan")], "a number >= 0"),
    ("n_max", [0], [-1], ">= 0"),
    ("k_neighbors", [1], [0], ">= 1"),
    ("garo_start", [0, None], [-1], "a step >= 0 or None"),
    ("garo_stop", [0, None], [-1], "a step >= 0 or None"),
    ("garo_every", [1, None], [0], ">= 1 or None"),
    ("prune_contribution_ratio", [0.0, 0.999], [1.0, -1e-9, float("nan")], "in [0, 1)"),
]


@pytest.mark.parametrize("name,ok,bad,words", GARO_EDGES)
def test_garo_settings_accept_their_edges_and_refuse_past_them_naming_the_flag(name, ok, bad, words):
    import re

    from garo_ns.errors import GaroConfigError

    for value in ok:
        GaroSettings(**{name: value}).validate_garo()
    flag = "--pipeline.model." + name.replace("_", "-")
    for value in bad:
        with pytest.raises(GaroConfigError, match=f"^{re.escape(flag)} must be {re.escape(words)}, got {value!r}$"):
            GaroSettings(**{name: value}).validate_garo()


def test_the_records_live_on_the_gaussians_device():
    """Every record starts on the device of the Gaussians (the meta device here: on a CPU-only machine, the only
    one that tells a tensor made without a device from one made on the Gaussians')."""
    meta, n = torch.device("meta"), 20
    params = {"means": torch.zeros(n, 3, device=meta)}
    info = _info(2, n)
    means2d = torch.zeros(2, n, 2, device=meta, requires_grad=True)
    means2d.grad = torch.zeros(2, n, 2, device=meta)
    info.update(means2d=means2d, radii=info["radii"].to(meta))
    strategy = GaroStrategy(refine_scale2d_stop_iter=100)
    state = {"grad2d": None, "count": None, "radii": None, "garo_grad": None, "garo_count": None}
    strategy._update_state(params, state, info)
    strategy.update_activity(params, state, info, False)
    assert {k: state[k].device.type for k in state} == {k: "meta" for k in state}


def _packed_info(n=20, seed=0):
    """A packed render's info for one camera: one row per visible Gaussian."""
    g = torch.Generator().manual_seed(seed)
    ids = torch.sort(torch.randperm(n, generator=g)[:12]).values
    means2d = torch.zeros(12, 2, requires_grad=True)
    means2d.grad = torch.randn(12, 2, generator=g) * 1e-3
    radii = (torch.rand(12, generator=g) * 30).int() + 1
    return {"width": 64, "height": 48, "n_cameras": 1, "radii": radii, "means2d": means2d, "gaussian_ids": ids,
            "camera_ids": torch.zeros(12, dtype=torch.long)}  # fmt: skip


def test_a_packed_render_keeps_gsplats_packed_record_through_the_step():
    n = 20
    params = {"means": torch.zeros(n, 3)}
    ours = GaroStrategy(refine_scale2d_stop_iter=0)
    state = ours.initialize_state()
    ours.step_post_backward(params, {}, state, 0, _packed_info(n), packed=True)
    want = {"grad2d": None, "count": None, "radii": None}
    DefaultStrategy(refine_scale2d_stop_iter=0)._update_state(params, want, _packed_info(n), packed=True)
    assert torch.equal(state["grad2d"], want["grad2d"]) and torch.equal(state["count"], want["count"])


def test_grow_budget_keeps_the_highest_gradients_that_fit():
    from garo_ns.garo_strategy import grow_budget

    grads = torch.tensor([5.0, 1.0, 9.0, 0.1, 7.0, 3.0])
    keep, held = grow_budget(grads, 2.0, 10)  # all four above 2 fit
    assert keep.tolist() == [True, False, True, False, True, True] and held == 0
    keep, held = grow_budget(grads, 2.0, 2)
    assert keep.tolist() == [False, False, True, False, True, False] and held == 2
    keep, held = grow_budget(grads, 2.0, 0)
    assert not keep.any() and held == 4
    keep, held = grow_budget(grads, 2.0, -5)  # already past the budget (pruned below it later)
    assert not keep.any() and held == 4


def test_grow_budget_counts_a_gradient_at_the_threshold_as_low_and_fills_a_room_of_one():
    from garo_ns.garo_strategy import grow_budget

    keep, held = grow_budget(torch.tensor([2.0, 3.0]), 2.0, 5)  # growth needs a gradient above the threshold
    assert keep.tolist() == [False, True] and held == 0
    keep, held = grow_budget(torch.tensor([5.0, 9.0, 7.0]), 2.0, 1)
    assert keep.tolist() == [False, True, False] and held == 2


def test_the_budget_ranks_by_the_mean_gradient_over_the_views_that_saw_each_gaussian(monkeypatch):
    """The budget ranks as densification thresholds: each Gaussian's gradient averaged over the steps that saw it
    (a Gaussian seen once is not halved, one seen often not multiplied)."""
    points, quats, scales = plane_and_sphere()
    params, optimizers = make_params(points, quats, scales)
    n = len(params["means"])
    seen = {}

    def grow(self, params, optimizers, state, step):  # gsplat's growth: what it is handed is what the test reads
        seen["g"] = state["grad2d"].clone()

    monkeypatch.setattr(DefaultStrategy, "_grow_gs", grow)
    strategy = GaroStrategy(mode="off", max_gaussians=n + 1)  # room for one
    t = strategy.grow_grad2d
    state = {"grad2d": torch.zeros(n), "count": torch.zeros(n)}
    state["grad2d"][:2] = torch.tensor([20 * t, 3 * t])  # means 2t over 10 views and 3t over one
    state["count"][:2] = torch.tensor([10.0, 1.0])
    strategy._grow_gs(params, optimizers, state, 100)
    assert seen["g"][0] == 0.0 and seen["g"][1] == state["grad2d"][1] > 0 and state["budget_held"] == 1
    strategy.max_gaussians = n  # no room: the one above the threshold after one view is held back
    state = {"grad2d": torch.zeros(n), "count": torch.zeros(n)}
    state["grad2d"][0], state["count"][0] = 1.5 * t, 1.0
    strategy._grow_gs(params, optimizers, state, 100)
    assert state["budget_held"] == 1 and not seen["g"].any()


def test_a_packed_render_s_gradient_norms_with_the_radius_record_on():
    n = 20
    strategy = GaroStrategy(refine_scale2d_stop_iter=1)
    grads, counts = strategy.gradient_norms({"means": torch.zeros(n, 3)}, _packed_info(n), packed=True)
    want = {"grad2d": None, "count": None, "radii": None}
    DefaultStrategy(refine_scale2d_stop_iter=1)._update_state({"means": torch.zeros(n, 3)}, want, _packed_info(n), True)
    assert torch.equal(grads, want["grad2d"]) and torch.equal(counts, want["count"])


@pytest.mark.parametrize("budget", [None, 1040, 1000, 900])
def test_densification_never_grows_past_max_gaussians(budget):
    points, quats, scales = plane_and_sphere()
    params, optimizers = make_params(points, quats, scales)
    strategy = GaroStrategy(
        mode="off", refine_start_iter=0, refine_every=5, reset_every=10**6, prune_opa=0.0, max_gaussians=budget
    )
    state = strategy.initialize_state()
    for step in range(1, 6):
        n = len(params["means"])
        info = fake_info(n)
        info["means2d"].grad = torch.linspace(1e-5, 1e-3, n).reshape(1, n, 1).expand(1, n, 2).contiguous()
        strategy.step_post_backward(params, optimizers, state, step, info)
    n = len(params["means"])
    grown = n - 1000
    if budget is None:
        assert grown > 100 and state["budget_held"] == 0
    else:
        assert n == max(budget, 1000) and all(len(p) == n for p in params.values())
        assert state["budget_held"] > 0
    for opt in optimizers.values():
        assert opt.state[opt.param_groups[0]["params"][0]]["exp_avg"].shape[0] == n


def test_max_gaussians_reaches_the_strategy_and_is_checked():
    from garo_ns.errors import GaroConfigError
    from garo_ns.garo_model import GaroModelConfig

    assert GaroModelConfig(max_gaussians=1234).make_strategy().max_gaussians == 1234
    for bad in (0, -1, 2.5, True):
        with pytest.raises(GaroConfigError, match="max-gaussians"):
            GaroModelConfig(max_gaussians=bad)
