"""Compaction after densification: rounds decided before they remove (noise between rounds, the per-round
bound, the total budget, a resume), the model left untouched by a refused round, bad settings, and a short
`garo-compact` training on the built-in scene (the guard reads training views only; the summary reaches
the checkpoint and garo-eval's JSON)."""

from __future__ import annotations

import copy
import json
import math
import types
from typing import Any, Dict, List

import pytest
import torch

from garo_ns.compaction import Compaction, importance
from garo_ns.compaction.guard import removal_cost, spread_indices
from garo_ns.compaction.report import round_line, scalars, stop_line, summary_for_json
from garo_ns.compaction.schedule import REASONS, last_training_step
from garo_ns.errors import GaroConfigError
from garo_ns.garo_strategy import GaroStrategy
from garo_ns.redundancy.select import lowest
from garo_ns.state.checkpoints import restore_strategy_state

N = 100


def gaussians(n: int = N, seed: int = 0):
    """Parameters with Adam moments from two real steps, and a strategy state with every kind of row."""
    g = torch.Generator().manual_seed(seed)
    params = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
            "scales": torch.nn.Parameter(torch.randn(n, 3, generator=g) - 3),
            "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
            "opacities": torch.nn.Parameter(torch.arange(n, dtype=torch.float32)),  # row ids
        }
    )
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for _ in range(2):
        for p in params.values():
            p.grad = torch.randn(p.shape, generator=g)
        for o in optimizers.values():
            o.step()
    with torch.no_grad():
        params["opacities"].copy_(torch.arange(n, dtype=torch.float32))
    return params, optimizers, g


def filled_state(strategy: GaroStrategy, n: int, g: torch.Generator) -> Dict[str, Any]:
    state = strategy.initialize_state()
    state.update(
        grad2d=torch.rand(n, generator=g),
        count=torch.rand(n, generator=g),
        garo_grad=torch.rand(n, generator=g),
        garo_count=torch.rand(n, generator=g),
        static=torch.rand(n, generator=g) > 0.5,
        static_offset=torch.rand(n, 10, generator=g),
        static_step=7,
    )
    return state


def ids(params) -> List[int]:
    return [int(i) for i in params["opacities"].detach()]


def adam_state(optimizer) -> Dict[str, torch.Tensor]:
    return dict(optimizer.state[optimizer.param_groups[0]["params"][0]])


def assert_same(params, optimizers, state, expected):
    """params / optimizers / state equal `expected` (a deep copy taken earlier), tensor by tensor."""
    e_params, e_opt, e_state = expected
    for k in e_params:
        assert torch.equal(params[k].detach(), e_params[k]), k
        opt = optimizers[k]
        assert opt.param_groups[0]["params"][0] is params[k], f"{k}: optimizer not bound to the parameter"
        got = adam_state(opt)
        assert set(got) == set(e_opt[k]), k
        for key, value in e_opt[k].items():
            assert torch.equal(got[key], value), (k, key)
    for k, v in e_state.items():
        if isinstance(v, torch.Tensor):
            assert torch.equal(state[k], v), k
        elif k != "compact":
            assert state[k] == v, k


def copy_of(params, optimizers, state):
    return (
        {k: p.detach().clone() for k, p in params.items()},
        {k: copy.deepcopy(adam_state(o)) for k, o in optimizers.items()},
        copy.deepcopy(state),
    )


def adam_step(params, optimizers, seed: int = 5):
    g = torch.Generator().manual_seed(seed)
    for k, p in params.items():
        p.grad = torch.randn(p.shape, generator=g)
        optimizers[k].step()


# --- the rounds ----------------------------------------------------------------------------------------

V = 16  # guard views


class Scene:
    """A model's guard views: view v's PSNR is 30 dB, plus `swing` (the reading's noise at this step, the
    same for every render of one step), less the summed `value[:, v]` of the Gaussians missing from the
    render (removed, or left out by `without`). It stands in for TrainingViewGuard (`psnrs`)."""

    def __init__(self, value: torch.Tensor, params):
        self.value = value  # [N, V] dB per Gaussian (by row id) and view
        self.params = params
        self.swing = 0.0
        self.renders = 0

    def psnrs(self, model: Any, without=None) -> torch.Tensor:
        self.renders += 1
        present = self.params["opacities"].detach().long()
        if without is not None:
            present = present[~without]
        lost = torch.ones(len(self.value), dtype=torch.bool)
        lost[present] = False
        return 30.0 + self.swing - self.value[lost].sum(0)

    def importance(self) -> torch.Tensor:
        """Scores by worth (ties by row id), so the cheapest Gaussians are the candidates."""
        return self.value[self.params["opacities"].detach().long()].sum(1)

    def loss(self) -> torch.Tensor:
        """What every removal so far costs each view, in dB."""
        return 30.0 + self.swing - self.psnrs(None)


def run_rounds(strategy, params, optimizers, state, scene, steps, last_step=None, between=None):
    events = []
    for step in steps:
        cost = removal_cost(None, scene)
        event = strategy.compact(params, optimizers, state, step, cost, scene.importance, last_step)
        if event is not None:
            events.append(event)
            if "stop" in event:
                break
        if between is not None:
            between(step)
    return events


def worth(n: int, free: int, per_gaussian: float, views: int = V) -> torch.Tensor:
    """[n, views]: the first `free` Gaussians cost nothing, each other one `per_gaussian` dB on view 0 only."""
    value = torch.zeros(n, views, dtype=torch.float64)
    value[free:, 0] = per_gaussian
    return value


def compaction(**settings) -> Compaction:
    return Compaction(**{"start": 0, "every": 1, "fraction": 0.2, "min_gaussians": 0, **settings})


def test_a_training_psnr_that_swings_by_a_db_between_rounds_does_not_stop_free_removals():
    """The failure of the GPU run: the training-view PSNR read 1000 steps apart swung by ~1 dB, and a round
    that cost nothing was undone. Each round now compares two renders of its own step: the swing cancels."""
    strategy = GaroStrategy(compaction=compaction(max_rounds=6, round_bound_db=0.1, budget_db=0.3))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(worth(N, N, 0.0), params)

    def fine_tune(step):
        adam_step(params, optimizers, seed=step)
        scene.swing = 1.0 if step % 2 == 0 else -0.2  # ~1 dB between consecutive readings

    events = run_rounds(strategy, params, optimizers, state, scene, range(20), between=fine_tune)
    assert [e["removed"] for e in events] == [20, 16, 12, 10, 8, 6, 0]  # every round, then the limit
    assert [e["cost_worst_db"] for e in events[:-1]] == [0.0] * 6
    summary = state["compact"]
    assert summary["reason"] == "max_rounds" and summary["stopped_step"] == 6 and summary["spent_db"] == 0.0
    assert len(params["means"]) == summary["num_gaussians_end"] == 28
    assert all(len(e["tries"]) == 1 and e["share"] == 0.2 for e in events[:-1])


