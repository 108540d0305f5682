"""Timing a training step phase by phase inside nerfstudio's loop: a mark (the host clock and, on CUDA, an event on
the training stream) at every phase boundary, the phases' device and host milliseconds from them, and their means
over a window of steps (garo_ns.bench.train_profile's `phases`; the phases are listed in `PHASES`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch

PHASES = (
    "data",
    "deformation_forward",
    "rasterization_forward",
    "metrics",
    "loss_forward",
    "loss_backward",
    "rasterization_backward",
    "deformation_backward",
    "optimizers",
    "strategy",
    "after_step_other",
    "loop_between_steps",
)
"""The phases of a step, in the order they run (see the module docstring)."""


class Mark:
    """A point in a step: the host clock and, on CUDA, an event recorded on the current stream."""

    __slots__ = ("host", "event")

    def __init__(self, cuda: bool) -> None:
        self.host = time.perf_counter()
        self.event = None
        if cuda:
            self.event = torch.cuda.Event(enable_timing=True)
            self.event.record()

    def device_ms_to(self, later: "Mark") -> float:
        """Milliseconds from this mark to `later` on the device's timeline (the host clock without CUDA);
        call after a synchronisation."""
        if self.event is not None and later.event is not None:
            return float(self.event.elapsed_time(later.event))
        return (later.host - self.host) * 1e3

    def host_ms_to(self, later: "Mark") -> float:
        return (later.host - self.host) * 1e3


@dataclass
class StepMarks:
    """The marks of one instrumented step: each phase's (start, end) and nested phases to subtract."""

    spans: Dict[str, List[Tuple[Mark, Mark]]] = field(default_factory=dict)
    points: Dict[str, Mark] = field(default_factory=dict)

    def add(self, phase: str, start: Mark, end: Mark) -> None:
        self.spans.setdefault(phase, []).append((start, end))


def phase_times(step: StepMarks, next_start: Optional[Mark]) -> Dict[str, Dict[str, float]]:
    """{"device": {phase: ms}, "host": {phase: ms}} of one step from its marks (after a synchronisation).

    The backward pass is cut at the points its hooks marked: `backward_start` (the loss's gradient),
    `render_grad` (the render's), `splats_grad` (the deformed Gaussians'), and ends where the optimizers
    start; the strategy runs inside the after-step callback and is subtracted from it. `next_start`:
    the next step's first mark (the loop between the two), None for a window's last step.
    """
    out: Dict[str, Dict[str, float]] = {"device": {}, "host": {}}

    def put(phase: str, start: Mark, end: Mark) -> None:
        out["device"][phase] = out["device"].get(phase, 0.0) + start.device_ms_to(end)
        out["host"][phase] = out["host"].get(phase, 0.0) + start.host_ms_to(end)

    for phase, spans in step.spans.items():
        if phase == "step":
            continue
        for start, end in spans:
            put(phase, start, end)
    p = step.points
    cuts = [p.get("backward_start"), p.get("render_grad"), p.get("splats_grad")]
    # The backward pass ends where the optimizers' step starts (zero_grad, also "optimizers", runs first).
    if all(c is not None for c in cuts) and "optimizer_step" in p:
        ends = cuts[1:] + [p["optimizer_step"]]
        for phase, start, end in zip(("loss_backward", "rasterization_backward", "deformation_backward"), cuts, ends):
            put(phase, start, end)  # type: ignore[arg-type]
    if "after_start" in p:  # from the first after-step callback to the step's end
        put("after_step_other", p["after_start"], step.spans["step"][0][1])
    for kind in ("device", "host"):
        if "after_step_other" in out[kind]:
            out[kind]["after_step_other"] -= out[kind].get("strategy", 0.0)
    first, last = step.spans["step"][0]
    out["device"]["step"] = first.device_ms_to(last)
    out["host"]["step"] = first.host_ms_to(last)
    if next_start is not None:
        put("loop_between_steps", last, next_start)
    return out


