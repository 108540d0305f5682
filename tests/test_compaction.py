"""Compaction after densification: the exact undo, the rounds' stopping rule, bad settings, and a short
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
from garo_ns.compaction.guard import spread_indices
from garo_ns.compaction.report import round_line, stop_line, summary_for_json
from garo_ns.errors import GaroConfigError
from garo_ns.garo_strategy import GaroStrategy, _copy
from garo_ns.redundancy.select import lowest

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
        elif k not in ("compact", "compact_snapshot"):
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


# --- snapshot and restore ---------------------------------------------------------------------------


def test_restore_puts_back_params_adam_and_state_rows_exactly_and_training_goes_on_alike():
    strategy = GaroStrategy(compaction=Compaction(start=0))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    before = copy_of(params, optimizers, state)
    twin_params, twin_opt, _ = gaussians()  # the same Gaussians and moments, never touched below
    saved = strategy.snapshot(params, optimizers, state)
    mask = torch.zeros(N, dtype=torch.bool)
    mask[::3] = True
    from gsplat.strategy.ops import remove

    remove(params=params, optimizers=optimizers, state=state, mask=mask)
    adam_step(params, optimizers, seed=9)  # training after the removal changes what is left
    assert len(params["means"]) == N - 34
    strategy.restore(params, optimizers, state, saved)
    assert_same(params, optimizers, state, before)
    assert state["static_step"] == 7
    # The restored Gaussians train exactly as the untouched twin: moments and step counts came back.
    adam_step(params, optimizers)
    adam_step(twin_params, twin_opt)
    for k in params:
        assert torch.equal(params[k].detach(), twin_params[k].detach()), k
    # The snapshot holds copies: training the restored parameters did not change it.
    assert torch.equal(saved["params"]["means"], before[0]["means"])


def test_restore_rebinds_an_optimizer_that_had_no_state_yet():
    strategy = GaroStrategy()
    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(4, 3))})
    optimizers = {"means": torch.optim.Adam([params["means"]], lr=0.1)}
    state = strategy.initialize_state()
    saved = strategy.snapshot(params, optimizers, state)
    params["means"] = torch.nn.Parameter(torch.ones(2, 3))
    strategy.restore(params, optimizers, state, saved)
    assert optimizers["means"].param_groups[0]["params"][0] is params["means"]
    assert torch.equal(params["means"].detach(), torch.zeros(4, 3))
    params["means"].grad = torch.ones(4, 3)
    optimizers["means"].step()
    assert torch.allclose(params["means"].detach(), torch.full((4, 3), -0.1))


# --- the rounds ----------------------------------------------------------------------------------------


class Scene:
    """A model whose training-view PSNR is 30 dB less the summed value of the Gaussians it lost (by row id);
    `drift` lowers every later measurement (fine-tuning that does not recover)."""

    def __init__(self, value: torch.Tensor):
        self.value = value
        self.drift = 0.0
        self.measured = 0

    def measure(self, params) -> float:
        self.measured += 1
        lost = torch.ones(len(self.value), dtype=torch.bool)
        lost[params["opacities"].detach().long()] = False
        return 30.0 - float(self.value[lost].sum()) - self.drift

    def importance(self, params) -> torch.Tensor:
        return self.value[params["opacities"].detach().long()]


def run_rounds(strategy, params, optimizers, state, scene, steps, last_step=None, between=None):
    events = []
    for step in steps:
        event = strategy.compact(
            params,
            optimizers,
            state,
            step,
            lambda: scene.measure(params),
            lambda: scene.importance(params),
            last_step,
        )
        if event is not None:
            events.append(event)
            if "stop" in event:
                break
        if between is not None:
            between(step)
    return events


def value_40_percent_free(n: int = N) -> torch.Tensor:
    """The first 40 Gaussians are worth nothing (the lowest scores), the rest 0.02 dB each."""
    value = torch.full((n,), 0.02, dtype=torch.float64)
    value[:40] = 0.0
    return value


def test_tolerance_zero_removes_only_what_costs_nothing_and_undoes_the_round_that_costs():
    strategy = GaroStrategy(compaction=Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.0, min_gaussians=0))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(value_40_percent_free())
    copies = {}

    def keep_copy(step):
        copies[step] = copy_of(params, optimizers, state)

    keep_copy(-1)
    events = run_rounds(strategy, params, optimizers, state, scene, range(20), between=keep_copy)
    # 100 -> 80 -> 64 (free Gaussians only); the third round would take 12 with only 4 free left: undone.
    assert [e["removed"] for e in events] == [20, 16, 12]
    assert events[-1]["stop"] == "tolerance" and events[-1]["restored"] == 12
    assert len(params["means"]) == 64
    assert set(range(36, 100)) == set(ids(params))  # every lost Gaussian was worth nothing
    assert_same(params, optimizers, state, copies[1])  # exactly as before the undone round
    summary = state["compact"]
    assert summary["reason"] == "tolerance" and summary["num_gaussians_end"] == 64
    assert summary["reference_psnr"] == summary["final_psnr"] == 30.0
    assert state["compact_snapshot"] is None  # the undo copy is freed
    assert "put back" in round_line(events[-1], 0.0)
    line = stop_line(summary)
    assert "tolerance" in line and "kept 64 of 100" in line and "undone" in line
    # Stopped for good: later steps do nothing.
    assert strategy.compact(params, optimizers, state, 30, lambda: 0.0, lambda: torch.zeros(64)) is None


def test_a_larger_tolerance_removes_more_and_says_it_stopped_at_the_round_limit():
    ends = {}
    for tol in (0.0, 0.25, 100.0):
        compaction = Compaction(start=0, every=1, fraction=0.2, tolerance_db=tol, max_rounds=5, min_gaussians=0)
        strategy = GaroStrategy(compaction=compaction)
        params, optimizers, g = gaussians()
        state = filled_state(strategy, N, g)
        run_rounds(strategy, params, optimizers, state, Scene(value_40_percent_free()), range(20))
        ends[tol] = (len(params["means"]), state["compact"]["reason"], state["compact"]["final_psnr"])
    assert ends[0.0] == (64, "tolerance", 30.0)
    # 0.25 dB: the third round's 8 Gaussians (0.16 dB) stay; the fourth round's 10 cost 0.20 dB at once (within
    # the tolerance) but 0.36 dB in all, which the next round finds and undoes.
    assert ends[0.25][:2] == (52, "tolerance") and math.isclose(ends[0.25][2], 29.84, abs_tol=1e-5)
    assert ends[100.0][:2] == (34, "max_rounds")  # 100, 80, 64, 52, 42, 34


def test_a_removal_that_does_not_recover_in_fine_tuning_is_undone_at_the_next_round():
    compaction = Compaction(start=10, every=5, fraction=0.2, tolerance_db=0.5, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))  # every removal is free at once...
    copies = {}

    def train(step):
        adam_step(params, optimizers, seed=step)
        copies[step] = copy_of(params, optimizers, state)  # as the next step starts
        if step == 15:  # ...but after the second removal the training-view PSNR falls by 0.6 dB
            scene.drift = 0.6

    events = run_rounds(strategy, params, optimizers, state, scene, range(10, 40), between=train)
    assert [(e["step"], e["removed"]) for e in events[:2]] == [(10, 20), (15, 16)]
    last = events[-1]
    assert last["step"] == 20 and last["stop"] == "tolerance" and last["restored"] == 16
    assert_same(params, optimizers, state, copies[14])  # as before round 15's removal
    assert "below the best" in state["compact"]["detail"]


def test_the_last_training_step_checks_the_pending_removal():
    for drift, reason, n in ((0.0, "training_ended", 80), (1.0, "tolerance", 100)):
        compaction = Compaction(start=0, every=100, tolerance_db=0.5, fraction=0.2, min_gaussians=0)
        strategy = GaroStrategy(compaction=compaction)
        params, optimizers, g = gaussians()
        state = filled_state(strategy, N, g)
        scene = Scene(torch.zeros(N))
        events = run_rounds(
            strategy, params, optimizers, state, scene, range(50), last_step=49,
            between=lambda s: setattr(scene, "drift", drift) if s == 0 else None,
        )  # fmt: skip
        assert [e["step"] for e in events] == [0, 49]
        assert state["compact"]["reason"] == reason and len(params["means"]) == n


def test_stops_without_measuring_on_an_empty_model_without_views_or_before_its_start():
    def never():
        raise AssertionError("measured")

    strategy = GaroStrategy(compaction=Compaction(start=0))
    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(0, 3))})
    optimizers = {"means": torch.optim.Adam([params["means"]])}
    state = strategy.initialize_state()
    event = strategy.compact(params, optimizers, state, 0, never, never)
    assert event["stop"] == "empty_model" and state["compact"]["reason"] == "empty_model"
    assert "no Gaussians" in stop_line(state["compact"])

    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    assert strategy.compact(params, optimizers, state, 0, None, never)["stop"] == "no_training_views"

    late = GaroStrategy(compaction=Compaction(start=500))
    state = filled_state(late, N, g)
    assert late.compact(params, optimizers, state, 100, never, never, last_step=200) is None
    assert late.compact(params, optimizers, state, 200, never, never, last_step=200)["stop"] == "training_ended"
    assert "before the first round (step 500)" in state["compact"]["detail"]
    assert len(params["means"]) == N


def test_a_tiny_model_is_left_as_it_is():
    strategy = GaroStrategy(compaction=Compaction(start=0, min_gaussians=1000))
    params, optimizers, g = gaussians(20)
    state = filled_state(strategy, 20, g)
    before = copy_of(params, optimizers, state)
    scene = Scene(torch.zeros(20))
    event = strategy.compact(params, optimizers, state, 0, lambda: scene.measure(params), lambda: torch.zeros(20))
    assert event["stop"] == "min_gaussians" and event["removed"] == 0
    assert_same(params, optimizers, state, before)
    # A round whose share rounds down to no Gaussian stops too.
    strategy = GaroStrategy(compaction=Compaction(start=0, fraction=0.04, min_gaussians=0))
    state = filled_state(strategy, 20, g)
    event = strategy.compact(params, optimizers, state, 0, lambda: scene.measure(params), lambda: torch.zeros(20))
    assert event["stop"] == "nothing_to_remove" and len(params["means"]) == 20


def test_a_strategy_without_compaction_has_no_compaction_state_and_does_nothing():
    strategy = GaroStrategy()
    state = strategy.initialize_state()
    assert "compact" not in state and "compact_snapshot" not in state
    params, optimizers, _ = gaussians()
    assert strategy.compact(params, optimizers, state, 0, lambda: 1.0, lambda: torch.zeros(N)) is None


def approx_record(record: Dict[str, Any]) -> Dict[str, Any]:
    """A record with its floats compared to 1e-9 (the scene's PSNRs are sums of float64 values)."""
    return {k: pytest.approx(v, abs=1e-9) if isinstance(v, float) else v for k, v in record.items()}


def test_every_round_record_and_the_summary_say_what_happened():
    """The full record of a run that removes twice and undoes its third removal: every key of every
    round and of the summary (the log, the checkpoint's metadata and garo-eval's JSON read them)."""
    compaction = Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.0, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    events = run_rounds(strategy, params, optimizers, state, Scene(value_40_percent_free()), range(20))
    common = {"restored": 0, "psnr_before": 30.0, "psnr_after": 30.0}
    expected = [
        {"round": 0, "step": 0, "num_before": 100, "removed": 20, "num_after": 80, **common},
        {"round": 1, "step": 1, "num_before": 80, "removed": 16, "num_after": 64, **common},
        {"round": 2, "step": 2, "num_before": 64, "removed": 12, "restored": 12, "num_after": 64,
         "psnr_before": 30.0, "psnr_after": 30.0 - 8 * 0.02, "stop": "tolerance"},
    ]  # fmt: skip
    assert events == [approx_record(e) for e in expected]
    summary = state["compact"]
    assert summary["rounds"] == events
    assert {k: v for k, v in summary.items() if k not in ("rounds", "settings")} == {
        "reference_psnr": 30.0,
        "best_psnr": 30.0,
        "final_psnr": 30.0,
        "num_gaussians_start": 100,
        "num_gaussians_end": 64,
        "stopped_step": 2,
        "reason": "tolerance",
        "detail": "removing 12 Gaussians cost 0.16 dB; undone",
    }
    assert summary["settings"]["fraction"] == 0.2 and summary["settings"]["tolerance_db"] == 0.0


def test_the_best_psnr_follows_fine_tuning_that_gains():
    """A round measured above every earlier one raises the bar that later rounds are held to."""
    compaction = Compaction(start=0, every=1, fraction=0.1, tolerance_db=0.05, max_rounds=2, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))
    events = run_rounds(
        strategy, params, optimizers, state, scene, range(5),
        between=lambda step: setattr(scene, "drift", -0.3 * (step + 1)),
    )  # fmt: skip
    assert [e["psnr_before"] for e in events] == pytest.approx([30.0, 30.3, 30.6])
    summary = state["compact"]
    assert summary["reference_psnr"] == 30.0 and summary["best_psnr"] == pytest.approx(30.6)
    assert summary["reason"] == "max_rounds" and summary["detail"] == "2 rounds"
    assert summary["final_psnr"] == pytest.approx(30.6) and summary["stopped_step"] == 2
    assert events[-1]["num_after"] == summary["num_gaussians_end"] == 81 == len(params["means"])


