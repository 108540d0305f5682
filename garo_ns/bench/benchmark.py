"""`python -m garo_ns.bench.benchmark`: GARO against the D-3DGS baseline, speed against error, in one run.

Phase 1 trains every variant, one process per GPU (round-robin when there are more variants than
GPUs; several processes may share a GPU). Phase 2, after all training has ended, loads each run in
turn and evaluates it on the chosen split and times it with the FPS protocol (garo_ns.tools.fps), so
no timing overlaps another job. Phase 3 (`--paired-passes`) times the plain renders again in alternating
passes (`fps_paired`). One JSON holds everything; a Markdown table and a PNG plot (FPS against PSNR, marker area by
Gaussian count) are written next to it.

Variants: deform-splatfacto (baseline), garo-deform (full GARO), and on request garo-oaa, garo-gca
(the paper's ablations), garo-rho<value> (rho_max sweep), garo-prune<ratio> (GARO plus pruning
of a fixed share of the least contributing Gaussians) and garo-compact / garo-compact<dB> (GARO plus
compaction measured on training views, with its default total budget or the one given in dB) /
garo-compact--<setting>-<value>--... (any compaction settings, e.g. `garo-compact--fraction-0.3`).
A name may carry render-time switches after `+`: `+static` (static Gaussians skip the MLP), `+graph`
(everything before the rasterizer as one CUDA graph), `+lean` (gsplat's kernels called directly), `+table`
(the time table forced on, garo_ns.render.time_table), `+fp16` (parameters rounded to the compact
half-precision file of garo_ns.state.storage; its size is the model size), `+auto` (every switch left to the
finished model, as ns-viewer, ns-render and garo-eval render without flags; the row records what it chose in
`render_switches_used`), `+framegraph` (with graph and lean: the camera's share of a frame as one graph,
garo_ns.render.frame_graph), e.g. `garo-deform+static+graph+lean`; such variants reuse the training of the name
before the first `+` and differ only at render time. Every such row records `psnr_vs_plain`: its PSNR minus
the plain row's (the name before the first `+`), view by view (an approximate switch's bound: within 0.02 dB
on every view). Deleted paths (`+bf16`, `+fused`, `+static4x`, `+tf32`, `+half`) and what they measured:
benchmarks/HISTORY.md; their names are refused as unknown switches.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

from garo_ns import compat
from garo_ns.bench import transfer
from garo_ns.bench.results import publish, save_figure

compat.install()

FULL_ITERATIONS = 40_000
RENDER_SWITCHES: Dict[str, Dict[str, Any]] = {
    "static": {"static_skip": True},
    "graph": {"cuda_graph": True},
    "lean": {"lean_raster": True},
    "fp16": {"storage": "fp16"},
    # What a user of ns-viewer, ns-render or garo-eval gets without flags: every switch left to the
    # finished model, which decides from the losses it measured at the end of training.
    "auto": {"static_skip": None, "cuda_graph": None, "lean_raster": None, "time_table": None},
    # The time table forced on (garo_ns.render.time_table), whatever the model measured.
    "table": {"time_table": True},
    # The camera's share of a frame as one graph (garo_ns.render.frame_graph; with graph and lean, or auto).
    "framegraph": {"frame_graph": True},
}
# The plain render: every switch off, the parameters as trained.
PLAIN_RENDER = {
    "static_skip": False,
    "cuda_graph": False,
    "lean_raster": False,
    "time_table": False,
    "frame_graph": False,
    "storage": "fp32",
}
# Render-time rows added by --speed for every trained variant: each switch alone, then together.
SPEED_ROWS = ("+static", "+graph", "+lean", "+static+graph", "+static+graph+lean", "+static+graph+lean+fp16")


def split_variant(name: str) -> Tuple[str, Dict[str, Any]]:
    """(trained variant, render-time model-config overrides) of a variant name like `garo-deform+static`."""
    base, *switches = name.split("+")
    render = dict(PLAIN_RENDER)
    for switch in switches:
        if switch not in RENDER_SWITCHES:
            raise ValueError(f"unknown render switch '+{switch}' in {name!r} (known: {sorted(RENDER_SWITCHES)})")
        render.update(RENDER_SWITCHES[switch])
    return base, render


def compaction_overrides(name: str) -> Dict[str, Any]:
    """The settings a `garo-compact--<setting>-<value>--...` name sets, e.g.
    `garo-compact--fraction-0.3--round_bound_db-0.05` (settings named as `compact_<setting>` in
    garo_ns.compaction.schedule.CompactionSettings, plus GARO's `rho_max`: how much GARO prunes before
    compaction measures the rest), so that one run can train several settings side by side; only letters,
    digits, `.`, `_` and `-`, as the result files and exports are named after it."""
    from garo_ns.compaction.schedule import CompactionSettings

    known = {f.name[len("compact_") :]: f for f in fields(CompactionSettings) if f.name.startswith("compact_")}
    garo = {"rho_max"}
    overrides: Dict[str, Any] = {}
    for item in name.split("--")[1:]:
        key, _, text = item.partition("-")
        if key not in known and key not in garo:
            raise ValueError(
                f"unknown compaction setting {key!r} in {name!r} (known: {sorted(known)}, and GARO's {sorted(garo)})"
            )
        integer = key in known and (isinstance(known[key].default, int) or key == "start")  # start: None or a step
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise ValueError(f"setting {key!r} in {name!r} needs {kind}, got {text!r}") from None
        overrides[key if key in garo else f"compact_{key}"] = value
    return overrides


def check_variant(name: str) -> None:
    """Raise for a variant name, render switch, compaction or GARO setting that training would refuse, before
    any run starts (a worker failing after the others trained would cost their GPU time)."""
    from garo_ns.compaction.schedule import CompactionSettings
    from garo_ns.garo_strategy import GaroSettings

    _, overrides = variant_settings(split_variant(name)[0])
    compact = {k: v for k, v in overrides.items() if k.startswith("compact_")}
    if compact:
        CompactionSettings(**compact).compaction()  # GaroConfigError out of range
    garo = {k: v for k, v in overrides.items() if k in {f.name for f in fields(GaroSettings)}}
    GaroSettings(**garo).validate_garo()


def variant_settings(name: str) -> Tuple[str, Dict[str, Any]]:
    """(method, model-config overrides) of a trained variant name."""
    if name.startswith("garo-compact--"):  # compaction with the settings the name gives
        return "garo-compact", compaction_overrides(name)
    if name.startswith("garo-compact"):  # garo-compact (its defaults) or garo-compact<total budget in dB>
        budget = name[len("garo-compact") :]
        return "garo-compact", {"compact_budget_db": float(budget)} if budget else {}
    if name.startswith("garo-prune"):
        return "garo-deform", {"garo_mode": "full", "prune_contribution_ratio": float(name[len("garo-prune") :])}
    if name == "deform-splatfacto":
        return "deform-splatfacto", {}
    if name == "garo-deform":
        return "garo-deform", {"garo_mode": "full", "garo_activity_window": "garo_step"}
    if name == "garo-oaa":
        return "garo-deform", {"garo_mode": "oaa"}
    if name == "garo-gca":
        return "garo-deform", {"garo_mode": "gca"}
    if name == "garo-alltime":  # activity averaged over all of training
        return "garo-deform", {"garo_mode": "full", "garo_activity_window": "training"}
    if name.startswith("garo-rho"):
        return "garo-deform", {"garo_mode": "full", "rho_max": float(name[len("garo-rho") :])}
    raise ValueError(f"unknown variant {name!r}")


@dataclass
class BenchArgs:
    """Train the baseline and GARO (and ablations) on one scene and report speed against error."""

    scene: Path
    """A D-NeRF scene, or a real capture (a video processed by ns-process-data, a NeRF-DS / HyperNeRF capture): a
    capture trains each variant's `-real` method and scores its held-out frames."""
    split: Literal["train", "val", "test"] = "test"
    """Split to score (lego: val)."""
    output: Path = Path("benchmarks/results/benchmark.json")
    """Result JSON; the .md table and .png plot go next to it."""
    work_dir: Path = Path("runs/benchmark")
    """Where the runs (checkpoints, logs) go."""
    variants: List[str] = field(default_factory=lambda: ["deform-splatfacto", "garo-deform"])
    speed: bool = False
    """Also report every trained variant with the render-time switches of SPEED_ROWS."""
    remeasure_switches: bool = False
    """Measure the approximate render switches again on the loaded model's training views before its rows (as
    the end of training does; for arms trained, or imported, from before a switch existed)."""
    model_set: List[str] = field(default_factory=list)
    """Model settings of every loaded run, `NAME=VALUE` (garo_ns.tools.eval.model_overrides), e.g.
    `time_table_budget_mb=1024` with --remeasure-switches and --pretrained: the same trained arms measured under
    another render setting; recorded as `model_settings`."""
    profile: bool = True
    """Add a per-stage breakdown of one frame (garo_ns.bench.frame_profile) to every variant."""
    iterations: Optional[int] = None
    """Training steps of every variant (None: the full schedule, 40k; a real capture's 20k); fewer than the full
    schedule is labelled shortened in the JSON."""
    gpus: List[int] = field(default_factory=lambda: [0])
    """GPUs for the training processes (variants are assigned round-robin)."""
    arms_per_gpu: int = 0
    """At most this many arms train on one GPU at a time; the others wait for a place on any of `gpus` (0: every
    arm at once). 1 trains each arm alone on its GPU, so its `train_seconds` are a lone run's: what
    garo_ns.bench.train_speed takes from a result file (three 40k arms sharing one GPU under MPS took 1122 s
    together, against about 240 s each alone, so on few GPUs queueing is also the quicker way)."""
    device: Literal["cuda", "cpu"] = "cuda"
    quick: bool = False
    """CPU smoke test: the compressed schedule of garo_ns.tools.train.QuickSchedule."""
    background: Literal["black", "white"] = "black"
    warmup_views: int = 5
    timing_repeats: int = 3
    deadline_s: Optional[float] = None
    """Stop training this many seconds after the start even if unfinished (recorded per variant)."""
    paired_passes: int = 6
    """After every row is measured, time the trained variants' plain renders again in this many alternating
    passes (garo_ns.bench.timing.paired_fps; 0: not done): `fps_paired` per variant and the ratio of these in
    `garo_vs_baseline`, steadier than one timing after another when frames take a few milliseconds."""
    export_dir: Optional[Path] = None
    """Also write each trained variant here as soon as it has trained (garo_ns.bench.transfer): its record,
    config and a checkpoint without optimizer state, so a later run can evaluate it beside its own arms."""
    renders_dir: Optional[Path] = None
    """Also write a few held-out views of each plain variant here as PNGs (`<variant>/<view>.png`, the ground truth
    as `ground-truth/`), spread over time, for a strip of renders (garo_ns.bench.strip)."""
    renders_views: int = 5
    pretrained: List[Path] = field(default_factory=list)
    """Exports of variants trained by an earlier run (same scene, same schedule): these are not trained
    again but evaluated and timed in this run's phase 2, one at a time like the rest. For pairs that do
    not fit one machine hold; each row says where it was trained (`trained_in`)."""

    def all_variants(self) -> List[str]:
        names = list(self.variants)
        if self.speed:
            names = [m for n in names for m in [n] + [split_variant(n)[0] + row for row in SPEED_ROWS]]
        return list(dict.fromkeys(names))

    def real(self) -> bool:
        """Whether the scene is a real capture (trained with the `-real` methods)."""
        from garo_ns.tools.eval import is_dnerf_scene

        return not is_dnerf_scene(self.scene)

    def full_schedule(self) -> int:
        """The methods' own number of steps on this scene."""
        from garo_ns.config import REAL_ITERATIONS

        return REAL_ITERATIONS if self.real() else FULL_ITERATIONS

    def steps(self) -> int:
        """The steps every variant trains."""
        return self.full_schedule() if self.iterations is None else self.iterations

    def trained_variants(self) -> List[str]:
        """The variants that need a training of their own."""
        return list(dict.fromkeys(split_variant(n)[0] for n in self.all_variants()))


