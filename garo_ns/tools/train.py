"""Train a method of the plugin in-process (what `ns-train` does), for the demo, tests and benchmarks."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Optional

from garo_ns import compat
from garo_ns.config import METHODS

compat.install()

Method = Literal[
    "garo-deform",
    "deform-splatfacto",
    "garo-compact",
    "garo-deform-real",
    "deform-splatfacto-real",
    "garo-compact-real",
]


@dataclass
class QuickSchedule:
    """A short schedule for small scenes on a CPU: every phase of the full recipe, compressed.

    The full recipe is 40k steps (static warm-up 3k, densify 500..15k); this keeps the same
    order of events in `steps` steps so that a few hundred steps exercise all of them.
    """

    steps: int = 600
    num_random: int = 5000
    deform_width: int = 128
    deform_depth: int = 6
    deform_skip: int = 3
    deform_lr: float = 5e-3
    extra: Dict[str, Any] = field(default_factory=dict)

    def apply(self, config: Any) -> None:
        """Write the schedule into a TrainerConfig."""
        s = self.steps
        m = config.pipeline.model
        config.max_num_iterations = s
        config.steps_per_save = s
        m.num_random = self.num_random
        m.deform_width, m.deform_depth, m.deform_skip = self.deform_width, self.deform_depth, self.deform_skip
        m.deform_warmup = s // 4
        m.warmup_length = max(s // 20, 10)
        m.refine_every = max(s // 30, 5)
        m.reset_alpha_every = 10
        m.stop_split_at = int(s * 0.6)
        m.sh_degree_interval = max(s // 8, 1)
        m.static_every = max(s // 10, 1)
        m.health_every = max(s // 6, 1)
        # The heads start at zero here: with this schedule's 6x deformation rate, a field starting
        # from random offsets is still moving everywhere after a few hundred steps (no Gaussian of
        # the built-in scene under a third of a pixel), while the zero start leaves the static parts
        # quiet. The collapse that zero heads risk at 40k steps is watched by the health check.
        m.deform_head_init = "zero"
        m.time_noise_steps = s
        m.prune_contribution_steps = (int(s * 0.7),)
        # Compaction rounds (when on) from the end of densification (60%) to 90% of the steps.
        m.compact_every = max(s // 30, 5)
        m.compact_max_rounds = max((int(s * 0.9) - m.stop_split_at) // m.compact_every, 1)
        m.compact_min_gaussians = min(m.compact_min_gaussians, self.num_random // 10)
        for opt in config.optimizers.values():
            sched = opt.get("scheduler")
            if sched is not None and hasattr(sched, "max_steps"):
                sched.max_steps = s
        # D-3DGS's deformation rate (8e-4) is tuned for 37k deforming steps; with a few hundred, the
        # MLP would barely move from its initial state, so it learns faster here.
        deform = config.optimizers["deformation"]
        deform["optimizer"].lr = self.deform_lr
        deform["scheduler"].lr_final = self.deform_lr / 100
        for key, value in self.extra.items():
            setattr(m, key, value)


@dataclass
class DemoSchedule(QuickSchedule):
    """The demo's schedule: QuickSchedule, with the deformation field's warm-up and learning rate its own.

    In QuickSchedule the deformation rate decays from step 0, so by the end of the static warm-up it has
    already lost a third of its log-range, and the field then learns the motion in the remaining steps at
    a falling rate. Here the rate holds at `deform_lr` until the field switches on (`deform_warmup_frac`
    of the steps) and only then decays, to `deform_lr * deform_lr_final_ratio` at the last step.
    """

    deform_warmup_frac: float = 0.25
    deform_lr_final_ratio: float = 0.01
    lr_scale: Dict[str, float] = field(default_factory=dict)
    """Factors on the learning rates of these parameter groups (initial and final alike; e.g. "means").
    D-3DGS's rates are set for 30k-40k steps: the means' rate, 8e-4 decaying 100x, adds up to about 0.34
    scene units of travel over 2000 steps (Adam moves a parameter at most about its rate per step), and
    the colours' 2.5e-3 to 5 SH units, so a compressed schedule may need them faster."""

    def apply(self, config: Any) -> None:
        """Write the schedule into a TrainerConfig."""
        super().apply(config)
        warmup = int(self.steps * self.deform_warmup_frac)
        if "deform_warmup" not in self.extra:
            config.pipeline.model.deform_warmup = warmup
        sched = config.optimizers["deformation"]["scheduler"]
        sched.warmup_steps = warmup
        sched.lr_pre_warmup = self.deform_lr
        sched.lr_final = self.deform_lr * self.deform_lr_final_ratio
        for group, factor in self.lr_scale.items():
            if group not in config.optimizers:
                raise ValueError(f"lr_scale names {group!r}, not a parameter group ({', '.join(config.optimizers)})")
            opt = config.optimizers[group]
            opt["optimizer"].lr *= factor
            sched = opt.get("scheduler")
            if sched is not None and getattr(sched, "lr_final", None) is not None:
                sched.lr_final *= factor
            if sched is not None and group == "deformation":
                sched.lr_pre_warmup *= factor


def make_config(
    method: Method,
    data: Path,
    output_dir: Path,
    device: Literal["cpu", "cuda"] = "cpu",
    schedule: Optional[QuickSchedule] = None,
    alpha_color: Literal["black", "white"] = "black",
    eval_split: Literal["val", "test"] = "test",
    experiment_name: str = "run",
) -> Any:
    """A TrainerConfig for `method` on the scene `data` (D-NeRF layout; NeRF-DS layout for the -real methods)."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (known: {', '.join(METHODS)})")
    real = method.endswith("-real")
    config = copy.deepcopy(METHODS[method].config)
    config.output_dir = Path(output_dir)
    config.experiment_name = experiment_name
    config.timestamp = ""
    config.vis = "tensorboard"
    config.machine.device_type = device
    config.logging.local_writer.enable = False
    config.steps_per_eval_image = 10**9
    config.steps_per_eval_all_images = 10**9
    config.pipeline.datamanager.dataparser.data = Path(data)
    if not real:  # NeRF-DS captures are opaque and have train and val ids only
        config.pipeline.datamanager.dataparser.alpha_color = alpha_color
        config.pipeline.datamanager.dataparser.eval_split = eval_split
    if schedule is not None:
        schedule.apply(config)
    return config


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch, as `ns-train` does before building the trainer."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def setup_trainer(config: Any) -> Any:
    """The Trainer of `config`, set up as `ns-train` sets it up: the config saved, Python, numpy and torch seeded (the
    same initial Gaussians in every run of one seed)."""
    if not config.timestamp:
        config.set_timestamp()
    seed_everything(config.machine.seed)
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def train(config: Any) -> Any:
    """Run training to the end; returns the Trainer (its pipeline holds the trained model)."""
    trainer = setup_trainer(config)
    trainer.train()
    return trainer