def test_a_removal_undone_at_the_next_round_records_what_came_back_and_the_psnr_after():
    compaction = Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.5, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))
    events = run_rounds(
        strategy, params, optimizers, state, scene, range(5),
        between=lambda step: setattr(scene, "drift", 0.6) if step == 0 else None,
    )  # fmt: skip
    assert len(events) == 2 and len(params["means"]) == N
    assert events[1] == approx_record(
        {"round": 1, "step": 1, "num_before": 80, "removed": 0, "restored": 20, "num_after": 100,
         "psnr_before": 29.4, "psnr_after": 29.4, "stop": "tolerance"}
    )  # fmt: skip
    summary = state["compact"]
    assert summary["detail"] == (
        "PSNR 29.40 dB after fine-tuning, 0.60 dB below the best 30.00 dB; the last removal is undone"
    )
    assert summary["final_psnr"] == pytest.approx(29.4) and summary["num_gaussians_end"] == N
    assert summary["stopped_step"] == 1 and state["compact_snapshot"] is None


def test_a_resumed_run_without_its_undo_copy_stops_and_keeps_the_gaussians_it_has():
    """A checkpoint does not keep the undo copy: a loss found after resuming stops the compaction
    with the Gaussians as they are, and says so."""
    compaction = Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.5, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))

    def resume(step):
        state["compact_snapshot"] = None  # as loaded from a checkpoint
        scene.drift = 0.6

    events = run_rounds(strategy, params, optimizers, state, scene, range(5), between=resume)
    assert [e.get("stop") for e in events] == [None, "tolerance"]
    assert events[1]["restored"] == 0 and events[1]["num_after"] == 80 == len(params["means"])
    assert events[1]["psnr_after"] is None
    summary = state["compact"]
    assert summary["detail"] == (
        "PSNR 29.40 dB after fine-tuning, 0.60 dB below the best 30.00 dB; no copy to undo the last removal with"
    )
    assert summary["final_psnr"] == 30.0  # the last round's, before the loss was found
    assert summary["num_gaussians_end"] == 80 and summary["stopped_step"] == 1