def test_a_removal_over_the_bound_is_never_made_and_nothing_changes():
    """Every Gaussian costs 0.2 dB on one of 16 views: even the smallest share (2 Gaussians, 0.4 dB on that
    view) is over the 0.1 dB bound, though its mean over the views (0.025 dB) is not. Nothing is removed:
    the Gaussians, their Adam moments and the strategy's rows stay exactly as they were."""
    strategy = GaroStrategy(compaction=compaction(round_bound_db=0.1, budget_db=0.3))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(worth(N, 0, 0.2), params)
    before = copy_of(params, optimizers, state)
    events = run_rounds(strategy, params, optimizers, state, scene, range(3))
    assert len(events) == 1 and events[0]["stop"] == "round_bound" and events[0]["removed"] == 0
    assert_same(params, optimizers, state, before)
    tries = events[0]["tries"]
    # Shares 0.2, 0.1, 0.05, 0.025 and the floor 0.02 (2 Gaussians again: not measured twice).
    assert [(t["share"], t["count"]) for t in tries] == [(0.2, 20), (0.1, 10), (0.05, 5), (0.025, 2)]
    assert [t["cost_worst_db"] for t in tries] == pytest.approx([4.0, 2.0, 1.0, 0.4])
    assert tries[-1]["cost_mean_db"] == pytest.approx(0.4 / V)
    assert scene.renders == 1 + len(tries)  # the plain renders once, each try once
    summary = state["compact"]
    assert summary["num_gaussians_end"] == N and summary["spent_db"] == 0.0
    assert "over the round bound 0.1 dB" in summary["detail"] and "kept 100 of 100" in stop_line(summary)


def test_a_round_halves_its_share_until_the_cost_is_within_the_bound():
    strategy = GaroStrategy(compaction=compaction(max_rounds=1, round_bound_db=0.1, budget_db=0.3))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(worth(N, 9, 0.05), params)
    events = run_rounds(strategy, params, optimizers, state, scene, range(3))
    # 20 Gaussians (11 costly: 0.55 dB), then 10 (1 costly: 0.05 dB, within the bound)
    assert [t["count"] for t in events[0]["tries"]] == [20, 10]
    assert [t["cost_worst_db"] for t in events[0]["tries"]] == pytest.approx([0.55, 0.05])
    assert events[0]["share"] == 0.1 and events[0]["removed"] == 10 and len(params["means"]) == 90
    assert set(ids(params)) == set(range(10, 100))
    assert "removed 10 of 100" in round_line(events[0])


def test_many_cheap_rounds_spend_at_most_the_total_budget():
    n = 1000
    strategy = GaroStrategy(compaction=compaction(max_rounds=100, round_bound_db=0.1, budget_db=0.3))
    params, optimizers, g = gaussians(n)
    state = filled_state(strategy, n, g)
    scene = Scene(worth(n, 0, 0.003), params)
    events = run_rounds(strategy, params, optimizers, state, scene, range(200))
    kept = [e for e in events if e["removed"]]
    assert len(kept) >= 3 and all(0 < e["cost_worst_db"] <= 0.1 for e in kept)
    summary = state["compact"]
    assert summary["reason"] == "budget" and "left of the 0.3 dB budget" in summary["detail"]
    assert summary["spent_db"] == pytest.approx(sum(e["cost_worst_db"] for e in kept)) and summary["spent_db"] <= 0.3
    assert float(scene.loss().max()) <= 0.3 + 1e-9  # what the removals cost in the end, on the worst view
    assert events[-1]["cost_worst_db"] > 0.3 - summary["spent_db"]  # the round refused would have overspent


def test_a_resumed_run_makes_the_same_rounds_as_an_unbroken_one(tmp_path):
    """Stopped after step 9 and resumed from the checkpoint: nerfstudio runs `max_num_iterations` (10) more
    steps after the loaded one, so the run ends at step 19, not 9, and its rounds are the unbroken run's."""
    settings = compaction(every=3, max_rounds=100, round_bound_db=0.1, budget_db=0.5)

    def fresh():
        strategy = GaroStrategy(compaction=settings)
        params, optimizers, g = gaussians(1000)
        state = filled_state(strategy, 1000, g)
        return strategy, params, optimizers, state, Scene(worth(1000, 300, 0.003), params)

    strategy, params, optimizers, state, scene = fresh()
    unbroken = run_rounds(strategy, params, optimizers, state, scene, range(20), last_step=last_training_step(0, 20))

    strategy, params, optimizers, state, scene = fresh()
    # Interrupted after step 9 (its checkpoint), then resumed with max_num_iterations=10.
    first = run_rounds(strategy, params, optimizers, state, scene, range(10), last_step=last_training_step(0, 20))
    torch.save({"state": dict(state), "params": dict(params)}, tmp_path / "ckpt.pt")
    saved = torch.load(tmp_path / "ckpt.pt", weights_only=False)
    strategy, params, optimizers, state, scene = fresh()
    restore_strategy_state(state, saved["state"], "cpu")
    for k, p in saved["params"].items():
        params[k] = torch.nn.Parameter(p.detach().clone())
        optimizers[k] = torch.optim.Adam([params[k]], lr=1e-3)
    scene.params = params
    last = last_training_step(10, 10)  # resumed at step 10 (the checkpoint's step 9 + 1)
    assert last == 19
    second = run_rounds(strategy, params, optimizers, state, scene, range(10, 20), last_step=last)

    def rounds(events):
        return [(e["step"], e["share"], e["removed"], e["num_after"], e.get("stop")) for e in events]

    assert rounds(first + second) == rounds(unbroken)
    assert len([e for e in unbroken if e["removed"]]) >= 4 and unbroken[-1]["step"] == 19
    assert state["compact"]["stopped_step"] == 19 and state["compact"]["reason"] == "training_ended"
    assert len(params["means"]) == unbroken[-1]["num_after"]


def test_the_end_of_training_stops_compaction_without_measuring():
    def never(*_):
        raise AssertionError("measured")

    strategy = GaroStrategy(compaction=compaction(every=10))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(worth(N, N, 0.0), params)
    events = run_rounds(strategy, params, optimizers, state, scene, range(20), last_step=15)
    assert [(e["step"], e["removed"], e.get("stop")) for e in events] == [
        (0, 20, None),
        (10, 16, None),
        (15, 0, "training_ended"),
    ]
    summary = state["compact"]
    assert summary["detail"] == "at step 15" and summary["stopped_step"] == 15
    assert summary["num_gaussians_end"] == 64 == len(params["means"]) and summary["rounds"][-1] is events[-1]
    assert strategy.compact(params, optimizers, state, 20, never, never) is None  # stopped for good

    late = GaroStrategy(compaction=Compaction(start=500))
    state = filled_state(late, N, g)
    assert late.compact(params, optimizers, state, 100, never, never, last_step=200) is None
    assert late.compact(params, optimizers, state, 200, never, never, last_step=200)["stop"] == "training_ended"
    assert state["compact"]["detail"] == "before the first round (step 500)"


