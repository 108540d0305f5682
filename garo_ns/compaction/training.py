"""Compaction inside nerfstudio's training loop: the round of a step (and the fixed-ratio expert knob), run on
the model and logged."""

from __future__ import annotations

from typing import Any, Dict, Optional

from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from garo_ns.compaction.guard import removal_cost
from garo_ns.compaction.importance import importance
from garo_ns.compaction.report import round_line, scalars, stop_line


def run_round(model: Any, step: int, last_step: Optional[int]) -> Optional[Dict[str, Any]]:
    """The compaction round of `step`, if any, on a training GaroModel: the strategy decides and removes,
    the model's guard measures (`model.compaction_guard`, None without training data), the model's
    blending weights over the training views rank. Logs the round; returns its record."""
    strategy = model.strategy
    if strategy.compaction is None:
        return None
    guard = model.compaction_guard

    def score() -> Tensor:
        was_training = model.training
        model.eval()  # the Gaussians as the guard measures them (no time noise)
        try:
            return importance(model.contribution(model.train_cameras), model.scales, strategy.compaction.volume_beta)
        finally:
            model.train(was_training)

    event = strategy.compact(
        model.gauss_params,
        model.optimizers,
        model.strategy_state,
        step,
        removal_cost(model, guard) if guard is not None else None,
        score,
        last_step,
    )
    if event is None:
        return None
    for name, value in scalars(event, model.strategy_state["compact"]["spent_db"]).items():
        writer.put_scalar(name=name, scalar=value, step=step)
    CONSOLE.print(round_line(event))
    if "stop" in event:
        CONSOLE.print(stop_line(model.strategy_state["compact"]))
    return event


def fixed_ratio_round(model: Any, step: int) -> Optional[int]:
    """The expert knob `prune_contribution_ratio`: at its steps, the strategy removes that fixed share of
    the Gaussians with the least blending weight over the training views. Returns how many it removed."""
    cfg = model.config
    ratio = cfg.prune_contribution_ratio
    if ratio <= 0 or step not in cfg.prune_contribution_steps or model.train_cameras is None:
        return None
    contribution = model.contribution(model.train_cameras)
    n = model.strategy.prune_by_contribution(
        model.gauss_params, model.optimizers, model.strategy_state, contribution, ratio
    )
    CONSOLE.print(f"step {step}: pruned {n} least contributing Gaussians, {model.num_points} left")
    return n
