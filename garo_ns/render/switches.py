"""Which render switches a model uses when its config leaves them to the plugin (None: "auto").

A finished model renders fast without flags. Outside a training run (ns-viewer, ns-render,
garo-eval, the benchmark loading a checkpoint) the exact switches (`cuda_graph`, `lean_raster`: same
arithmetic, fewer launches) are on wherever CUDA runs, and the approximate ones (`static_skip`, a
lower MLP `render_precision`) are on when, measured on training views, they cost at most
`bound_db` of PSNR against the plain render on every view checked. During a training run, and so
for a viewer attached to one, every switch left to auto stays off: what the user watches is what
trains. A switch set explicitly is used as set, in both cases.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garo_ns.render.frame import FrameSettings

EXACT = ("cuda_graph", "lean_raster")
"""Switches that change no pixel: on by default outside training wherever CUDA runs."""

DEFAULT_BOUND_DB = 0.02
"""Largest PSNR loss on any checked training view for which an approximate switch is turned on by
default: well below what a viewer can see, and the bound the benchmark holds render paths to."""

Measure = Callable[[FrameSettings], float]
"""Renders training views with the given switches and returns the largest PSNR loss (dB) of any
view against the same views rendered plain."""


def label(trial: FrameSettings) -> str:
    """The name under which `resolve` records a trial's loss: the approximate switch it adds."""
    if trial.render_precision != "fp32":
        return f"render_precision={trial.render_precision}"
    return "static_skip"


def resolve(
    requested: Mapping[str, Any],
    training_run: bool,
    cuda: bool,
    measure: Optional[Measure] = None,
    precisions: Sequence[str] = ("fp16", "tf32"),
    bound_db: float = DEFAULT_BOUND_DB,
) -> Tuple[FrameSettings, Dict[str, float]]:
    """The switches to render with, and the measured PSNR loss of each approximate switch tried.

    Args:
        requested: the config's value of each FrameSettings field; None leaves it to this function.
        training_run: whether the model belongs to a run that is training (or will train).
        cuda: whether the model renders on CUDA (graphs, the lean path and tf32 need it).
        measure: see `Measure`; without one the approximate switches left to auto stay off.
        precisions: the MLP precisions to try, fastest first (benchmarks/results/deform_mlp_H100.json);
            the first within the bound is used.
        bound_db: see DEFAULT_BOUND_DB.
    """
    if not (bound_db >= 0 and math.isfinite(bound_db)):
        raise ValueError(f"the render switches' PSNR bound must be a finite number >= 0, got {bound_db}")
    names = {f.name for f in fields(FrameSettings)}
    unknown = set(requested) - names
    if unknown:
        raise ValueError(f"unknown render switches {sorted(unknown)}; known: {sorted(names)}")
    settings = FrameSettings(**{k: v for k, v in requested.items() if v is not None})
    fast = not training_run
    for name in EXACT:
        if requested.get(name) is None:
            settings = replace(settings, **{name: fast and cuda})
    tried: Dict[str, float] = {}
    if not fast or measure is None:
        return settings, tried

    def accept(trial: FrameSettings) -> bool:
        loss = float(measure(trial))
        tried[label(trial)] = loss
        return loss <= bound_db  # False for NaN too

    if requested.get("static_skip") is None:
        trial = replace(settings, static_skip=True)
        if accept(trial):
            settings = trial
    if requested.get("render_precision") is None and cuda:
        for mode in precisions:
            trial = replace(settings, render_precision=mode)
            if accept(trial):
                settings = trial
                break
    return settings, tried


def replay(tried: Mapping[str, float]) -> Measure:
    """A Measure answering from losses `resolve` recorded earlier (at the end of training, where the
    training views are at hand); a trial never measured counts as an infinite loss."""
    return lambda trial: float(tried.get(label(trial), math.inf))


def measure_on_views(render: Callable[[int, Optional[FrameSettings]], Tensor], targets: Sequence[Tensor]) -> Measure:
    """A Measure over views: `render(i, None)` is view i rendered plain (fp32, every Gaussian),
    `render(i, trial)` the same view with the trial's switches; `targets[i]` its ground truth."""
    gt = torch.stack([t.float() for t in targets])
    reference = torch.stack([render(i, None).float() for i in range(len(targets))])
    return lambda trial: worst_psnr_loss(reference, torch.stack([render(i, trial).float() for i in range(len(gt))]), gt)


def worst_psnr_loss(reference: Tensor, trial: Tensor, targets: Tensor) -> float:
    """Largest PSNR loss (dB) over views of `trial` renders against `reference` renders, both
    scored on `targets` ([V, H, W, 3] each, values in [0, 1]). A trial render that is not finite
    anywhere counts as an infinite loss."""
    if not bool(torch.isfinite(trial).all()):
        return math.inf
    dims = tuple(range(1, reference.dim()))
    mse_ref = ((reference - targets) ** 2).mean(dim=dims).clamp_min(1e-12)
    mse_trial = ((trial - targets) ** 2).mean(dim=dims).clamp_min(1e-12)
    return float((10 * torch.log10(mse_trial / mse_ref)).max())
