"""`garo-demo`: the main job on the built-in dynamic scene.

Writes the built-in scene, trains `garo-deform` and the baseline `deform-splatfacto` on it with the same
compressed schedule (CPU, or CUDA when present), and sets them side by side: test PSNR, Gaussians, model
size and render time, as a table (`demo_results.md`, `demo_results.json`), a strip of test renders over time
next to the ground truth (`demo_strip.png`) and the speed-against-error plot (`demo_speed_error.png`).

On a CPU with a core per arm the arms train at once, each in its own single-thread process: the demo's
tensors are too small for a second thread to help one arm, so two processes finish in about the time of one.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

from garo_ns import compat
from garo_ns.deformation import ScaleOffset

compat.install()

Method = Literal["garo-deform", "deform-splatfacto"]


@dataclass
class DemoArgs:
    """Train garo-deform and the baseline on the built-in dynamic scene and set them side by side."""

    output_dir: Path = Path("runs/demo")
    """Where the scene, the runs and the results go."""
    steps: int = 2000
    """Training steps of each arm (the full recipe is 40k; this compresses its phases, every one of them, the
    learning-rate decays included, scaled with the step count)."""
    resolution: int = 48
    """Scene resolution in pixels (most of the remaining error lies on the floor's edges, which a finer
    pixel sharpens)."""
    methods: Tuple[Method, ...] = ("garo-deform", "deform-splatfacto")
    """The arms to train, in this order."""
    device: Optional[Literal["cpu", "cuda"]] = None
    """Default: cuda when available."""
    parallel: Optional[bool] = None
    """Train the arms at once, each in its own process (the first shows its progress, the others log it to
    their run folder). Default: on a CPU with at least a core per arm."""
    strip_frames: int = 6
    """Test views in the picture, ordered by time."""
    n_train: int = 60
    """Training views of the generated scene (one per training time; they cost no time per step)."""
    n_test: int = 6
    """Test views of the generated scene."""
    n_val: int = 2
    """Validation views of the generated scene (the demo does not use them)."""
    ground_squares: int = 2
    """Checker squares along each side of the floor (the library's default scene has 9.6: 4 per unit)."""
    sphere_stripes: int = 2
    """Coloured stripes around the ball (the library's default scene has 8)."""
    box_turns: float = 0.0
    """Turns of the box about the vertical axis (the library's default scene: half a turn). The demo's box
    slides instead: in this schedule the deformation field does not learn the turn of the box's differently
    coloured faces, whose colours average out to grey (at 32 px after 2000 steps the box's pixels of the
    training views scored 21 dB turning, 28 dB sliding; neither a 6x128 field, a shorter static warm-up nor
    48 px learned the turn)."""
    box_slide: float = 0.6
    """Scene units the box slides over the sequence (the library's default scene: 0)."""
    ball_turns: float = 0.0
    """Turns of the ball's stripes about the vertical axis (the library's default scene: 1.25). At 0 the ball
    travels and hops with its stripes fixed, a motion the field learns in the demo's schedule (the ball's
    pixels of the training views: 24 dB with the stripes turning, 29 dB fixed, at 32 px after 2000 steps)."""
    num_random: int = 500
    """Random Gaussians the scene starts from."""
    deform_width: int = 64
    """Width of the deformation MLP."""
    deform_depth: int = 4
    """Depth of the deformation MLP."""
    deform_skip: int = 2
    """Layer of the deformation MLP that takes its input again."""
    deform_lr: float = 5e-3
    """Learning rate of the deformation MLP, held through the static warm-up, then decaying 100x."""
    deform_warmup_frac: float = 0.25
    """Share of the steps trained static before the deformation field switches on."""
    deform_head_init: Literal["zero", "default"] = "default"
    """Initial heads of the deformation MLP. With "zero" (QuickSchedule's) the field collapsed in 800-step trials
    on this scene (its last layer died after the switch-on; the ball and box rendered as static blurs)."""
    means_lr_scale: float = 20.0
    """Factor on D-3DGS's position learning rate (tuned for 30k steps)."""
    color_lr_scale: float = 4.0
    """Factor on D-3DGS's colour learning rates (SH coefficients)."""
    scales_lr_scale: float = 2.0
    """Factor on D-3DGS's scale learning rate."""
    densify_grad_thresh: float = 0.002
    """Densification's gradient threshold (a higher one keeps the Gaussians, and the CPU time per step, fewer)."""
    static_threshold: Optional[float] = None
    """Static threshold as a share of the scene extent. Default: the model's 2.5e-4 scaled by 800 / resolution,
    the same fraction of a pixel as the default at 800 px (the D-NeRF size)."""
    deform_scale_offset: ScaleOffset = "log"
    """How both arms compose the field's scale offset with a scale: `log` (the model's default) for both, so that the
    demo compares GARO with the same model without it. Both methods train with `linear` (the official code's, which
    matches it at 40k on D-NeRF), but on this schedule `linear` scored 0.3 to 0.9 dB below `log` in each of three
    seeds (`benchmarks/demo_ab.py` at 7997206, benchmarks/results/demo_scale_term_cpu.json)."""


def scene_spec(args: DemoArgs) -> Any:
    """The built-in scene the demo trains on: the library's scene with its floor and ball textures coarser,
    its box sliding instead of turning and its ball's stripes carried without turning."""
    from garo_ns.tools.scene import GROUND_HALF, SceneSpec

    return SceneSpec(
        resolution=args.resolution,
        n_train=args.n_train,
        n_val=args.n_val,
        n_test=args.n_test,
        checks_per_unit=args.ground_squares / (2 * GROUND_HALF),
        sphere_stripes=args.sphere_stripes,
        box_turns=args.box_turns,
        box_slide=args.box_slide,
        ball_turns=args.ball_turns,
    )


def static_threshold(args: DemoArgs) -> float:
    """The static threshold the demo trains with (share of the scene extent)."""
    return args.static_threshold if args.static_threshold is not None else 2.5e-4 * 800 / args.resolution


def demo_scene(args: DemoArgs, out: Path) -> Path:
    """The built-in scene under `out`, named by its settings; written unless it is already there."""
    from garo_ns.tools.scene import generate_scene

    out.mkdir(parents=True, exist_ok=True)
    scene = out / (
        f"scene_{args.resolution}px_{args.n_train}x{args.n_val}x{args.n_test}"
        f"_{args.ground_squares}sq_{args.sphere_stripes}st"
        f"_box{args.box_turns:g}t{args.box_slide:g}s_ball{args.ball_turns:g}t"
    )
    if not (scene / "transforms_test.json").exists():
        generate_scene(scene, scene_spec(args))
        print(f"wrote the built-in scene to {scene}")
    return scene


def demo_config(args: DemoArgs, method: Method, scene: Path, out: Path, device: str) -> Any:
    """The training config of one arm: `method`'s recipe on the demo's compressed schedule."""
    from garo_ns.tools.train import DemoSchedule, make_config

    schedule = DemoSchedule(
        steps=args.steps,
        num_random=args.num_random,
        deform_width=args.deform_width,
        deform_depth=args.deform_depth,
        deform_skip=args.deform_skip,
        deform_lr=args.deform_lr,
        deform_warmup_frac=args.deform_warmup_frac,
        lr_scale={
            "means": args.means_lr_scale,
            "features_dc": args.color_lr_scale,
            "features_rest": args.color_lr_scale,
            "scales": args.scales_lr_scale,
        },
        extra={
            "densify_grad_thresh": args.densify_grad_thresh,
            "static_threshold": static_threshold(args),
            "deform_head_init": args.deform_head_init,
            "deform_scale_offset": args.deform_scale_offset,
        },
    )
    return make_config(method, scene, out, device=device, schedule=schedule, experiment_name=method)


def train_arm(
    args: DemoArgs, method: Method, scene: Path, out: Path, device: str, turn: Optional[Tuple[Any, Any]] = None
) -> Dict[str, Any]:
    """Train one arm with nerfstudio's trainer (progress lines shown) and measure it; returns its figures. `turn`
    (a barrier of every arm and a lock), for arms trained at once: the render is timed once no arm trains any more,
    one arm at a time, so that no arm's time includes another's training."""
    from garo_ns.tools.eval import evaluate, load_split
    from garo_ns.tools.fps import measure_fps, model_size_mb
    from garo_ns.tools.strip import views_over_time
    from garo_ns.tools.train import train

    config = demo_config(args, method, scene, out, device)
    config.logging.local_writer.enable = True  # nerfstudio's own progress output
    config.logging.steps_per_log = max(args.steps // 20, 1)
    start = time.perf_counter()
    trainer = train(config)
    seconds = time.perf_counter() - start
    model = trainer.pipeline.model
    cameras, images = load_split(scene, "test", model.background_color)
    result = evaluate(trainer.pipeline, scene, "test", (cameras, images))
    if turn is None:
        timing = measure_fps(model, cameras, warmup=1, repeats=1)
    else:
        barrier, lock = turn
        try:
            barrier.wait()  # every arm has trained
        except threading.BrokenBarrierError:  # another arm failed (the parent broke the barrier): time now
            pass
        with lock:
            timing = measure_fps(model, cameras, warmup=1, repeats=1)
    result.update(
        {
            "method": method,
            "iterations": args.steps,
            "train_seconds": seconds,
            "device": device,
            "rasterizer": "gsplat (CUDA)" if device == "cuda" else "reference (pure torch)",
            "render_ms": timing["ms_per_view"],
            "fps": timing["fps"],
            "model_mb": model_size_mb(model),
            "static_fraction": model.static_fraction(),
            "floor": floor_check(model, args.resolution, args.box_slide),
            "run_dir": str(config.get_base_dir()),
            "config": str(config.get_base_dir() / "config.yml"),
        }
    )
    (config.get_base_dir() / "eval_test.json").write_text(json.dumps(result, indent=2))
    result["_frames"] = views_over_time(trainer.pipeline, scene, "test", args.strip_frames)[1:]
    return result


def floor_check(model: Any, resolution: int, box_slide: float = 0.0) -> Optional[Dict[str, Any]]:
    """How the static classification treats the built-in scene's floor, which never moves.

    Floor Gaussians: those lying on the ground plane (within 0.03 of it) away from where the ball and the box
    ever touch it (`box_slide` as in the scene). Returns their number, the share classified static, the
    threshold and their median frozen-offset displacement (scene units and pixels of the test views), or None
    for a model without a static classification (the baseline).
    """
    import math

    import numpy as np
    import torch

    from garo_ns.render.static import displacement, motion_statistics
    from garo_ns.tools import scene as S

    static = model.strategy_state.get("static") if hasattr(model, "strategy_state") else None
    if not isinstance(static, torch.Tensor) or static.shape[0] != model.num_points:
        return None
    with torch.no_grad():
        means = model.means.detach()
        xyz = means.cpu().numpy()
        when = np.linspace(0, 1, 101)
        path = np.array([S.sphere_center(t)[:2] for t in when])
        to_ball = np.linalg.norm(xyz[:, None, :2] - path[None], axis=-1).min(axis=1)
        box_path = np.array([S.box_center(t, box_slide)[:2] for t in when])
        to_box = np.linalg.norm(xyz[:, None, :2] - box_path[None], axis=-1).min(axis=1)
        on_floor = (
            (np.abs(xyz[:, 2] - S.GROUND_Z) < 0.03)
            & (np.abs(xyz[:, :2]).max(axis=1) <= S.GROUND_HALF)
            & (to_ball > S.SPHERE_RADIUS + 0.15)
            & (to_box > S.BOX_HALF * math.sqrt(2) + 0.1)
        )
        idx = torch.from_numpy(np.nonzero(on_floor)[0]).to(means.device)
        if idx.numel() == 0:
            return {"floor_gaussians": 0}
        times = torch.linspace(0.0, 1.0, model.config.static_times)
        log_scales = model.scales.detach()[idx]
        deviation, mean = motion_statistics(
            model.deformation, means[idx], times, log_scales=log_scales, scale_offset=model.config.deform_scale_offset
        )
        size = torch.exp(log_scales + mean[:, 7:]).amax(dim=-1)
        move = displacement(deviation, size).float().cpu()
    threshold = model.config.static_threshold * model.scene_extent
    pixel = S.CAMERA_RADIUS * 2 * math.tan(0.5 * S.CAMERA_ANGLE_X) / resolution
    median = float(move.median())
    return {
        "floor_gaussians": int(idx.numel()),
        "floor_static_fraction": float(static[idx.to(static.device)].float().mean()),
        "static_threshold": threshold,
        "floor_median_move": median,
        "floor_median_move_px": median / pixel,
        "threshold_px": threshold / pixel,
    }


def floor_sentence(check: Optional[Dict[str, Any]]) -> str:
    """One line on whether the floor was classified static, and why not where it was not."""
    if not check or not check.get("floor_gaussians"):
        return "floor: no Gaussians found on the floor away from the moving objects"
    share = check["floor_static_fraction"]
    line = f"floor: {share:.0%} of its {check['floor_gaussians']:,} Gaussians (away from the ball and box)"
    line += " classified static (the floor never moves, so ideally all of them)"
    if share < 0.9:
        line += (
            f"; held at their average position, the floor's Gaussians would move by {check['floor_median_move']:.2g} "
            f"scene units ({check['floor_median_move_px']:.2f} px in the test views; median over the floor) "
            f"against a static threshold of {check['static_threshold']:.2g} ({check['threshold_px']:.3f} px): "
            "the deformation network still nudges the floor a little over time, and a Gaussian it moves by more "
            "than the threshold is not static"
        )
    return line


def write_strip(arms: List[Dict[str, Any]], path: Path) -> Path:
    """A PNG (garo_ns.tools.strip.draw_strip): ground truth in the first row, each arm's renders below, test views
    left to right by time (each arm's `_frames`: times, ground truths and renders from `views_over_time`)."""
    from garo_ns.tools.strip import draw_strip

    times, truths, _ = arms[0]["_frames"]
    rows = [("ground truth", truths)] + [(f"{a['method']}\n{a['psnr']:.2f} dB", a["_frames"][2]) for a in arms]
    return draw_strip(rows, times, path, "Built-in scene, test views over time")


def write_speed_error_plot(arms: List[Dict[str, Any]], path: Path) -> Path:
    """A PNG of render time against test PSNR, one point per arm."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6))
    for arm in arms:
        ax.scatter(arm["render_ms"], arm["psnr"], s=60)
        ax.annotate(
            f"{arm['method']}\n{arm['num_gaussians']:,} Gaussians",
            (arm["render_ms"], arm["psnr"]),
            textcoords="offset points",
            xytext=(6, 4),
            fontsize=8,
        )
    ax.set_xlabel(f"render time per test view, ms ({arms[0]['rasterizer']})")
    ax.set_ylabel("test PSNR, dB")
    ax.ticklabel_format(useOffset=False)
    ax.grid(alpha=0.3)
    ax.margins(0.35)
    # At least 2 dB of PSNR axis with 0.1 dB ticks: arms a few hundredths of a dB apart look alike, as they are.
    low, high = psnr_axis([arm["psnr"] for arm in arms])
    ax.set_ylim(low, high)
    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.1f"))
    ax.annotate(
        "better: up and left\n(sharper, faster)",
        xy=(0.02, 0.97),
        xycoords="axes fraction",
        va="top",
        fontsize=8,
        color="0.35",
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def psnr_axis(values: List[float], min_span: float = 2.0) -> Tuple[float, float]:
    """Limits of a PSNR axis (dB) around `values`: their range with a margin, and at least `min_span` wide."""
    low, high = min(values), max(values)
    pad = max((min_span - (high - low)) / 2, 0.35 * (high - low))
    return low - pad, high + pad


def resume_command(method: str, config_path: Path, scene: Path, steps: int = 1000) -> str:
    """The `ns-train` command that resumes a demo arm's run (its config.yml) for `steps` more steps: with the settings
    that shape its tensors where they are not the method's (the demo's field is smaller), the rest of the recipe
    the method's own from the arm's last step on."""
    import yaml

    from garo_ns.config import METHODS
    from garo_ns.state.checkpoints import as_flags, shape_settings

    trained = yaml.load(Path(config_path).read_text(), Loader=yaml.Loader).pipeline.model
    flags = as_flags(shape_settings(trained, METHODS[method].config.pipeline.model))
    models = Path(config_path).parent / "nerfstudio_models"
    return (
        f"{shell_command('ns-train')} {method} --data {scene} {flags} --load-dir {models} --max-num-iterations {steps}"
    )


def shell_command(name: str) -> str:
    """How to call the console script `name` of this environment from the current folder: its bare name when the
    shell finds this environment's copy (an activated venv), else its path (e.g. `.venv/bin/ns-viewer`)."""
    import shutil
    import sys

    local = Path(sys.executable).parent / name
    found = shutil.which(name)
    if not local.exists() or (found is not None and Path(found).resolve() == local.resolve()):
        return name
    try:
        return str(local.relative_to(Path.cwd()))
    except ValueError:
        return str(local)


def results_table(arms: List[Dict[str, Any]]) -> str:
    """The side-by-side Markdown table."""
    lines = [
        "| method | test PSNR | SSIM | Gaussians | model MB | render ms/view | static | train s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for a in arms:
        static = "-" if a["static_fraction"] is None else f"{a['static_fraction']:.0%}"
        lines.append(
            f"| {a['method']} | {a['psnr']:.2f} | {a['ssim']:.4f} | {a['num_gaussians']:,} | {a['model_mb']:.2f} | "
            f"{a['render_ms']:.1f} | {static} | {a['train_seconds']:.0f} |"
        )
    return "\n".join(lines)


def figure_notes(arms: List[Dict[str, Any]], args: DemoArgs) -> str:
    """What each figure of the table (and the end-of-training lines) means, in words."""
    rasterizer = arms[0]["rasterizer"] if arms else "the"
    views = arms[0]["n_images"] if arms else args.n_test
    return "\n".join(
        [
            "What the figures mean:",
            f"- test PSNR (dB): how closely the renders of the {views} test views (views never used in training) "
            "match the true images; higher is better, and 1 dB more means about 20% less squared error.",
            "- SSIM: similarity of structure to the true images, from 0 to 1 (identical).",
            "- Gaussians: the 3D Gaussians in the finished model; fewer render faster and take less memory. "
            "Both remove transparent or oversized ones; garo-deform also removes redundant ones (GARO).",
            "- model MB: size of the model's parameters (the Gaussians and the deformation network).",
            f"- render ms/view: time to render one test view at {args.resolution} px with the {rasterizer} rasterizer, "
            "deforming the Gaussians to the view's time included; lower is faster.",
            "- static: share of the Gaussians that the deformation network barely moves (less than "
            "the static threshold); a finished model may skip the network for them.",
            "- train s: how long the training took.",
            "- 'Render switches on N training views (PSNR loss against plain): static_skip X dB', printed at the end "
            "of training: how much PSNR the worst of those training views would lose if the static Gaussians "
            "skipped the deformation network (and, on a GPU, with a faster network precision); a finished model "
            "turns such a switch on only when that loss is tiny (switch-bound-db, 0.02 dB by default).",
        ]
    )


def _arm_process(
    args: DemoArgs, method: Method, scene: Path, out: Path, device: str, log: Optional[Path], turn: Tuple[Any, Any]
) -> None:
    """One arm in a process of its own: train and measure it, and leave its figures and strip frames in
    `out/<method>/arm.pt` for the parent. With `log`, its output goes there instead of the terminal."""
    import resource

    import torch

    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "w") as sink:  # the descriptors themselves, so that rich's console follows
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
    torch.set_num_threads(1)  # one core per arm (see the module docstring)
    result = train_arm(args, method, scene, out, device, turn)
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    torch.save(result, out / method / "arm.pt")


def train_arms_at_once(args: DemoArgs, scene: Path, out: Path, device: str) -> List[Dict[str, Any]]:
    """Train every arm at the same time, each in a spawned process; returns their figures in `args.methods`'
    order. The first arm shows nerfstudio's progress lines, the others write theirs to `<method>/train.log`."""
    import multiprocessing

    import torch

    context = multiprocessing.get_context("spawn")  # a fresh interpreter: no torch threads inherited by fork
    processes = []
    turn = (context.Barrier(len(args.methods)), context.Lock())  # renders timed after training, one at a time
    for k, method in enumerate(args.methods):
        log = None if k == 0 else out / method / "train.log"
        if log is not None:
            print(f"{method} trains at the same time; its progress goes to {log}")
        (out / method / "arm.pt").unlink(missing_ok=True)
        process = context.Process(target=_arm_process, args=(args, method, scene, out, device, log, turn))
        process.start()
        processes.append(process)
    for k, (method, process) in enumerate(zip(args.methods, processes)):
        process.join()
        if process.exitcode != 0:
            turn[0].abort()  # the arms still waiting to time their renders go on
            where = "its output above" if k == 0 else out / method / "train.log"
            raise RuntimeError(f"training {method} failed (exit status {process.exitcode}); see {where}")
    return [torch.load(out / method / "arm.pt", weights_only=False) for method in args.methods]


def run(args: DemoArgs) -> Dict[str, Any]:
    """Generate the scene, train every arm, write the table, the strip and the plot; returns the results."""
    import resource

    import torch

    start = time.perf_counter()
    out = args.output_dir.resolve()
    scene = demo_scene(args, out)
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    parallel = args.parallel
    if parallel is None:
        parallel = device == "cpu" and len(args.methods) > 1 and (os.cpu_count() or 1) >= len(args.methods)
    if parallel:
        arms = train_arms_at_once(args, scene, out, device)
    else:
        arms = [train_arm(args, method, scene, out, device) for method in args.methods]
    strip = write_strip(arms, out / "demo_strip.png")
    plot = write_speed_error_plot(arms, out / "demo_speed_error.png")
    table = results_table(arms)
    floors = [f"{a['method']} {floor_sentence(a['floor'])}." for a in arms if a.get("floor") is not None]
    if floors:
        table += "\n\n" + "\n".join(floors)
    table += "\n\n" + figure_notes(arms, args)
    public = [{k: v for k, v in a.items() if not k.startswith("_")} for a in arms]
    summary = {"scene": str(scene), "resolution": args.resolution, "steps": args.steps, "device": device}
    summary["args"] = {
        k: (str(v) if isinstance(v, Path) else list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items()
    }
    summary["parallel"] = parallel
    summary["wall_seconds"] = time.perf_counter() - start
    # Linux reports KiB. Arms trained at once hold their memory at the same time, so their peaks add up
    # (an upper bound: the peaks need not coincide).
    summary["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if parallel:
        summary["peak_rss_mb"] += sum(a["peak_rss_mb"] for a in arms)
    summary["arms"] = public
    (out / "demo_results.json").write_text(json.dumps(summary, indent=2))
    (out / "demo_results.md").write_text(
        f"Built-in scene, {args.resolution} px, {args.steps} steps per arm, {device}.\n\n{table}\n"
    )
    print(f"\nBuilt-in scene ({args.resolution} px, {args.steps} steps per arm, {device}):\n\n{table}\n")
    print(f"picture:  {strip}  (test views over time: the true images on top, each method's renders below)")
    print(f"plot:     {plot}  (render time per view against test PSNR, one point per method)")
    print(f"results:  {out / 'demo_results.json'}  (every figure above, per test view too)")
    memory = "the sum of the processes' peaks, an upper bound" if parallel else "the largest the process held"
    print(f"took {summary['wall_seconds'] / 60:.1f} min; peak memory {summary['peak_rss_mb']:.0f} MB ({memory})")
    viewer, scorer = shell_command("ns-viewer"), shell_command("garo-eval")
    print("open a trained model in the viewer (time slider in its Control tab), or score it:")
    for a in public:
        print(f"{a['method']}: {viewer} --load-config {a['config']} --viewer.websocket-host 127.0.0.1")
        scores = f"eval-{a['method']}.json"  # one file per method: the second command must not overwrite the first's
        print(f"{' ' * len(a['method'])}  {scorer} --load-config {a['config']} --split test --output-path {scores}")
    print("or train one on for 1000 more steps (the method's own recipe from its last step on):")
    for a in public:
        print(f"{a['method']}: {resume_command(a['method'], Path(a['config']), scene)}")
    if viewer != "ns-viewer":
        print("(or `source .venv/bin/activate` first, then the bare command names work)")
    print(
        f"your own video: {shell_command('ns-process-data')} video --data my.mp4 --output-dir data/mine --no-gpu, "
        f"then {shell_command('ns-train')} garo-deform-real --data data/mine (docs/data.md, 'Your own video')"
    )
    return summary


def main() -> None:
    """Console entry point."""
    import tyro

    run(tyro.cli(DemoArgs))