def test_stops_without_measuring_on_an_empty_model_without_views_or_a_model_too_small():
    def never(*_):
        raise AssertionError("measured")

    strategy = GaroStrategy(compaction=Compaction(start=0))
    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(0, 3))})
    state = strategy.initialize_state()
    event = strategy.compact(params, {"means": torch.optim.Adam([params["means"]])}, state, 0, never, never)
    assert event["stop"] == "empty_model" and state["compact"]["detail"] == "nothing to compact"
    assert "no Gaussians" in stop_line(state["compact"])

    params, optimizers, g = gaussians()
    blind = GaroStrategy(compaction=compaction())
    state = filled_state(blind, N, g)
    assert blind.compact(params, optimizers, state, 0, None, never)["stop"] == "no_training_views"
    assert state["compact"]["detail"] == "the model was given no training data"

    tiny = GaroStrategy(compaction=Compaction(start=0, min_gaussians=1000))
    state = filled_state(tiny, N, g)
    assert tiny.compact(params, optimizers, state, 0, never, never)["stop"] == "min_gaussians"
    assert state["compact"]["detail"] == f"{N} <= 1000" and len(params["means"]) == N

    none_left = GaroStrategy(compaction=compaction(fraction=0.005, min_fraction=0.005))
    state = filled_state(none_left, N, g)
    event = none_left.compact(params, optimizers, state, 0, never, lambda: torch.zeros(N))
    assert event["stop"] == "nothing_to_remove" and state["compact"]["detail"] == f"0.005 x {N} Gaussians"

    no_rounds = GaroStrategy(compaction=compaction(max_rounds=0))
    state = filled_state(no_rounds, N, g)
    assert no_rounds.compact(params, optimizers, state, 0, never, never)["stop"] == "max_rounds"


def test_a_strategy_without_compaction_or_a_state_without_its_summary_does_nothing():
    strategy = GaroStrategy()
    state = strategy.initialize_state()
    assert "compact" not in state
    params, optimizers, _ = gaussians()
    assert strategy.compact(params, optimizers, state, 0, lambda m: torch.zeros(V), lambda: torch.zeros(N)) is None
    with_compaction = GaroStrategy(compaction=Compaction(start=0))
    assert with_compaction.compact(params, optimizers, state, 0, None, None) is None and "compact" not in state


def test_every_round_record_and_the_summary_say_what_happened():
    """The full record of a run that removes once and then finds even the smallest share too costly: every
    key the log, the checkpoint's metadata and garo-eval's JSON read."""
    strategy = GaroStrategy(compaction=compaction(fraction=0.1, min_fraction=0.05, round_bound_db=0.1, budget_db=1))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(worth(N, 10, 0.5), params)
    events = run_rounds(strategy, params, optimizers, state, scene, range(5))
    expected = [
        {"round": 0, "step": 0, "num_before": 100, "share": 0.1, "cost_mean_db": 0.0, "cost_worst_db": 0.0,
         "removed": 10, "num_after": 90,
         "tries": [{"share": 0.1, "count": 10, "cost_mean_db": 0.0, "cost_worst_db": 0.0}]},
        {"round": 1, "step": 1, "num_before": 90, "share": 0.05, "cost_mean_db": 2.0 / V, "cost_worst_db": 2.0,
         "removed": 0, "num_after": 90, "stop": "round_bound",
         "tries": [{"share": 0.1, "count": 9, "cost_mean_db": 4.5 / V, "cost_worst_db": 4.5},
                   {"share": 0.05, "count": 4, "cost_mean_db": 2.0 / V, "cost_worst_db": 2.0}]},
    ]  # fmt: skip
    assert events == expected
    summary = state["compact"]
    assert summary["rounds"] == events
    assert {k: v for k, v in summary.items() if k not in ("rounds", "settings")} == {
        "spent_db": 0.0,
        "num_gaussians_start": 100,
        "num_gaussians_end": 90,
        "stopped_step": 1,
        "reason": "round_bound",
        "detail": "removing 4 Gaussians would cost 2.000 dB (worst view), over the round bound 0.1 dB",
    }
    assert summary["settings"]["round_bound_db"] == 0.1 and summary["settings"]["budget_db"] == 1
    assert scalars(events[1], summary["spent_db"]) == {
        "compact/removed": 0.0, "compact/num_gaussians": 90.0, "compact/spent_db": 0.0, "compact/share": 0.05,
        "compact/cost_mean_db": 2.0 / V, "compact/cost_worst_db": 2.0, "compact/stop_round_bound": 1.0,
    }  # fmt: skip
    assert scalars(events[0], 0.25)["compact/spent_db"] == 0.25 and "compact/stop_round_bound" not in scalars(
        events[0], 0.0
    )
    assert "nothing removed" in round_line(events[1]) and "2.000 dB worst view" in round_line(events[1])
    assert "kept 90 of 100 Gaussians (90%), 0.000 dB of the 1 dB budget" in stop_line(summary)
    assert summary_for_json(summary)["reason_text"].startswith("even the smallest share")


def test_a_measurement_that_is_not_finite_never_removes():
    strategy = GaroStrategy(compaction=compaction())
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    nan = torch.full((V,), math.nan)
    event = strategy.compact(params, optimizers, state, 0, lambda m: nan, lambda: torch.zeros(N))
    assert event["stop"] == "round_bound" and len(params["means"]) == N


def test_lowest_marks_exactly_count_of_the_smallest_and_refuses_counts_out_of_range():
    score = torch.tensor([3.0, 1.0, 2.0, 1.0, 5.0])
    assert lowest(score, 0).tolist() == [False] * 5
    assert lowest(score, 1).tolist() == [False, True, False, False, False]  # a tie goes to the lower index
    assert lowest(score, 3).tolist() == [False, True, True, True, False]
    assert lowest(score, 5).tolist() == [True] * 5
    for count in (-1, 6):
        with pytest.raises(ValueError, match=f"cannot mark {count} of 5 Gaussians"):
            lowest(score, count)
    assert lowest(torch.zeros(0), 0).shape == (0,)


# --- on a model: the field and the optimizers, and a resumed run's end ------------------------------------