class StepInstrument:
    """Marks the phases of the steps of a nerfstudio Trainer whose model is a GaroModel.

    It wraps bound methods of the trainer's own objects (the datamanager, the model, its strategy, the
    optimizers) and adds hooks on the loss, the render and the deformed Gaussians; outside an active
    window each wrapper costs one attribute test."""

    def __init__(self, trainer: Any) -> None:
        self.trainer = trainer
        self.model = trainer.pipeline.model
        self.cuda = self.model.device.type == "cuda"
        self.active = False
        self.steps: List[StepMarks] = []
        self._handles: List[Any] = []
        dm, model, opt = trainer.pipeline.datamanager, self.model, trainer.optimizers
        self._wrap(dm, "next_train", "data")
        # The backward pass's cuts: where the gradient reaches the deformed Gaussians, the render and the loss.
        self._wrap(model, "gaussians_at", "deformation_forward", lambda splats: self._hook(splats.means, "splats_grad"))
        self._wrap(model, "render", "rasterization_forward")
        self._wrap(model, "get_metrics_dict", "metrics")
        self._wrap(
            model, "get_loss_dict", "loss_forward", lambda loss: self._hook(loss.get("main_loss"), "backward_start")
        )
        self._wrap(model, "get_outputs", None, lambda outputs: self._hook(outputs.get("rgb"), "render_grad"))
        self._wrap(model.strategy, "step_post_backward", "strategy")
        self._wrap(opt, "zero_grad_some", "optimizers")
        self._wrap(opt, "optimizer_scaler_step_some", "optimizers", point="optimizer_step")
        self._wrap(opt, "scheduler_step_all", "optimizers")

    def mark(self) -> Mark:
        return Mark(self.cuda)

    def _wrap(
        self,
        obj: Any,
        name: str,
        phase: Optional[str],
        after: Optional[Callable[[Any], None]] = None,
        point: Optional[str] = None,
    ) -> None:
        """Replace `obj.name` by a wrapper that marks `phase` around the call, the point `point` at its
        start, and passes the result to `after` (to hook its tensors)."""
        inner = getattr(obj, name)

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            if not self.active or not self.steps:
                return inner(*args, **kwargs)
            start = self.mark() if phase else None
            if point is not None and start is not None:
                self.steps[-1].points.setdefault(point, start)
            result = inner(*args, **kwargs)
            if phase:
                self.steps[-1].add(phase, start, self.mark())  # type: ignore[arg-type]
            if after is not None:
                after(result)
            return result

        setattr(obj, name, wrapped)

    def _hook(self, tensor: Any, name: str) -> None:
        """Mark the point `name` of this step when the gradient reaches `tensor` (a training step's tensors only)."""
        if self.model.training and isinstance(tensor, torch.Tensor) and tensor.requires_grad:
            points = self.steps[-1].points

            def hook(grad: Any) -> None:  # returns None: the gradient passes on unchanged
                points.setdefault(name, self.mark())

            self._handles.append(tensor.register_hook(hook))

    def begin_step(self) -> None:
        if self.active:
            self.steps.append(StepMarks())
            self.steps[-1].points["step_start"] = self.mark()

    def after_start(self) -> None:
        if self.active and self.steps:
            self.steps[-1].points["after_start"] = self.mark()

    def end_step(self) -> None:
        if self.active and self.steps:
            step = self.steps[-1]
            step.add("step", step.points.pop("step_start"), self.mark())
            for handle in self._handles:  # hooks on leaf parameters would outlive the step
                handle.remove()
            self._handles.clear()


def summarise_window(steps: List[StepMarks]) -> Dict[str, Any]:
    """Mean device and host milliseconds per step of each phase over the instrumented steps."""
    nexts = [s.spans["step"][0][0] for s in steps[1:]] + [None]
    times = [phase_times(s, n) for s, n in zip(steps, nexts)]
    out: Dict[str, Any] = {}
    for kind in ("device", "host"):
        names = [p for p in PHASES + ("step",) if any(p in t[kind] for t in times)]
        means = {}
        for p in names:
            values = [t[kind][p] for t in times if p in t[kind]]
            means[p] = sum(values) / len(values)
        out[f"{kind}_ms"] = means
    inside = out["device_ms"].get("step", 0.0)
    labelled = sum(v for k, v in out["device_ms"].items() if k not in ("step", "loop_between_steps"))
    out["device_ms_unlabelled_in_step"] = inside - labelled
    return out