# ---------------------------------------------------------------------------- training (one variant)
class _Deadline(Exception):
    pass


def train_variant(args: BenchArgs, name: str, deadline: Optional[float]) -> Dict[str, Any]:
    """Train one variant in this process; returns its training record (also written to run dir)."""
    import torch
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from garo_ns.tools.train import QuickSchedule, make_config, setup_trainer

    method, overrides = variant_settings(name)
    if args.real():
        method += "-real"
    config = make_config(
        method,  # type: ignore[arg-type]
        args.scene,
        args.work_dir,
        device=args.device,
        schedule=QuickSchedule(steps=args.steps()) if args.quick else None,
        alpha_color=args.background,
        eval_split="val" if args.split == "val" else "test",
        experiment_name=name,
    )
    config.timestamp = "bench"
    config.max_num_iterations = args.steps()
    config.steps_per_save = min(2000, args.steps())
    for key, value in overrides.items():
        setattr(config.pipeline.model, key, value)
    config.logging.local_writer.enable = True  # progress lines in the worker's log
    trainer = setup_trainer(config)  # seeded as ns-train seeds: the same initial Gaussians in every variant
    last_step = {"step": 0}

    def watch(step: int) -> None:
        last_step["step"] = step
        if deadline is not None and time.time() > deadline and step % 100 == 99:
            raise _Deadline

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], watch))
    if args.device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    stopped = False
    try:
        trainer.train()
    except _Deadline:
        stopped = True
        trainer.save_checkpoint(last_step["step"])
    seconds = time.perf_counter() - start
    iterations = last_step["step"] + 1
    health = getattr(trainer.pipeline.model, "health_log", [])
    record = {
        "variant": name,
        "method": method,
        "overrides": overrides,
        "iterations": iterations,
        "stopped_by_deadline": stopped,
        "train_seconds": seconds,
        "train_steps_per_second": iterations / seconds,
        "train_peak_memory_mb": torch.cuda.max_memory_allocated() / 2**20 if args.device == "cuda" else None,
        # What the caching allocator held at most: what a smaller GPU must have, beyond the tensors themselves.
        "train_peak_reserved_mb": torch.cuda.max_memory_reserved() / 2**20 if args.device == "cuda" else None,
        "config": str(config.get_base_dir() / "config.yml"),
        # A collapsed deformation field renders the scene as static: such an arm is no comparison.
        "deformation_collapsed": any(h["collapsed"] for h in health),
        "deformation_health": health[-1] if health else None,
    }
    (args.work_dir / f"{name}.record.json").write_text(json.dumps(record, indent=2))
    if args.export_dir is not None:
        transfer.export_run(record, environment(args.device), args.export_dir / name)
    return record