def tiny_model(**settings):
    """A small GaroModel with the field on, three training cameras around the origin and an Adam state in
    every optimizer (the Gaussians' and the field's)."""
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.scene_box import SceneBox

    from garo_ns.garo_model import GaroModelConfig

    cfg = GaroModelConfig(**{
        "num_random": 200, "deform_width": 16, "deform_depth": 2, "deform_skip": 0, "deform_warmup": 0,
        "sh_degree": 0, "rasterizer": "reference", **settings,
    })  # fmt: skip
    model = cfg.setup(scene_box=SceneBox(torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=3, metadata={})
    model.step = 100
    c2w = torch.eye(4)[:3].repeat(3, 1, 1)
    c2w[:, :, 3] = torch.tensor([[0.0, 0.0, 3.0], [0.3, 0.0, 3.0], [-0.3, 0.0, 3.0]])
    size = dict(fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
    model.train_cameras = Cameras(camera_to_worlds=c2w, times=torch.tensor([[0.0], [0.5], [1.0]]), **size)
    model.train_times = torch.tensor([0.0, 0.5, 1.0])
    groups = model.get_param_groups()
    model.optimizers = {name: torch.optim.Adam(params, lr=1e-3) for name, params in groups.items() if params}
    g = torch.Generator().manual_seed(3)
    for name, optimizer in model.optimizers.items():
        for p in groups[name]:
            p.grad = torch.randn(p.shape, generator=g)
        optimizer.step()
        optimizer.zero_grad()
    return model


def model_copy(model) -> Dict[str, Any]:
    return {
        "params": {k: p.detach().clone() for k, p in model.named_parameters()},
        "optimizers": {k: copy.deepcopy(o.state_dict()) for k, o in model.optimizers.items()},
        "state": copy.deepcopy(model.strategy_state),
    }


def assert_model_unchanged(model, before: Dict[str, Any]) -> None:
    now = model_copy(model)
    assert now["params"].keys() == before["params"].keys()
    for k, p in before["params"].items():
        assert torch.equal(now["params"][k], p), k  # the Gaussians and the deformation field
    for name, saved in before["optimizers"].items():
        got = now["optimizers"][name]
        assert got["param_groups"] == saved["param_groups"], name
        assert got["state"].keys() == saved["state"].keys(), name
        for i, moments in saved["state"].items():
            for key, value in moments.items():
                assert torch.equal(got["state"][i][key], value), (name, i, key)
    groups = model.get_param_groups()
    for name, optimizer in model.optimizers.items():  # still bound to the model's parameters
        assert [p for g in optimizer.param_groups for p in g["params"]] == groups[name], name


def test_a_round_over_the_bound_leaves_the_gaussians_their_optimizers_and_the_field_exactly_as_before():
    model = tiny_model(compact=True, compact_start=100, compact_min_gaussians=0, compact_guard_views=3)
    from garo_ns.compaction.guard import TrainingViewGuard
    from garo_ns.compaction.training import run_round  # after the model: nerfstudio's writer is not imported first

    model.train()
    guard = TrainingViewGuard(model.train_cameras, images=[torch.zeros(16, 16, 3)] * 3, indices=[0, 1, 2])
    with torch.no_grad():
        model.eval()
        images = [guard.render(model, i) for i in range(3)]
        everything = torch.ones(model.num_points, dtype=torch.bool)
        background = guard.render(model, 0, without=everything)
        model.train()
    assert not torch.equal(images[0], background)  # the Gaussians show...
    assert torch.equal(background, model.background_color.expand(16, 16, 3))  # ...and a render without them is bare
    guard.images = [image + 0.05 for image in images]  # the truth: close to the renders, not equal
    real = guard.psnrs

    def psnrs(model, without=None):  # every Gaussian left out costs view 1 another 0.1 dB
        extra = torch.zeros(3, dtype=torch.float64)
        if without is not None:
            extra[1] = 0.1 * float(without.sum())
        return real(model, without) - extra

    guard.psnrs = psnrs
    model.compaction_guard = guard
    before = model_copy(model)
    event = run_round(model, 100, last_step=None)
    assert event["stop"] == "round_bound" and event["removed"] == 0
    assert [t["count"] for t in event["tries"]] == [30, 15, 7, 4]  # 0.15, 0.075, 0.0375, 0.02 of 200
    assert all(t["cost_worst_db"] > 0.1 for t in event["tries"])
    assert model.training and model.num_points == 200
    assert_model_unchanged(model, before)


def test_the_guard_renders_on_the_model_s_background_clamped_and_scores_against_the_composited_truth():
    """A guard view is the exact field's render (the render switches only where given), on the model's background,
    clamped to [0, 1]; its truth is the training image composited on the same background."""
    from garo_ns.compaction.guard import TrainingViewGuard, psnr
    from garo_ns.render.frame import FrameSettings

    model = tiny_model()
    grey = torch.tensor([0.25, 0.5, 0.75])
    model.background_color = grey
    model.eval()
    guard = TrainingViewGuard(model.train_cameras, images=[], indices=[0, 1, 2])
    everything = torch.ones(model.num_points, dtype=torch.bool)
    with torch.no_grad():
        assert torch.equal(guard.render(model, 0, without=everything), grey.expand(16, 16, 3))
        # Every Gaussian frozen where the static classification put it: only a render with the switches shows it.
        model.strategy_state["static"] = torch.ones(model.num_points, dtype=torch.bool)
        model.strategy_state["static_offset"] = torch.zeros(model.num_points, 10)  # position, rotation, scale
        model.deformation.layers[0].bias.fill_(5.0)  # a field that moves every Gaussian
        model.config.static_skip = True  # the model's own switches freeze them too; the guard's render does not
        frozen = guard.render(model, 1, FrameSettings(static_skip=True))
        assert not torch.equal(guard.render(model, 1), frozen)
        assert not torch.equal(guard.render(model, 1, FrameSettings(static_skip=False)), frozen)
        model.gauss_params["opacities"].fill_(10.0)
        model.gauss_params["features_dc"].fill_(10.0)  # colours far above 1
        bright = guard.render(model, 1)
        model.gauss_params["features_dc"].fill_(-10.0)  # and far below 0
        dark = guard.render(model, 1)
    assert float(bright.max()) == 1.0 and float(bright.min()) >= 0.0 and float(dark.min()) >= 0.0
    with torch.no_grad():  # the background shows through by what the Gaussians leave: 1 - alpha of it
        model.gauss_params["features_dc"].zero_()  # mid-grey Gaussians, nothing clamped
        model.gauss_params["opacities"].fill_(0.0)
        model.background_color = torch.zeros(3)
        on_black = guard.render(model, 1)
        model.background_color = torch.full((3,), 0.2)
        through = guard.render(model, 1) - on_black
        model.background_color = grey
    assert float(through.max()) <= 0.2 + 1e-6 and float(through.min()) < 0.19
    transparent = torch.cat([torch.ones(16, 16, 3), torch.zeros(16, 16, 1)], dim=-1)
    guard.images = [transparent, transparent[..., :3], transparent]
    targets = guard.targets(model)
    assert torch.equal(targets[0], grey.expand(16, 16, 3)) and torch.equal(targets[1], torch.ones(16, 16, 3))
    model.train()
    with torch.no_grad():
        scores = guard.psnrs(model)
        model.eval()
        expected = [psnr(guard.render(model, i), targets[i]) for i in range(3)]
    assert scores.dtype == torch.float64 and scores.tolist() == pytest.approx(expected)


def test_the_guard_renders_with_the_sh_degree_of_the_step():
    """Before the first SH band is on (step 50 of 1000 per band) the guard's render ignores it, as training does."""
    from garo_ns.compaction.guard import TrainingViewGuard

    model = tiny_model(sh_degree=1, sh_degree_interval=1000)
    model.step = 50
    model.eval()
    guard = TrainingViewGuard(model.train_cameras, images=[], indices=[0, 1, 2])
    with torch.no_grad():
        model.gauss_params["features_rest"].normal_(generator=torch.Generator().manual_seed(0))
        banded = guard.render(model, 0)
        model.gauss_params["features_rest"].zero_()
        assert torch.equal(guard.render(model, 0), banded)


def test_a_resumed_run_ends_and_measures_its_render_switches_at_its_real_last_step():
    """nerfstudio runs max_num_iterations steps after the loaded one: resumed at step 40 (a checkpoint of
    step 39) for 20 steps, training ends at 59, not 19; the switches' record the checkpoint brought (from
    the first part's end) is measured again there."""
    from nerfstudio.engine.callbacks import TrainingCallbackAttributes

    from garo_ns.compaction.guard import TrainingViewGuard

    model = tiny_model(compact=True, compact_start=45, compact_every=5, compact_guard_views=3)
    trainer = types.SimpleNamespace(_start_step=40, config=types.SimpleNamespace(max_num_iterations=20))
    pipeline = types.SimpleNamespace(datamanager=types.SimpleNamespace(train_dataparser_outputs=None))
    attributes = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=pipeline, trainer=trainer)
    model.get_training_callbacks(attributes)  # the last step is seen below: the switches measured at 59, not 58
    guard = TrainingViewGuard(model.train_cameras, images=[torch.rand(16, 16, 3)] * 3, indices=[0, 1, 2])
    model.compaction_guard = model.switch_guard = guard  # compaction's views and the switches' views
    from garo_ns.render.switches import MEASURE_VERSION

    # A record the current check wrote (so trusted, and valid to decide from), but of the first part's end.
    stale = {"step": 19, "views": 3, "tried": {"static_skip": 0.5}, "measure": MEASURE_VERSION}
    model.switches.record = stale
    model.step = 19
    assert model.switches.trusted_record() is stale  # as the first part left it
    model.step = 40
    assert model.switches.trusted_record() is None  # of an earlier state: no decision is taken from it
    for step in (58, 59):
        model.train()
        model.step = step
        outputs = model.get_outputs(model.train_cameras[0:1])
        outputs["rgb"].mean().backward()
        model.after_iteration(step)
        if step == 58:
            assert model.switches.record is stale
    assert model.switches.record is not stale and model.switches.record["step"] == 59
    assert model.switches.record["views"] == 3
    assert model.strategy_state["compact"]["stopped_step"] == 59  # compaction ends there too, not at 19


# --- settings and helpers ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field,value",
    [
        ("round_bound_db", -0.1),
        ("round_bound_db", float("nan")),
        ("budget_db", float("inf")),
        ("budget_db", -1.0),
        ("fraction", 0.0),
        ("min_fraction", 0.0),
        ("min_fraction", 0.5),  # above the share it halves from
        ("max_rounds", -1),
        ("fraction", 1.0),
        ("every", 0),
        ("guard_views", 0),
        ("volume_beta", float("nan")),
        ("start", -1),
    ],
)
def test_settings_out_of_range_fail_naming_the_flag(field, value):
    flag = f"--pipeline.model.compact-{field.replace('_', '-')}"
    with pytest.raises(GaroConfigError, match=f"^{flag} must be"):
        Compaction(**{field: value})
    from garo_ns.garo_model import GaroModelConfig

    with pytest.raises(GaroConfigError, match=f"^{flag} must be"):
        GaroModelConfig(**{f"compact_{field}": value})  # what the command line builds