@pytest.mark.parametrize("n,min_gaussians,reason,detail", [
    (20, 20, "min_gaussians", "20 <= 20"),
    (20, 0, "nothing_to_remove", "0.04 x 20 Gaussians"),
    (21, 20, "nothing_to_remove", "0.04 x 21 Gaussians"),
])  # fmt: skip
def test_stop_details_of_a_model_too_small_to_cut(n, min_gaussians, reason, detail):
    strategy = GaroStrategy(compaction=Compaction(start=0, fraction=0.04, min_gaussians=min_gaussians))
    params, optimizers, g = gaussians(n)
    state = filled_state(strategy, n, g)
    scene = Scene(torch.zeros(n))
    event = strategy.compact(params, optimizers, state, 0, lambda: scene.measure(params), lambda: torch.zeros(n))
    assert event["stop"] == reason and state["compact"]["detail"] == detail
    assert state["compact"]["final_psnr"] == 30.0 and state["compact"]["num_gaussians_end"] == n


def test_stop_details_without_gaussians_without_views_and_at_the_last_step():
    strategy = GaroStrategy(compaction=Compaction(start=0, every=10, fraction=0.2, min_gaussians=0))
    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(torch.zeros(0, 3))})
    state = strategy.initialize_state()
    strategy.compact(params, {}, state, 0, lambda: 0.0, lambda: torch.zeros(0))
    assert state["compact"]["detail"] == "nothing to compact" and state["compact"]["num_gaussians_end"] == 0

    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    strategy.compact(params, optimizers, state, 0, None, lambda: torch.zeros(N))
    assert state["compact"]["detail"] == "the model was given no training data"
    assert state["compact"]["final_psnr"] is None and state["compact"]["stopped_step"] == 0

    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))
    events = run_rounds(strategy, params, optimizers, state, scene, range(20), last_step=15)
    assert [(e["step"], e.get("stop")) for e in events] == [(0, None), (10, None), (15, "training_ended")]
    summary = state["compact"]
    assert summary["detail"] == "at step 15" and summary["final_psnr"] == 30.0
    assert summary["stopped_step"] == 15 and summary["num_gaussians_end"] == 64 == len(params["means"])
    assert summary["rounds"][-1] is events[-1] and events[-1]["num_after"] == 64


