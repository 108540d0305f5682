"""Where a training step's time goes, measured inside nerfstudio's own training loop.

At a few steps of a real run (say 2k, 10k and 30k) a window of steps is timed in two ways:

* **plain**: the wall time of `plain_steps` steps with no instrument but one synchronisation at each end,
  which is what the run costs;
* **phases**: `phase_steps` steps with a mark at every phase boundary (a CUDA event on the training
  stream and the host clock): the data, the deformation field's forward, the rasterizer's forward, the
  metrics and the loss (SSIM included), then the backward pass cut where the gradient reaches the render
  (the loss's backward done) and the deformed Gaussians (the rasterizer's backward done; the rest is the
  field's backward and the activations'), the optimizers, the strategy, the rest of the after-step work
  (static classification, health check, compaction) and the loop between steps (logging, checkpoints).

Device milliseconds are the time between a phase's two marks on the GPU's timeline, host milliseconds
the time the Python thread spent there: where the host time of a step exceeds its device time, the GPU
waits for the loop. On CUDA the window also counts the host synchronisations (torch's sync debug mode:
each `.item()`, `.cpu()`, `nonzero` ...) with the lines that cause most of them, and a short profiler
pass gives the share of the step's wall time the GPU spends in kernels. A last pass records the host's side
(`host_ops`): per step, the CUDA runtime calls (kernel and graph launches, copies, waits) and the host operations
that take the most of the Python thread's time, which is where a host-bound step can be cut. On a CPU the marks
are host clocks and both columns agree, so the same code runs in the tests.

It measures with `step_phases`, `host_syncs`, `kernel_table` and writes with `profile_docs`.

    python -m garo_ns.bench.train_profile --scene data/dnerf/jumpingjacks --method garo-deform \
        --windows 2000 10000 30000 --output train_profile.json
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch

from garo_ns.bench.host_syncs import SyncCounter, host_op_summary
from garo_ns.bench.kernel_table import kernel_share, top_kernels
from garo_ns.bench.profile_docs import markdown_table
from garo_ns.bench.step_phases import StepInstrument, summarise_window
from garo_ns.tools.fps import synchronize


@dataclass
class ProfileSettings:
    """Where and how long to measure."""

    windows: Sequence[int] = (2000, 10_000, 30_000)
    """Steps at which a window starts (those past the run's end are skipped)."""
    plain_steps: int = 100
    """Steps timed with no instrument, for the window's wall time per step."""
    phase_steps: int = 30
    """Steps timed phase by phase, right after the plain ones."""
    profiler_steps: int = 10
    """On CUDA, steps under torch's profiler after those, for the GPU's busy share (0: none)."""
    host_op_steps: int = 10
    """Steps under torch's profiler recording the host too, last: each step's CUDA runtime calls and its costliest
    host operations (`host_ops`; 0: none). Apart from the busy share's pass, whose timing the host events would
    slow."""
    timeline_every: int = 1000
    """Every this many steps, the run's elapsed seconds and Gaussian count (0: none): where a whole run's time goes
    (the windows are a few steps each; the densification phase, evaluations and checkpoints fall between them)."""


SETTINGS = ("plain_steps", "phase_steps", "profiler_steps", "host_op_steps", "timeline_every")
"""ProfileSettings' step counts, each a command-line option (`--plain-steps` ...) and recorded in the result."""


class TrainProfiler:
    """Runs the windows of `settings` inside a nerfstudio Trainer's loop (two training callbacks)."""

    def __init__(self, trainer: Any, settings: ProfileSettings) -> None:
        from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

        self.trainer, self.settings = trainer, settings
        self.instrument = StepInstrument(trainer)
        self.cuda, self.device = self.instrument.cuda, self.instrument.model.device
        self.windows: List[Dict[str, Any]] = []
        self._plan: Dict[int, Tuple[str, int]] = {}
        # Each part of a window and its steps, in the order they run.
        self._parts = {"plain": settings.plain_steps, "phases": settings.phase_steps}
        self._parts.update(profiler=settings.profiler_steps if self.cuda else 0, host_ops=settings.host_op_steps)
        span = sum(self._parts.values())
        # A window whose steps (every part of it) pass the run's end is skipped.
        for start in (w for w in settings.windows if w + span <= trainer.config.max_num_iterations):
            step = start
            for kind, n in self._parts.items():
                for _ in range(n):
                    self._plan[step] = (kind, start)
                    step += 1
        self._current: Optional[Dict[str, Any]] = None
        self._t0 = 0.0
        self._sync_counter: Optional[SyncCounter] = None
        self._prof: Any = None
        self.timeline: List[Dict[str, float]] = []
        self.render_choice_seconds: Optional[float] = None
        self._time_render_choice()
        self.run_start: Optional[float] = None
        before, after = TrainingCallbackLocation.BEFORE_TRAIN_ITERATION, TrainingCallbackLocation.AFTER_TRAIN_ITERATION
        # First before the step, first and last after it: the step's span and its after-step part.
        trainer.callbacks.insert(0, TrainingCallback([before], self._before))
        trainer.callbacks.insert(1, TrainingCallback([after], lambda step: self.instrument.after_start()))
        trainer.callbacks.append(TrainingCallback([after], self._after))

    def _time_render_choice(self) -> None:
        """Time the finished model's render-switch measurement at the last step (garo_ns.render.switches: the time
        tables it builds and the training views it renders), which runs inside the last step's callback: it
        prepares rendering, not training, so the result reports it apart."""
        switches = getattr(self.instrument.model, "switches", None)
        inner = getattr(switches, "measure_on_training_views", None)
        if inner is None:
            return

        def timed(*args: Any, **kwargs: Any) -> Any:
            synchronize(self.device)
            t0 = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                synchronize(self.device)
                self.render_choice_seconds = (self.render_choice_seconds or 0.0) + time.perf_counter() - t0

        switches.measure_on_training_views = timed

    def _before(self, step: int) -> None:
        if self.run_start is None:
            self.run_start = time.perf_counter()
        kind, start = self._plan.get(step, (None, None))
        prev = self._plan.get(step - 1, (None, None))
        if kind is not None and prev != (kind, start):  # the first step of a part of a window
            if kind == "plain":
                self._current = {"step": start, "gaussians": int(self.instrument.model.num_points)}
                self.windows.append(self._current)
            synchronize(self.device)
            self._t0 = time.perf_counter()
            if kind == "phases":
                self.instrument.active = True
                if self.cuda:
                    self._sync_counter = SyncCounter()
                    self._sync_counter.start()
            if kind in ("profiler", "host_ops"):
                activities = [torch.profiler.ProfilerActivity.CUDA] if self.cuda else []
                if kind == "host_ops":
                    activities.append(torch.profiler.ProfilerActivity.CPU)
                self._prof = torch.profiler.profile(activities=activities)
                self._prof.__enter__()
        self.instrument.begin_step()

    def _after(self, step: int) -> None:
        self.instrument.end_step()
        every = self.settings.timeline_every
        if every and (step + 1) % every == 0 and self.run_start is not None:
            # No synchronisation: the host runs at most a few steps ahead of the GPU, which is noise at this scale.
            elapsed = time.perf_counter() - self.run_start
            self.timeline.append(
                {"step": step + 1, "seconds": elapsed, "gaussians": int(self.instrument.model.num_points)}
            )
        kind, start = self._plan.get(step, (None, None))
        if kind is None or self._plan.get(step + 1, (None, None)) == (kind, start):
            return
        synchronize(self.device)
        wall_ms = (time.perf_counter() - self._t0) * 1e3
        window = self._current if self._current is not None else {}
        n = self._parts[kind]
        if kind == "plain":
            window["plain_ms_per_step"] = wall_ms / n
        elif kind == "phases":
            self.instrument.active = False
            window["instrumented_ms_per_step"] = wall_ms / n
            window.update(summarise_window(self.instrument.steps))
            self.instrument.steps = []
            if self._sync_counter is not None:
                self._sync_counter.stop()
                window["host_syncs_per_step"] = self._sync_counter.count / n
                window["host_sync_sources"] = dict(self._sync_counter.sources.most_common(8))
                self._sync_counter = None
        elif kind == "profiler" and self._prof is not None:
            self._prof.__exit__(None, None, None)
            window["gpu_busy_share"] = kernel_share(self._prof, wall_ms)
            window["top_kernels"] = top_kernels(self._prof, n)
            window["profiled_ms_per_step"] = wall_ms / n
            self._prof = None
        elif kind == "host_ops" and self._prof is not None:
            self._prof.__exit__(None, None, None)
            window["host_ops"] = {"ms_per_step": wall_ms / n, **host_op_summary(self._prof, n)}
            self._prof = None


def loop_work(config: Any) -> None:
    """The training loop without what `ns-train` does besides training: the harness's config already evaluates
    nothing and writes TensorBoard only; one checkpoint, at the end."""
    config.steps_per_save = config.max_num_iterations


def adam_graph_counts(optimizers: Any) -> Optional[Dict[str, int]]:
    """How often the run's Adam graph (`adam_cuda_graph`) was captured and replayed (None: not in use)."""
    graph = getattr(optimizers, "adam_graph", None)
    return None if graph is None else {"captures": graph.captures, "replays": graph.replays}


def cuda_memory_mib(device: str) -> Optional[Dict[str, float]]:
    """The run's peak of memory in tensors and of memory the caching allocator reserved (what other processes
    cannot use, and what nvidia-smi shows), in MiB; None off CUDA."""
    if device != "cuda":
        return None
    return {
        "peak_allocated": torch.cuda.max_memory_allocated() / 2**20,
        "peak_reserved": torch.cuda.max_memory_reserved() / 2**20,
    }


def splats_graph_counts(model: Any) -> Optional[Dict[str, float]]:
    """How often the run's training graph of the Gaussians (`deform_cuda_graph`) was captured, one capture per new
    count of Gaussians, and the wall seconds those captures took, warm-up runs included (None: no such graph)."""
    graph = getattr(model, "train_splats", None)
    if graph is None or not getattr(graph, "enabled", False):
        return None
    return {"captures": int(graph.captures), "capture_s": float(graph.capture_s)}


def render_choice_record(model: Any) -> Optional[Dict[str, Any]]:
    """What the finished model's render choice measured (garo_ns.render.switches): each approximate switch's change,
    and for the time table the rungs tried, their changes and build seconds and the table taken (None: no record)."""
    record = getattr(getattr(model, "switches", None), "record", None)
    if not record:
        return None
    table = record.get("time_table") or {}
    info = table.get("info") or {}
    return {
        "tried_db": dict(record.get("tried", {})),
        "table_rungs_db": table.get("intervals_tried_db"),
        "table_rungs_build_s": table.get("build_s"),
        "table_rungs_previewed_db": table.get("intervals_previewed_db"),
        "table_rungs_preview_s": table.get("preview_s"),
        "table_taken": {k: info.get(k) for k in ("keys", "mb", "build_s", "network", "gaussians")} if info else None,
        "table_off": table.get("off"),
    }


def main(argv: Optional[Sequence[str]] = None) -> Dict[str, Any]:
    from garo_ns.bench.benchmark import environment
    from garo_ns.tools.eval import model_overrides
    from garo_ns.tools.train import QuickSchedule, make_config, setup_trainer

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True, help="a D-NeRF scene folder")
    parser.add_argument("--method", default="garo-deform")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default: the method's)")
    parser.add_argument("--windows", type=int, nargs="+", default=list(ProfileSettings.windows))
    for key in SETTINGS:  # --plain-steps ... --timeline-every: ProfileSettings' fields, its defaults
        parser.add_argument(f"--{key.replace('_', '-')}", type=int, default=getattr(ProfileSettings, key))
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--quick", action="store_true", help="the compressed CPU schedule (tests)")
    parser.add_argument("--split", choices=("test", "val"), default="test", help="eval split of the run's config")
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/train_profile"))
    parser.add_argument("--score", action="store_true", help="score the trained model on --split at the end")
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument(
        "--set", nargs="+", default=[], metavar="NAME=VALUE", help="model settings, e.g. deform_cuda_graph=True"
    )
    args = parser.parse_args(argv)
    overrides = model_overrides(args.set)
    config = make_config(
        args.method,
        args.scene,
        args.work_dir,
        device=args.device,
        schedule=QuickSchedule(steps=args.steps or 600, num_random=2000) if args.quick else None,
        eval_split=args.split,
        experiment_name=args.method,
    )
    config.timestamp = "profile"
    for name, value in overrides.items():
        setattr(config.pipeline.model, name, value)
    if args.steps:
        config.max_num_iterations = args.steps
    loop_work(config)
    trainer = setup_trainer(config)
    settings = ProfileSettings(args.windows, **{key: getattr(args, key) for key in SETTINGS})
    profiler = TrainProfiler(trainer, settings)
    start = time.perf_counter()
    trainer.train()
    seconds = time.perf_counter() - start
    steps = config.max_num_iterations
    result: Dict[str, Any] = {
        "scene": args.scene.name,
        "method": args.method,
        "device": args.device,
        "environment": environment(args.device),
        "steps": steps,
        "train_seconds": seconds,
        "steps_per_second": steps / seconds,
        "windows": profiler.windows,
        "settings": {key: getattr(settings, key) for key in SETTINGS},
        "render_choice_seconds": profiler.render_choice_seconds,
        "render_choice_record": render_choice_record(trainer.pipeline.model),
        "seconds_before_first_step": None if profiler.run_start is None else profiler.run_start - start,
        "timeline": profiler.timeline,
        "model_settings": overrides,
        "adam_graph": adam_graph_counts(trainer.optimizers),
        "splats_graph": splats_graph_counts(trainer.pipeline.model),
        "gaussians_final": int(trainer.pipeline.model.num_points),
        "cuda_memory_mib": cuda_memory_mib(args.device),
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    args.output.with_suffix(".md").write_text(
        f"{args.method} on {args.scene.name}, {result['environment'].get('gpu') or 'CPU'}: "
        + ("ms per step, device (host); " if result["windows"] else "")
        + f"{steps} steps in {seconds:.0f} s ({result['steps_per_second']:.1f} steps/s)\n\n"
        + markdown_table(result)
    )
    if args.score:  # the trained model on the eval split, as garo-eval scores it (plain render)
        from garo_ns.tools.eval import evaluate

        model = trainer.pipeline.model
        model.eval()
        scores = evaluate(trainer.pipeline, args.scene, args.split)
        kept = ("psnr", "ssim", "lpips", "num_gaussians", "split", "background", "n_images")
        result["score"] = {k: scores.get(k) for k in kept if k in scores}
        args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(markdown_table(result))
    return result


if __name__ == "__main__":
    main()