def test_schedule_and_removal_count():
    c = Compaction(every=1000, max_rounds=2, fraction=0.15, min_gaussians=1000)
    # Round steps; how many of them remove is the summary's count (max_rounds), kept across a resume.
    assert [s for s in range(0, 19_000, 500) if c.is_round(s, 15_000)] == [15_000, 16_000, 17_000, 18_000]
    assert Compaction(start=3).first_step(15_000) == 3
    assert c.shares() == [0.15, 0.075, 0.0375, 0.02]
    assert Compaction(fraction=0.02, min_fraction=0.02).shares() == [0.02]
    assert c.removal_count(10_000, 0.02) == 200
    assert c.removal_count(10_000) == 1500
    assert c.removal_count(1100) == 100  # never below min_gaussians
    assert c.removal_count(900) == 0


def test_importance_is_weight_times_relative_volume_to_beta():
    contribution = torch.tensor([1.0, 1.0, 0.0, 2.0])
    log_scales = torch.log(torch.tensor([[1.0, 1.0, 1.0], [0.1, 0.1, 0.1], [9.0, 9.0, 9.0], [0.1, 1.0, 1.0]]))
    score = importance(contribution, log_scales, 0.5)
    volume = torch.tensor([1.0, 1e-3, 729.0, 0.1]) / 729.0
    torch.testing.assert_close(score, contribution * volume**0.5)
    assert torch.equal(importance(contribution, log_scales, 0.0), contribution)
    assert lowest(score, 2).tolist() == [False, True, True, False]
    assert lowest(torch.tensor([1.0, 0.0, 0.0]), 1).tolist() == [False, True, False]  # ties: lower index
    with pytest.raises(ValueError):
        lowest(score, 5)


def test_importance_names_a_count_mismatch_and_takes_no_gaussians_and_a_beta_of_one():
    with pytest.raises(ValueError, match="^3 contributions for 2 Gaussians$"):
        importance(torch.ones(3), torch.zeros(2, 3), 0.1)
    assert importance(torch.zeros(0), torch.zeros(0, 3), 0.1).shape == (0,)  # an empty model: no volume to scale
    contribution, log_scales = torch.tensor([1.0, 3.0]), torch.log(torch.tensor([[2.0, 2.0, 2.0], [1.0, 1.0, 1.0]]))
    torch.testing.assert_close(importance(contribution, log_scales, 1.0), torch.tensor([1.0, 3.0 / 8.0]))