def test_rounds_start_where_densification_stops_unless_told_otherwise():
    strategy = GaroStrategy(refine_stop_iter=50, compaction=Compaction(every=10, fraction=0.2, min_gaussians=0))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))
    events = run_rounds(strategy, params, optimizers, state, scene, range(75))
    assert [e["step"] for e in events] == [50, 60, 70]
    state = filled_state(strategy, N, g)
    assert strategy.compact(params, optimizers, state, 40, None, None, last_step=40)["stop"] == "training_ended"
    assert state["compact"]["detail"] == "before the first round (step 50)"


def test_the_summary_after_each_kept_round_and_the_psnr_a_stop_reports():
    """The summary is current after every kept round (a run stopped by the user keeps it), and a stop
    reports the PSNR measured at that round, not the last kept round's."""
    compaction = Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.0, min_gaussians=0)
    strategy = GaroStrategy(compaction=compaction)
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(value_40_percent_free())
    seen = []

    def fine_tune(step):
        summary = state["compact"]
        seen.append((summary["num_gaussians_end"], summary["final_psnr"], summary["reason"]))
        scene.drift = -0.2 * (step + 1)  # fine-tuning gains 0.2 dB a round

    run_rounds(strategy, params, optimizers, state, scene, range(10), between=fine_tune)
    assert seen == [(80, 30.0, None), (64, pytest.approx(30.2), None)]
    summary = state["compact"]  # round 2 measures 30.4 dB, and its removal (8 costly Gaussians) is undone
    assert summary["reason"] == "tolerance" and summary["final_psnr"] == pytest.approx(30.4)
    assert summary["detail"] == "removing 12 Gaussians cost 0.16 dB; undone"

    strategy = GaroStrategy(compaction=Compaction(start=0, every=10, fraction=0.2, min_gaussians=0))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    scene = Scene(torch.zeros(N))
    run_rounds(
        strategy, params, optimizers, state, scene, range(20), last_step=15,
        between=lambda step: setattr(scene, "drift", -0.1) if step == 12 else None,
    )  # fmt: skip
    assert state["compact"]["reason"] == "training_ended" and state["compact"]["final_psnr"] == pytest.approx(30.1)