# ---------------------------------------------------------------------------- evaluation and timing
def evaluate_variant(args: BenchArgs, record: Dict[str, Any], names: List[str]) -> Dict[str, Dict[str, Any]]:
    """Score and time a trained variant (alone on its device) under each render setting in `names`."""

    from garo_ns.bench.frame_profile import profile_frame
    from garo_ns.compaction.report import summary_for_json
    from garo_ns.render.static import sample_times
    from garo_ns.state import storage
    from garo_ns.tools.eval import apply_model_settings, evaluate, load_run, model_overrides, split_views
    from garo_ns.tools.eval import train_times as scene_train_times
    from garo_ns.tools.fps import measure_fps, measure_same_time, model_size_mb, synchronize

    started = time.perf_counter()
    _, pipeline, _, step = load_run(Path(record["config"]), settings=model_overrides(args.model_set))
    model = pipeline.model
    apply_model_settings(model, args.model_set)
    synchronize(model.device)
    load_s = time.perf_counter() - started  # as garo-eval's: the checkpoint read, the model and its time table built
    views = split_views(pipeline, args.scene, args.split)
    cameras = views[0]
    all_train_times = scene_train_times(pipeline, args.scene)
    train_times = sample_times(all_train_times, model.config.static_times)  # as training samples them
    trained_threshold = model.config.static_threshold
    if model.static_fraction() is None:  # a checkpoint from before the classification existed
        model.refresh_static(train_times)
    if args.remeasure_switches:
        from garo_ns.compaction.guard import TrainingViewGuard

        model.train_times = all_train_times
        guard = TrainingViewGuard.from_datamanager(pipeline.datamanager, model.config.switch_views)
        print(model.switches.measure_on_training_views(model, guard, int(step)), flush=True)
        print(model.switches.line(model.config, False, model.device), flush=True)
    results = {}
    original = storage.snapshot(model)
    state: Dict[str, Any] = {"classified_at": trained_threshold, "rounded": False, "compact_mb": None}

    def score(name: str) -> Dict[str, Any]:
        settings = dict(split_variant(name)[1])
        half = settings.pop("storage") == "fp16"
        if half != state["rounded"]:  # parameters as the compact file holds them, or back to the trained ones
            if half:
                state["compact_mb"] = storage.round_to_storage(model) / 2**20
            else:
                storage.restore(model, original)
            state["rounded"] = half
            state["classified_at"] = None  # the field changed: classify again from it
        # A static switch (or +auto) classifies where training left it, again after the parameters changed.
        if settings["static_skip"] is not False and trained_threshold != state["classified_at"]:
            model.config.static_threshold = trained_threshold
            model.refresh_static(train_times)
            state["classified_at"] = trained_threshold
        for key, value in settings.items():
            setattr(model.config, key, value)
        result = evaluate(pipeline, args.scene, args.split, views)
        timing = measure_fps(model, cameras, warmup=args.warmup_views, repeats=args.timing_repeats)
        out = {
            **{k: result[k] for k in ("psnr", "psnr_per_view", "ssim", "lpips", "num_gaussians")},
            **{k: timing[k] for k in ("fps", "ms_per_view", "ms_deformation", "ms_rasterization")},
            "ms_per_view_same_time": measure_same_time(model, cameras),
            "static_fraction": model.static_fraction(),
            "render_settings": {**settings, "static_threshold": model.config.static_threshold, "storage_fp16": half},
            # The switches the frame path used: the row's own, or with +auto the model's choice.
            "render_switches_used": asdict(model.render_settings()),
            "time_table": model.frame.table_info if model.render_settings().time_table else None,
            "switch_record": {k: v for k, v in (model.switches.record or {}).items() if k != "views"},
            "peak_memory_mb": {
                "training": record["train_peak_memory_mb"],
                "training_reserved": record.get("train_peak_reserved_mb"),  # absent from older exports' records
                "rendering": timing["render_peak_memory_mb"],
            },
            "model_size_mb": state["compact_mb"] if half else model_size_mb(model),
            "storage": "fp16 (positions fp32)" if half else "fp32",
            **{k: record[k] for k in ("train_seconds", "train_steps_per_second", "iterations", "stopped_by_deadline")},
            "shortened": record["iterations"] < args.full_schedule(),
            "deformation_collapsed": record.get("deformation_collapsed"),
            **{k: getattr(model.config, k) for k in ("garo_mode", "rho_max", "prune_contribution_ratio")},
            "compaction": summary_for_json(model.strategy_state.get("compact")),
            "checkpoint_step": int(step),
            # Load to first frame (issue 70's load_s): the loaded model's, then this row's first view.
            "load_seconds": load_s,
            "first_frame_seconds": result["first_frame_seconds"],
            # Where this arm trained: this run, or (imported with --pretrained) an earlier run's machine and commit.
            "trained_in": record.get("trained_in", "this run"),
        }
        if args.profile:
            out["profile"] = profile_frame(model, cameras)
        if args.renders_dir is not None and "+" not in name:
            from garo_ns.bench.strip import save_views

            save_views(pipeline, args.scene, args.split, args.renders_dir, name, args.renders_views)
        return out

    for name in names:
        try:
            results[name] = score(name)
        except Exception as err:  # a failing render switch must not cost the rows already measured
            if "+" not in name:
                raise
            results[name] = {"error": f"{type(err).__name__}: {err}"}
            print(f"row {name} failed: {results[name]['error']}", flush=True)
    for name, row in results.items():
        plain = results.get(split_variant(name)[0])
        if "+" in name and "error" not in row and plain is not None and "error" not in plain:
            row["psnr_vs_plain"] = psnr_difference(row["psnr_per_view"], plain["psnr_per_view"])
    return results