def test_guard_psnr_is_garo_eval_s():
    from garo_ns.compaction.guard import psnr

    truth = torch.full((4, 4, 3), 0.5)
    assert psnr(truth - 0.1, truth) == pytest.approx(20.0, abs=1e-4)  # MSE 0.01
    assert psnr(truth + 0.1, truth) == pytest.approx(20.0, abs=1e-4)
    assert psnr(truth, truth) == pytest.approx(120.0)  # an exact render: the MSE is floored at 1e-12


def test_guard_views_of_equal_times_keep_their_order_and_one_view_is_kept():
    """A stable order: the same views in every run when times tie (a capture without times reads all 0)."""
    assert spread_indices(torch.zeros(5000), 5000, 3) == [0, 2500, 4999]
    assert spread_indices(None, 1, 1) == [0]
    assert spread_indices(None, 7, 1) == [0]


class TrainViews:
    """A training dataset as the guard reads it: cameras with times, and images by index (pixel value = index)."""

    def __init__(self, times: torch.Tensor) -> None:
        self.cameras = types.SimpleNamespace(times=times)

    def __len__(self) -> int:
        return len(self.cameras.times)

    def __getitem__(self, i: int) -> Dict[str, torch.Tensor]:
        return {"image": torch.full((2, 2, 3), float(i))}


def test_the_guard_takes_its_views_and_images_from_the_training_split():
    from garo_ns.compaction.guard import TrainingViewGuard

    dataset = TrainViews(torch.tensor([[0.9], [0.1], [0.5], [0.3]]))
    guard = TrainingViewGuard.from_datamanager(types.SimpleNamespace(train_dataset=dataset), 2)
    assert guard.cameras is dataset.cameras and guard.indices == [1, 0]  # the earliest and the latest
    assert [float(image[0, 0, 0]) for image in guard.images] == [1.0, 0.0]
    cached = [{"image": torch.full((2, 2, 3), 10.0 + i)} for i in range(4)]  # a full-image datamanager's cache
    guard = TrainingViewGuard.from_datamanager(types.SimpleNamespace(train_dataset=dataset, cached_train=cached), 2)
    assert [float(image[0, 0, 0]) for image in guard.images] == [11.0, 10.0]
    one = TrainingViewGuard.from_datamanager(types.SimpleNamespace(train_dataset=TrainViews(torch.ones(1, 1))), 5)
    assert one.indices == [0] and len(one.images) == 1
    assert TrainingViewGuard.from_datamanager(types.SimpleNamespace(), 2) is None
    assert (
        TrainingViewGuard.from_datamanager(types.SimpleNamespace(train_dataset=TrainViews(torch.ones(0, 1))), 2) is None
    )


def test_a_round_keeps_a_cost_equal_to_its_bound_and_measures_a_single_gaussian_or_view():
    from garo_ns.compaction.decision import decide

    def flat(cost_db: float, views: int = 2):
        return lambda mask: torch.full((views,), cost_db, dtype=torch.float64)

    c = Compaction(fraction=0.5, min_fraction=0.5, round_bound_db=0.1, budget_db=0.3, min_gaussians=0)
    scores = torch.tensor([3.0, 1.0])
    kept = decide(scores, 2, c, 0.0, flat(0.1))  # exactly the bound: allowed
    assert kept["mask"].tolist() == [False, True] and kept["stop"] is None and kept["detail"] is None
    assert kept["tries"] == [{"share": 0.5, "count": 1, "cost_mean_db": 0.1, "cost_worst_db": 0.1}]
    assert decide(scores, 2, c, 0.0, flat(0.0, views=1))["mask"].tolist() == [False, True]  # one guard view
    none = decide(scores, 2, c, 0.0, lambda mask: torch.zeros(0, dtype=torch.float64))  # no views: never kept
    assert none["mask"] is None and none["stop"] == "round_bound" and math.isnan(none["tries"][0]["cost_worst_db"])


def test_a_round_stopped_by_what_is_left_of_the_budget_says_so():
    """A cost within the round bound but over what the budget has left stops by the budget."""
    from garo_ns.compaction.decision import decide

    c = Compaction(fraction=0.5, min_fraction=0.5, round_bound_db=0.1, budget_db=0.3, min_gaussians=0)
    stopped = decide(torch.tensor([3.0, 1.0]), 2, c, 0.25, lambda mask: torch.full((2,), 0.1, dtype=torch.float64))
    assert stopped["mask"] is None and stopped["stop"] == "budget"
    assert stopped["detail"] == (
        "removing 1 Gaussians would cost 0.100 dB (worst view), over the 0.050 dB left of the 0.3 dB budget"
    )


def test_every_compaction_setting_at_its_edge_is_valid_and_beyond_it_names_its_range():
    edges = dict(round_bound_db=0.0, budget_db=0.0, every=1, max_rounds=0, min_gaussians=0, guard_views=1)
    Compaction(**edges, volume_beta=0.0, start=0)
    beyond = {
        "round_bound_db": (-1.0, "compact-round-bound-db must be a number of dB >= 0, got -1.0"),
        "budget_db": (-1.0, "compact-budget-db must be a number of dB >= 0, got -1.0"),
        "every": (0, "compact-every must be >= 1, got 0"),
        "max_rounds": (-1, "compact-max-rounds must be >= 0, got -1"),
        "min_gaussians": (-1, "compact-min-gaussians must be >= 0, got -1"),
        "guard_views": (0, "compact-guard-views must be >= 1, got 0"),
        "volume_beta": (-1.0, "compact-volume-beta must be a number >= 0, got -1.0"),
        "start": (-1, "compact-start must be a step >= 0 or None, got -1"),
    }
    for name, (value, message) in beyond.items():
        with pytest.raises(GaroConfigError) as err:
            Compaction(**{name: value})
        assert str(err.value) == f"--pipeline.model.{message}", name


