"""The model's training callbacks: what nerfstudio's loop calls around each step besides the forward and backward.

Before a step the model records the step and the optimizers (`GaroModel.step_cb`). After it, the model runs its
strategy (densification, GARO, contribution pruning, compaction) and then `after_strategy`: the static
classification when due, the deformation field's health check, and at the last step the render switches'
measurement on training views. `training_callbacks` also sets up, once, what the loop's steps share: the trainer's
last step and logging interval, the grouped (and graphed) Adam, one device camera per view.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, List, Optional

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from garo_ns.compaction.schedule import last_training_step
from garo_ns.deformation import collapse_warning, health_check, health_due
from garo_ns.engine.adam import AdamGraph, install_grouped_step
from garo_ns.engine.allocator import extend_segments_in_place
from garo_ns.engine.training_data import reuse_step_cameras
from garo_ns.render import table_cache
from garo_ns.render.static import classification_due, classify, sample_times


def training_callbacks(model: Any, attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
    """`model`'s callbacks for nerfstudio's loop (before each step, after each step, after training), with what
    the steps share set up first."""
    model.training_run = True
    if model.config.expandable_segments:  # before densification grows anything (garo_ns.engine.allocator)
        extend_segments_in_place(model.device)
    model.adopt_training_data(attributes.pipeline)
    trainer = attributes.trainer
    if trainer is not None:  # the checkpoint is loaded by now: a resumed run starts after its step
        model.last_step = last_training_step(getattr(trainer, "_start_step", 0), trainer.config.max_num_iterations)
        # The checkpoint the run ends with: its time table is written beside it (garo_ns.render.table_cache).
        folder = getattr(trainer, "checkpoint_dir", None)
        name = f"step-{model.last_step:09d}.ckpt"  # nerfstudio's name for a step's checkpoint
        model.final_checkpoint = None if folder is None else Path(folder) / name
        logging = getattr(trainer.config, "logging", None)  # a trainer of nerfstudio's has one; stand-ins may not
        model.metrics_every = max(int(getattr(logging, "steps_per_log", 1)), 1)
    if attributes.optimizers is not None:
        # Replayed once the parameters settle: for longer than densification's interval, as a graph captured on
        # the 100th step after a refinement would be dropped by the next one (144 such in a 40k run).
        settle = max(100, model.config.refine_every + 1)
        graph = AdamGraph(stable_steps=settle) if model.config.adam_cuda_graph else None
        install_grouped_step(attributes.optimizers, graph)  # CUDA runs: all groups' Adam updates at once
    if getattr(attributes.pipeline, "datamanager", None) is not None:
        reuse_step_cameras(attributes.pipeline.datamanager)  # one device camera per view, not one per step
    before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
    return [
        TrainingCallback([before], model.step_cb, args=[attributes.optimizers]),
        TrainingCallback([after], model.after_iteration),
        TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], lambda step: model.collector.stop()),
    ]


def after_strategy(model: Any, step: int) -> None:
    """After the strategy's work at `step`: the static classification when due, the field's health check, and at
    the run's last step the render switches' measurement on training views."""
    cfg = model.config
    if model.deformation_active() and classification_due(step, cfg.deform_warmup, cfg.static_every, model.last_step):
        refresh_static(model)
        fraction = model.static_fraction()
        if fraction is not None:
            writer.put_scalar("garo/static_fraction", fraction, step)
    check_health(model, step)
    if step == model.last_step and model.switch_guard is not None and model.deformation_active():
        CONSOLE.print(model.switches.measure_on_training_views(model, model.switch_guard, step))
        checkpoint = getattr(model, "final_checkpoint", None)
        said = table_cache.keep_trained_table(model, checkpoint) if checkpoint is not None else None
        if said:
            CONSOLE.print(said)


def check_health(model: Any, step: int) -> None:
    """Every `health_every` steps after the warm-up, measure whether the deformation field still models motion;
    warn once when it has collapsed (no later step can undo it)."""
    cfg = model.config
    if model.num_points == 0 or not health_due(step, cfg.deform_warmup, cfg.health_every):
        return
    health = health_check(model.deformation, model.means, sample_times(model.train_times, 8), model.scene_extent, step)
    model.health_log.append(health)
    writer.put_scalar("garo/deform_time_sensitivity", health["time_sensitivity"], step)
    writer.put_scalar("garo/deform_dead_fraction_max", max(health["dead_fraction"]), step)
    if health["collapsed"] and not any(h["collapsed"] for h in model.health_log[:-1]):
        CONSOLE.print(collapse_warning(health, cfg.deform_head_init))


@torch.no_grad()
def refresh_static(model: Any, times: Optional[Tensor] = None) -> None:
    """Re-decide which of `model`'s Gaussians are static from its current deformation field, at `times` (default:
    up to `static_times` of the training times, evenly spread)."""
    times = sample_times(model.train_times, model.config.static_times) if times is None else times
    threshold = model.config.static_threshold * model.scene_extent
    scale_offset = model.config.deform_scale_offset
    static, offset = classify(model.deformation, model.means, model.scales, times, threshold, scale_offset)
    model.strategy_state.update({"static": static, "static_offset": offset, "static_step": int(model.step)})