def paired_timing(args: BenchArgs, records: Dict[str, Dict[str, Any]], names: List[str]) -> Dict[str, Dict[str, Any]]:
    """Every trained variant loaded at once and its plain render (fp32, no switches) timed in alternating
    passes over the split's views (garo_ns.bench.timing.paired_fps)."""
    from garo_ns.bench.timing import frame_pass, paired_fps
    from garo_ns.tools.eval import apply_model_settings, load_run, split_views

    frames, device = {}, None
    for name in names:
        _, pipeline, _, _ = load_run(Path(records[name]["config"]))
        model = pipeline.model
        apply_model_settings(model, args.model_set)
        settings = dict(split_variant(name)[1])
        settings.pop("storage")
        for key, value in settings.items():
            setattr(model.config, key, value)
        model.eval()
        cameras, _ = split_views(pipeline, args.scene, args.split)
        frames[name] = frame_pass(model, cameras)
        device = model.device
    timings = paired_fps(frames, device, passes=args.paired_passes)
    for timing in timings.values():
        timing["passes"] = args.paired_passes
    return timings


def psnr_difference(row: List[float], plain: List[float]) -> Dict[str, Any]:
    """A render-time row's PSNR minus its plain row's, view by view (dB): the largest difference either
    way, the mean, and every view's."""
    diff = [a - b for a, b in zip(row, plain)]
    return {
        "max_abs_db": max((abs(d) for d in diff), default=0.0),
        "mean_db": sum(diff) / len(diff) if diff else 0.0,
        "per_view_db": diff,
    }