def test_the_round_and_stop_lines_say_what_happened_in_words():
    nothing = {"round": 2, "step": 300, "share": None, "num_after": 40, "tries": []}
    assert round_line(nothing) == "compaction round 2 at step 300: nothing tried, 40 Gaussians"
    tries = [
        {"share": 0.15, "count": 6, "cost_worst_db": 0.5, "cost_mean_db": 0.25},
        {"share": 0.075, "count": 3, "cost_worst_db": 0.05, "cost_mean_db": 0.01},
    ]
    event = {"round": 1, "step": 200, "share": 0.075, "tries": tries, "removed": 3, "num_before": 40, "num_after": 37}
    assert round_line(event) == (
        "compaction round 1 at step 200: tried 0.15 (6) cost 0.500 dB worst view, 0.250 mean; "
        "0.075 (3) cost 0.050 dB worst view, 0.010 mean: removed 3 of 40, 37 left"
    )
    summary = {  # an empty model, a reason of a later version, no budget recorded
        "num_gaussians_start": 0,
        "num_gaussians_end": 0,
        "settings": {},
        "reason": "later_reason",
        "detail": "d",
        "stopped_step": 9,
    }
    assert stop_line(summary) == (
        "compaction stopped at step 9 (later_reason: later_reason; d): kept 0 of 0 Gaussians, "
        "0.000 dB of the 0 dB budget"
    )
    summary.update(num_gaussians_start=40, num_gaussians_end=30, spent_db=0.125, settings={"budget_db": 0.3})
    summary.update(reason="budget")
    assert stop_line(summary) == (
        f"compaction stopped at step 9 (budget: {REASONS['budget']}; d): kept 30 of 40 Gaussians (75%), "
        "0.125 dB of the 0.3 dB budget"
    )


def test_guard_views_spread_over_time():
    times = torch.tensor([0.9, 0.1, 0.5, 0.3, 0.7, 0.0])
    assert spread_indices(times, 6, 3) == [5, 3, 0]  # earliest, middle (position 2.5 rounds to 2), latest
    assert spread_indices(None, 10, 4) == [0, 3, 6, 9]
    assert spread_indices(times, 6, 100) == [5, 1, 3, 2, 4, 0]
    assert spread_indices(times, 0, 3) == []


# --- a short garo-compact training on the built-in scene -------------------------------------------------


class Forbidden:
    """Stands in for the eval split: any use of it fails the test (asking whether there is one, as the
    trainer does at its end, answers no)."""

    def __bool__(self):
        return False

    def __getattr__(self, name):
        raise AssertionError(f"the eval split was read ({name})")

    def __getitem__(self, index):
        raise AssertionError("the eval split was read")

    def __len__(self):
        raise AssertionError("the eval split was read")

    def __iter__(self):
        raise AssertionError("the eval split was read")


def train_compact(scene: Any, out: Any, budget: float) -> Dict[str, Any]:
    from garo_ns.tools.train import QuickSchedule, make_config, seed_everything

    config = make_config(
        "garo-compact",
        scene,
        out,
        schedule=QuickSchedule(
            steps=60, num_random=800, deform_width=16, deform_depth=2, deform_skip=0, extra={"sh_degree": 1}
        ),
        experiment_name=f"budget{budget}",
    )
    model_config = config.pipeline.model
    model_config.rasterizer = "reference"
    model_config.compact_round_bound_db = budget
    model_config.compact_budget_db = budget
    model_config.compact_fraction = 0.3
    model_config.compact_guard_views = 4
    config.set_timestamp()
    seed_everything(config.machine.seed)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    dm = trainer.pipeline.datamanager
    for name in ("eval_dataset", "cached_eval", "eval_dataparser_outputs", "dataparser"):
        setattr(dm, name, Forbidden())
    model = trainer.pipeline.model
    model.adopt_training_data(trainer.pipeline)  # the guard's views, chosen again with the eval split forbidden
    trainer.train()
    return {"trainer": trainer, "config": config, "summary": model.strategy_state["compact"]}


@pytest.fixture(scope="module")
def compact_runs(tmp_path_factory):
    from garo_ns.tools.scene import SceneSpec, generate_scene

    scene = generate_scene(tmp_path_factory.mktemp("scene"), SceneSpec(resolution=32, n_train=12, n_val=2, n_test=3))
    out = tmp_path_factory.mktemp("runs")
    return {tol: train_compact(scene, out, tol) for tol in (0.0, 50.0)} | {"scene": scene}


@pytest.mark.slow
def test_compaction_stops_by_itself_and_a_larger_budget_removes_more(compact_runs):
    strict, loose = compact_runs[0.0]["summary"], compact_runs[50.0]["summary"]
    for summary in (strict, loose):
        assert summary["reason"] is not None and summary["rounds"], summary
        assert (
            summary["num_gaussians_end"]
            == compact_runs[0.0 if summary is strict else 50.0]["trainer"].pipeline.model.num_points
        )
    # Budget 0: no kept removal lowered any guard view's PSNR, as measured before it was made.
    for event in strict["rounds"]:
        if event["removed"]:
            assert event["cost_worst_db"] <= 0.0, event
    assert strict["spent_db"] == 0.0 and 0 <= loose["spent_db"] <= 50.0
    assert loose["num_gaussians_end"] < strict["num_gaussians_end"]
    assert loose["reason"] in ("max_rounds", "min_gaussians", "training_ended"), loose


def test_the_methods_are_registered_in_pyproject():
    from pathlib import Path

    import tomllib

    from garo_ns import config

    table = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]["entry-points"]
    registered = table["nerfstudio.method_configs"]
    for name in ("garo-compact", "garo-compact-real"):
        module, attr = registered[name].split(":")
        assert module == "garo_ns.config" and getattr(config, attr) is config.METHODS[name]
        model = config.METHODS[name].config.pipeline.model
        expected = Compaction(every=model.compact_every, max_rounds=model.compact_max_rounds)
        assert model.compact and model.compaction() == expected
        assert config.METHODS[name].config.method_name == name
        # The chosen default GARO cap under compaction; garo-deform keeps the paper's.
        assert model.rho_max == config.COMPACT_RHO_MAX < config.METHODS["garo-deform"].config.pipeline.model.rho_max
    assert not config.METHODS["garo-deform"].config.pipeline.model.compact
    assert config.METHODS["garo-deform"].config.pipeline.model.rho_max == 0.02


@pytest.mark.slow
def test_compaction_summary_survives_the_checkpoint_and_reaches_garo_eval(compact_runs, tmp_path):
    from garo_ns.tools.eval import EvalArgs, load_run, run

    trained = compact_runs[50.0]
    config_path = trained["config"].get_base_dir() / "config.yml"
    _, pipeline, ckpt, _ = load_run(config_path)
    assert pipeline.model.strategy_state["compact"] == trained["summary"]
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)["pipeline"]
    extra = saved["_model._extra_state"]["strategy_state"]
    assert "compact_snapshot" not in extra and extra["compact"]["reason"] == trained["summary"]["reason"]
    result = run(EvalArgs(load_config=config_path, split="test", output_path=tmp_path / "eval.json"))
    written = json.loads((tmp_path / "eval.json").read_text())
    assert written["compaction"] == json.loads(json.dumps(summary_for_json(trained["summary"])))
    assert written["compaction"]["reason_text"] and result["num_gaussians"] == trained["summary"]["num_gaussians_end"]