def test_a_stopped_compaction_and_a_state_without_its_summary_do_nothing():
    def never():
        raise AssertionError("measured")

    strategy = GaroStrategy(compaction=Compaction(start=0, every=1, fraction=0.2, tolerance_db=0.0, min_gaussians=0))
    params, optimizers, g = gaussians()
    state = filled_state(strategy, N, g)
    events = run_rounds(strategy, params, optimizers, state, Scene(value_40_percent_free()), range(20))
    assert events[-1]["step"] == 2 and state["compact"]["reason"] == "tolerance"
    assert strategy.compact(params, optimizers, state, 3, never, never) is None  # step 3 is a round step
    assert len(state["compact"]["rounds"]) == 3
    # A state written without compaction (an older checkpoint's): nothing runs, nothing is added.
    plain = GaroStrategy().initialize_state()
    assert strategy.compact(params, optimizers, plain, 0, never, never) is None and "compact" not in plain


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


def test_copies_share_no_storage_and_keep_their_containers():
    inner = torch.arange(3.0)
    value = {"a": [inner, (inner, 2)], "b": {"c": inner}, "d": {"e": [1, 2]}}
    copied = _copy(value)
    assert type(copied["a"]) is list and type(copied["a"][1]) is tuple and copied["a"][1][1] == 2
    inner.add_(10)
    value["d"]["e"].append(3)
    assert copied["a"][0].tolist() == copied["a"][1][0].tolist() == copied["b"]["c"].tolist() == [0.0, 1.0, 2.0]
    assert copied["d"]["e"] == [1, 2]
    odd = [[1, [2]]]
    deep = _copy(odd)
    odd[0][1].append(3)
    assert deep == [[1, [2]]]
    holder = types.SimpleNamespace(items=[1])  # neither a tensor nor a container: copied deeply
    kept = _copy({"holder": holder})["holder"]
    holder.items.append(2)
    assert kept.items == [1]