# ---------------------------------------------------------------------------- report
def environment(device: str) -> Dict[str, Any]:
    """The machine (garo_ns.tools.fps.machine) and commit of this run."""
    from garo_ns.tools.fps import machine

    # GARO_GIT_COMMIT wins: on the GPU machine the project arrives as a copy whose git metadata
    # need not match the files.
    commit = os.environ.get("GARO_GIT_COMMIT")
    if not commit:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            commit = "unknown"
    return {
        **machine(device),
        "git_commit": commit,
        # Training processes sharing a GPU under CUDA MPS (benchmarks/device_run.sh starts it) run side by side;
        # timing happens after training, one arm at a time, either way.
        "cuda_mps": device == "cuda" and os.environ.get("GARO_MPS_ON") == "1",
    }


def write_report(result: Dict[str, Any], output: Path) -> Tuple[Path, Path]:
    """Markdown table and FPS-vs-PSNR plot next to the JSON."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = result["variants"]
    base = variants.get("deform-splatfacto")
    lines = [
        f"# {result['scene']} ({result['split']}, {result['background']} background) on {result['gpu'] or 'CPU'}",
        "",
        "| variant | iterations | PSNR | worst view vs plain | SSIM | LPIPS | FPS | speed-up | MLP ms | raster ms |"
        " Gaussians | static | model MB | train s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    failed = {n: v["error"] for n, v in variants.items() if "error" in v}
    variants = {n: v for n, v in variants.items() if "error" not in v}
    for name, v in variants.items():
        speed = f"{v['fps'] / base['fps']:.2f}x" if base else "-"
        lp = "-" if v["lpips"] is None else f"{v['lpips']:.4f}"
        static = v.get("static_fraction")
        static_txt = "-" if static is None or not v.get("render_settings", {}).get("static_skip") else f"{static:.0%}"
        vs_plain = f"{v['psnr_vs_plain']['max_abs_db']:.3f} dB" if "psnr_vs_plain" in v else "-"
        if v.get("deformation_collapsed"):
            name = f"{name} (deformation collapsed)"
        lines.append(
            f"| {name} | {v['iterations']} | {v['psnr']:.2f} | {vs_plain} | {v['ssim']:.4f} | {lp} | "
            f"{v['fps']:.1f} | {speed} | {v['ms_deformation']:.2f} | {v['ms_rasterization']:.2f} | "
            f"{v['num_gaussians']} | {static_txt} | {v['model_size_mb']:.2f} | {v['train_seconds']:.0f} |"
        )
    lines += [f"\nRow {n} failed: {e}" for n, e in failed.items()]
    paired = {n: v["fps_paired"] for n, v in variants.items() if "fps_paired" in v}
    if paired:
        base_paired = paired.get("deform-splatfacto")
        lines += [
            "",
            f"Timed again in {next(iter(paired.values()))['passes']} alternating passes, all variants loaded at "
            "once (median pass):",
            "",
            "| variant | FPS | speed-up |",
            "|---|---|---|",
        ]
        for n, t in paired.items():
            speed = f"{t['fps'] / base_paired['fps']:.2f}x" if base_paired else "-"
            lines.append(f"| {n} | {t['fps']:.1f} | {speed} |")
    elsewhere = {n: transfer.trained_elsewhere(v.get("trained_in")) for n, v in variants.items() if "+" not in n}
    lines += [
        f"\n{n} was trained by an earlier run ({where}) and imported: evaluated and timed in this run like the others."
        for n, where in elsewhere.items()
        if where is not None
    ]
    md = output.with_suffix(".md")
    md.write_text("\n".join(lines) + "\n")

    # Points are numbered and named in a legend beside the axes: with the speed rows, many
    # variants share a PSNR and their names would overprint each other.
    fig, ax = plt.subplots(figsize=(10, 4.8))
    counts = [v["num_gaussians"] for v in variants.values()]
    top = max(counts) if counts else 1
    for i, (name, v) in enumerate(variants.items(), start=1):
        ax.scatter(v["fps"], v["psnr"], s=40 + 800 * v["num_gaussians"] / top, alpha=0.6, label=f"{i}: {name}")
        ax.annotate(str(i), (v["fps"], v["psnr"]), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.set_xlabel("FPS (deformation + rasterization)")
    ax.set_ylabel(f"PSNR on {result['split']} (dB)")
    ax.set_title(f"{result['scene']}: marker area ~ number of Gaussians")
    ax.grid(alpha=0.3)
    if variants:
        legend = ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
        for handle in legend.legend_handles:
            handle.set_sizes([30])  # the legend names points; their size is in the axes
    return md, save_figure(fig, output)


# ---------------------------------------------------------------------------- driver
def physical_gpu(index: int) -> str:
    """The device a worker sees for our GPU `index`: indices count within this process's own
    CUDA_VISIBLE_DEVICES when it is set, so two benchmarks given disjoint sets never share a GPU,
    and each evaluates on the first GPU of its own set."""
    visible = [d.strip() for d in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if d.strip()]
    if not visible:
        return str(index)
    if not 0 <= index < len(visible):
        raise ValueError(f"--gpus {index} is not among the {len(visible)} visible devices {visible}")
    return visible[index]


def train_arms(args: BenchArgs, names: List[str], deadline: Optional[float]) -> List[str]:
    """Train `names` in worker processes, at most `args.arms_per_gpu` on a GPU at a time (0: all at once), each
    placed on the GPU of `args.gpus` with the fewest arms; on a CPU one after another (they would only compete for
    the same cores). Returns `names` once every arm has ended; raises naming the first that failed."""
    args_json = json.dumps(vars(args), default=str)
    places = arms_per_gpu(args, len(names))
    pending, running, failed = list(names), [], []
    load = {g: 0 for g in args.gpus}
    while pending or running:
        while pending and min(load.values()) < places:
            gpu = min(args.gpus, key=lambda g: load[g])  # the first of the least loaded, as round-robin does
            name = pending.pop(0)
            env = dict(os.environ)
            if args.device == "cuda":
                env["CUDA_VISIBLE_DEVICES"] = physical_gpu(gpu)
            log = open(args.work_dir / f"{name}.log", "w")
            cmd = [sys.executable, "-m", "garo_ns.bench.benchmark", "--worker", name, "--args", args_json]
            if deadline is not None:
                cmd += ["--deadline", str(deadline)]
            running.append((name, gpu, subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log))
            load[gpu] += 1
            print(f"training {name}" + (f" on GPU {gpu}" if args.device == "cuda" else ""), flush=True)
        time.sleep(0.05 if args.device != "cuda" else 2.0)
        for name, gpu, proc, log in [r for r in running if r[2].poll() is not None]:
            running.remove((name, gpu, proc, log))
            log.close()
            load[gpu] -= 1
            if proc.returncode != 0:
                failed.append(f"training {name} failed (exit {proc.returncode}); see {args.work_dir / (name + '.log')}")
    if failed:
        raise RuntimeError(failed[0])
    return names


def arms_per_gpu(args: BenchArgs, arms: int) -> int:
    """How many arms trained on one GPU at once (1: each alone; on a CPU they train one after another)."""
    if args.device != "cuda" or arms == 0:
        return min(arms, 1)
    most = -(-arms // len(args.gpus))  # all at once, round-robin
    return min(args.arms_per_gpu, most) if args.arms_per_gpu > 0 else most


def run(args: BenchArgs) -> Dict[str, Any]:
    """Phase 1 (training, parallel) then phase 2 (evaluation and timing, sequential); write outputs."""
    from garo_ns.tools.eval import model_overrides
    from garo_ns.tools.fps import protocol

    names = args.trained_variants()
    for name in args.all_variants():
        check_variant(name)
    model_overrides(args.model_set, "--model-set")  # an unknown setting refused before anything trains
    deadline = None if args.deadline_s is None else time.time() + args.deadline_s
    args.work_dir.mkdir(parents=True, exist_ok=True)
    imported = {}
    for export in args.pretrained:  # before any training: a wrong export fails at once, not after an hour
        record = transfer.import_run(export, args.work_dir, args.scene)
        if record["variant"] not in names:
            raise ValueError(f"{export} holds {record['variant']!r}, which this run does not evaluate ({names})")
        if record["iterations"] != args.steps():
            raise ValueError(f"{export} trained {record['iterations']} steps, this run {args.steps()}")
        imported[record["variant"]] = record
    records = dict(imported)
    trained = [n for n in names if n not in imported]
    for name in train_arms(args, trained, deadline):
        records[name] = json.loads((args.work_dir / f"{name}.record.json").read_text())
    variants: Dict[str, Dict[str, Any]] = {}
    everything = args.all_variants()
    for name in names:
        rows = evaluate_variant(args, records[name], [n for n in everything if split_variant(n)[0] == name])
        # Each trained variant's rows as soon as they are measured: a run cut short keeps what it finished.
        (args.work_dir / f"{name}.eval.json").write_text(json.dumps(rows, indent=1, default=str))
        variants.update(rows)
    paired_error = None
    if args.paired_passes > 0:
        try:
            for name, timing in paired_timing(args, records, names).items():
                variants[name]["fps_paired"] = timing
        except Exception as err:  # the extra timing must not cost the rows already measured
            paired_error = f"{type(err).__name__}: {err}"
            print(f"paired re-timing failed: {paired_error}", flush=True)
    variants = {n: variants[n] for n in everything}
    result = {
        **environment(args.device),
        "scene": args.scene.name,
        "split": args.split,
        "background": args.background,
        "iterations_full_schedule": args.full_schedule(),
        "model_settings": args.model_set,
        "fps_protocol": protocol(args.warmup_views, args.timing_repeats),
        # How many of this run's arms trained on one GPU at once: 1 makes each train_seconds a lone run's.
        "arms_per_gpu": arms_per_gpu(args, len(trained)),
        "variants": variants,
    }
    if paired_error is not None:
        result["paired_timing_error"] = paired_error
    base = variants.get("deform-splatfacto")
    garo = variants.get("garo-deform")
    if base and garo:
        result["garo_vs_baseline"] = {
            "fps_ratio": garo["fps"] / base["fps"],
            "psnr_drop_db": base["psnr"] - garo["psnr"],
            "gaussian_ratio": garo["num_gaussians"] / max(base["num_gaussians"], 1),
        }
        if "fps_paired" in base and "fps_paired" in garo:
            result["garo_vs_baseline"]["fps_ratio_paired"] = garo["fps_paired"]["fps"] / base["fps_paired"]["fps"]
    publish(result, args.output, write_report)
    return result


def _from_json(d: Dict[str, Any]) -> BenchArgs:
    """The worker's arguments from `json.dumps(vars(args), default=str)`: every path field a Path again."""
    for f in fields(BenchArgs):
        if f.type == "List[Path]":
            d[f.name] = [Path(p) for p in d[f.name]]
        elif "Path" in f.type and d[f.name] is not None:
            d[f.name] = Path(d[f.name])
    return BenchArgs(**d)


def main() -> None:
    """Console entry point (also the worker entry, used internally)."""
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        name = sys.argv[2]
        args = _from_json(json.loads(sys.argv[sys.argv.index("--args") + 1]))
        deadline = float(sys.argv[sys.argv.index("--deadline") + 1]) if "--deadline" in sys.argv else None
        train_variant(args, name, deadline)
        return
    import tyro

    run(tyro.cli(BenchArgs))


if __name__ == "__main__":
    main()