def test_benchmark_variants_of_compaction(tmp_path):
    from garo_ns.bench.benchmark import split_variant, variant_settings

    assert variant_settings("garo-compact") == ("garo-compact", {})
    assert variant_settings("garo-compact0.5") == ("garo-compact", {"compact_budget_db": 0.5})
    assert split_variant("garo-compact+fp16")[0] == "garo-compact"
    # Any compaction settings, so that one run can train several of them side by side.
    name = "garo-compact--fraction-0.3--round_bound_db-0.05--max_rounds-4--start-12000"
    method, overrides = variant_settings(name)
    assert method == "garo-compact"
    assert overrides == {
        "compact_fraction": 0.3,
        "compact_round_bound_db": 0.05,
        "compact_max_rounds": 4,
        "compact_start": 12000,
    }
    assert isinstance(overrides["compact_max_rounds"], int) and split_variant(name + "+auto")[0] == name
    # GARO's cap too: a gentler GARO leaves more to compaction's measured removals.
    assert variant_settings("garo-compact--rho_max-0.01--round_bound_db-0.3") == (
        "garo-compact",
        {"rho_max": 0.01, "compact_round_bound_db": 0.3},
    )
    with pytest.raises(ValueError, match="unknown compaction setting 'share'.*fraction.*GARO's \\['rho_max'\\]"):
        variant_settings("garo-compact--share-0.3")
    with pytest.raises(ValueError, match="'max_rounds' .* needs an integer, got '4.5'"):
        variant_settings("garo-compact--max_rounds-4.5")
    with pytest.raises(ValueError, match="'fraction' .* needs a number"):
        variant_settings("garo-compact--fraction-")
    # A setting out of range, an unknown variant or switch is refused before any run starts.
    from garo_ns.bench.benchmark import BenchArgs, check_variant, run
    from garo_ns.errors import GaroConfigError

    check_variant(name + "+auto")
    with pytest.raises(GaroConfigError, match="compact-fraction must be in"):
        check_variant("garo-compact--fraction-1.5")
    with pytest.raises(GaroConfigError, match="rho-max must be in \\[0, 1\\], got 1.5"):
        check_variant("garo-compact--rho_max-1.5")
    with pytest.raises(GaroConfigError, match="rho-max must be in"):
        check_variant("garo-rho2")
    with pytest.raises(ValueError, match="unknown render switch"):
        check_variant("garo-deform+tf32")
    args = BenchArgs(scene=tmp_path / "none", work_dir=tmp_path / "runs", variants=["garo-compact--fraction-1.5"])
    with pytest.raises(GaroConfigError):
        run(args)
    assert not (tmp_path / "runs").exists()  # refused before anything was made


def test_summary_edges_the_round_limits_and_the_default_start():
    """The stop details of the round and size limits at their boundaries, the running size after a kept
    round, an old summary without a budget record, and rounds that start where densification stops."""

    def never(*_):
        raise AssertionError("measured")

    params, optimizers, g = gaussians()
    no_rounds = GaroStrategy(compaction=compaction(max_rounds=0))
    state = filled_state(no_rounds, N, g)
    no_rounds.compact(params, optimizers, state, 0, never, never)
    assert state["compact"]["detail"] == "0 rounds"
    at_floor = GaroStrategy(compaction=compaction(min_gaussians=N))  # exactly at the floor: nothing to take
    state = filled_state(at_floor, N, g)
    assert at_floor.compact(params, optimizers, state, 0, never, never)["stop"] == "min_gaussians"

    strategy = GaroStrategy(compaction=compaction(fraction=0.1))
    state = filled_state(strategy, N, g)
    del state["compact"]["spent_db"]  # a summary written before the budget existed
    scene = Scene(worth(N, N, 0.0), params)
    event = strategy.compact(params, optimizers, state, 0, removal_cost(None, scene), scene.importance)
    assert event["removed"] == 10 and "stop" not in event
    assert state["compact"]["spent_db"] == 0.0 and state["compact"]["num_gaussians_end"] == 90

    params, optimizers, g = gaussians()
    late = GaroStrategy(refine_stop_iter=200, compaction=Compaction(every=10, min_gaussians=0))  # start: None
    state = filled_state(late, N, g)
    scene = Scene(worth(N, N, 0.0), params)
    cost = removal_cost(None, scene)
    assert late.compact(params, optimizers, state, 190, cost, scene.importance) is None
    assert late.compact(params, optimizers, state, 200, cost, scene.importance)["removed"] > 0
    unstarted = GaroStrategy(refine_stop_iter=200, compaction=Compaction(every=10))
    state = filled_state(unstarted, N, g)
    unstarted.compact(params, optimizers, state, 150, never, never, last_step=150)
    assert state["compact"]["detail"] == "before the first round (step 200)"


@pytest.mark.parametrize("method", ["garo-compact", "garo-compact-real"])
def test_the_presets_comments_name_the_steps_their_rounds_remove_at(method):
    """garo_ns/config.py says, above each preset, at which steps its rounds run and how long the model
    trains after the last: the preset's own strategy, driven over every step of its schedule with removals
    that cost nothing, removes at exactly those steps."""
    import inspect
    import re

    import garo_ns.config as presets

    config = presets.METHODS[method].config
    strategy = config.pipeline.model.make_strategy()
    strategy.compaction.min_gaussians = 0
    n = 5000
    params, optimizers, g = gaussians(n)
    state = filled_state(strategy, n, g)
    scene = Scene(torch.zeros(n, V, dtype=torch.float64), params)
    last = config.max_num_iterations - 1
    events = run_rounds(strategy, params, optimizers, state, scene, range(config.max_num_iterations), last)
    removing = [e["step"] for e in events if e["removed"]]
    assert state["compact"]["reason"] == "max_rounds"  # every round removed: the schedule alone ended it
    name = method.replace("-", "_")
    source = inspect.getsource(presets)
    comment = source[: source.index(f"\n{name} = MethodSpecification(")].splitlines()[-1]
    match = re.match(r"# (\d+)k steps: rounds at ([\d.]+)k, ([\d.]+)k, \.\.\., ([\d.]+)k at the latest", comment)
    assert match, comment
    steps, first, second, latest = (round(float(x) * 1000) for x in match.groups())
    assert (steps, first, second, latest) == (config.max_num_iterations, *removing[:2], removing[-1]), comment
    after = re.search(r"then ([\d.]+)k steps of training", comment)
    if after:
        assert round(float(after.group(1)) * 1000) == config.max_num_iterations - removing[-1], comment