# --- settings and helpers ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field,value",
    [
        ("tolerance_db", -0.1),
        ("tolerance_db", float("nan")),
        ("tolerance_db", float("inf")),
        ("fraction", 0.0),
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
    assert [s for s in range(0, 40_000, 500) if c.is_round(s, 15_000)] == [15_000, 16_000, 17_000]
    assert Compaction(start=3).first_step(15_000) == 3
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


def train_compact(scene: Any, out: Any, tolerance: float) -> Dict[str, Any]:
    from garo_ns.tools.train import QuickSchedule, make_config, seed_everything

    config = make_config(
        "garo-compact",
        scene,
        out,
        schedule=QuickSchedule(
            steps=60, num_random=800, deform_width=16, deform_depth=2, deform_skip=0, extra={"sh_degree": 1}
        ),
        experiment_name=f"tol{tolerance}",
    )
    model_config = config.pipeline.model
    model_config.rasterizer = "reference"
    model_config.compact_tolerance_db = tolerance
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
def test_compaction_stops_by_itself_and_a_larger_tolerance_removes_more(compact_runs):
    strict, loose = compact_runs[0.0]["summary"], compact_runs[50.0]["summary"]
    for summary in (strict, loose):
        assert summary["reason"] is not None and summary["rounds"], summary
        assert (
            summary["num_gaussians_end"]
            == compact_runs[0.0 if summary is strict else 50.0]["trainer"].pipeline.model.num_points
        )
    # Tolerance 0: no kept removal lowered the training-view PSNR.
    for event in strict["rounds"]:
        if event["removed"] > event["restored"]:
            assert event["psnr_after"] >= event["psnr_before"], event
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
    assert not config.METHODS["garo-deform"].config.pipeline.model.compact


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


def test_benchmark_variants_of_compaction():
    from garo_ns.bench.benchmark import split_variant, variant_settings

    assert variant_settings("garo-compact") == ("garo-compact", {})
    assert variant_settings("garo-compact0.5") == ("garo-compact", {"compact_tolerance_db": 0.5})
    assert split_variant("garo-compact+fp16")[0] == "garo-compact"
