"""`garo-eval`: score a trained run on any split of its scene, time its renders, and write JSON.

`ns-eval` always scores the `test` split; D-3DGS scores lego on `val`. This command renders the
chosen split itself and writes PSNR, SSIM, LPIPS (null without offline weights), the number of
Gaussians, the split, the render switches used (and what each approximate one was measured to change
against the plain render), and for a `garo-compact` run what its compaction decided. Beside the error, the
speed: the same views timed by the benchmark's FPS protocol (garo_ns.tools.fps; the frame rate, the
milliseconds in the deformation field and in the rasterizer, a view at a time already rendered), the model's
size and the machine that timed it (`--no-fps` leaves the timing out).

A D-NeRF scene's split comes from its transforms file (cameras and times, images composited on the model's
background). A real capture (a video processed by ns-process-data, a NeRF-DS / HyperNeRF capture) has training
frames and held-out frames: `val` and `test` both score the held-out ones, `train` the training ones, read
through the run's own dataparser and undistorted as training saw them.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras

from garo_ns import compat
from garo_ns.compaction.guard import psnr
from garo_ns.compaction.report import summary_for_json
from garo_ns.config import METHODS as METHOD_SPECS
from garo_ns.data.dnerf import read_split, split_cameras
from garo_ns.engine.metrics import lpips_fits, make_lpips
from garo_ns.errors import GaroInputError
from garo_ns.tools.files import check_new_file, written_atomically
from garo_ns.tools.fps import machine, measure_fps, measure_same_time, model_size_mb, protocol, synchronize

compat.install()

METHODS = tuple(METHOD_SPECS)


def register_methods() -> None:
    """Make every method of the plugin known to nerfstudio's loaders, also where the installed entry
    points predate one (an editable install does not re-read pyproject.toml's table)."""
    from nerfstudio.configs.method_configs import all_methods, descriptions

    for name, spec in METHOD_SPECS.items():
        all_methods.setdefault(name, spec.config)
        descriptions.setdefault(name, spec.description)


def load_run(
    config_path: Path, data: Optional[Path] = None, settings: Optional[Dict[str, Any]] = None
) -> Tuple[Any, Any, Path, int]:
    """Load a trained garo_ns run: (config, pipeline, checkpoint path, step); `data` replaces the scene folder the
    run was trained on (a scene that moved since); `settings` (`model_overrides`) are set on the model's config
    before the model is made, so the load already renders with them (a time table built at load, or not, as they
    say).

    Raises GaroInputError for a missing config, a run of another method, or an unreadable
    (e.g. truncated) checkpoint. Nothing on disk is modified, but for the model's time table, which a first load
    writes beside the run (`<run>/time_tables/`, garo_ns.render.table_cache) and later loads read.
    """
    import yaml
    from nerfstudio.utils.eval_utils import eval_setup

    config_path = Path(config_path)
    if not config_path.is_file():
        raise GaroInputError(f"run config not found: {config_path}")
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as err:
        raise GaroInputError(f"cannot read run config {config_path}: {err}") from None
    method = getattr(config, "method_name", None)
    if method not in METHODS:
        raise GaroInputError(f"{config_path} is a run of '{method}', not of {' or '.join(METHODS)}")
    register_methods()

    def update(loaded: Any) -> Any:
        if data is not None:
            loaded.pipeline.datamanager.data = Path(data)
            loaded.pipeline.datamanager.dataparser.data = Path(data)
        for name, value in (settings or {}).items():
            setattr(loaded.pipeline.model, name, value)
        return loaded

    if data is not None and not Path(data).is_dir():
        raise GaroInputError(f"--data {data} is not a folder")
    try:
        return eval_setup(config_path, test_mode="inference", update_config_callback=update)
    except (RuntimeError, EOFError, OSError, KeyError, AssertionError) as err:
        if isinstance(err, AssertionError) and "does not exist" not in str(err):
            raise
        ckpt = Path(config.output_dir) / config.experiment_name / config.method_name / config.timestamp
        raise GaroInputError(f"cannot load the checkpoint of {config_path} (under {ckpt}): {err}") from None


def setting_pairs(pairs: List[str], known: Any, flag: str, what: str) -> Dict[str, Any]:
    """`NAME=VALUE` pairs (VALUE read as a Python literal, else kept as a string) with each NAME in `known`; any
    other pair stops the command with one line naming `flag` and `what` NAME must be."""
    import ast

    out: Dict[str, Any] = {}
    for pair in pairs:
        name, sep, text = pair.partition("=")
        if not sep or name not in known:
            raise SystemExit(f"{flag} expects NAME=VALUE with NAME {what}, got {pair!r}")
        try:
            out[name] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            out[name] = text
    return out


def model_overrides(pairs: List[str], flag: str = "--set") -> Dict[str, Any]:
    """`NAME=VALUE` pairs as model settings; an unknown NAME is refused (naming `flag`) before anything runs."""
    from garo_ns.garo_model import GaroModelConfig

    return setting_pairs(pairs, {f.name for f in fields(GaroModelConfig)}, flag, "a model setting")


def apply_model_settings(model: Any, pairs: List[str]) -> None:
    """Set `NAME=VALUE` model settings on a loaded model, and on its frame path, which reads some of them."""
    for name, value in model_overrides(pairs).items():
        setattr(model.config, name, value)
    if pairs:
        model.frame.configure(model.config)
        model.switches.parameters_changed()


def scene_dir(config: Any) -> Path:
    """The scene directory a run was trained on."""
    dm = config.pipeline.datamanager
    data = dm.data if getattr(dm, "data", None) is not None else dm.dataparser.data
    return Path(data)


def load_split(data: Path, split: str, background: torch.Tensor) -> Tuple[Cameras, List[torch.Tensor]]:
    """Cameras (with times) and ground-truth images [H, W, 3] in [0, 1], composited on `background`."""
    import imageio.v2 as imageio

    paths, poses, times, angle, (h, w) = read_split(data, split)
    cameras = split_cameras(poses, times, angle, h, w)
    images = []
    bg = background.float().cpu()
    for path in paths:
        pixels = np.asarray(imageio.imread(path))
        # Scaled by the file's own range: a 16-bit PNG's 65535 is white, as training reads it.
        scale = float(np.iinfo(pixels.dtype).max) if np.issubdtype(pixels.dtype, np.integer) else 1.0
        img = torch.from_numpy(pixels.astype(np.float32)) / scale
        if img.ndim == 2:
            img = img[..., None].expand(-1, -1, 3)
        if img.shape[-1] == 4:
            img = img[..., :3] * img[..., 3:] + bg * (1.0 - img[..., 3:])
        images.append(img[..., :3])
    return cameras, images


def is_dnerf_scene(data: Path) -> bool:
    """Whether `data` is a D-NeRF scene (transforms_train.json), not a real capture."""
    return (Path(data) / "transforms_train.json").is_file()


def capture_views(pipeline: Any, split: str) -> Tuple[Cameras, List[torch.Tensor]]:
    """A real capture's cameras and images [H, W, 3] in [0, 1] of `split` (`train`, or the held-out frames for
    `val` / `test`), from the run's datamanager: its images undistorted as training read them, its cameras with
    the matching intrinsics."""
    dm = pipeline.datamanager
    dataset, cache = (dm.train_dataset, dm.cached_train) if split == "train" else (dm.eval_dataset, dm.cached_eval)
    images = []
    for item in cache:  # read first: undistorting sets the cameras' intrinsics
        image = item["image"].cpu()
        image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        images.append(image[..., :3])
    return dataset.cameras, images


def split_views(pipeline: Any, data: Path, split: str) -> Tuple[Cameras, List[torch.Tensor]]:
    """Cameras and ground-truth images of `split`: a D-NeRF scene's from its transforms file (`load_split`), a
    real capture's from the run's datamanager (`capture_views`)."""
    if is_dnerf_scene(data):
        return load_split(data, split, pipeline.model.background_color)
    return capture_views(pipeline, split)


def train_times(pipeline: Any, data: Path) -> torch.Tensor:
    """The distinct times of the training frames, ascending."""
    if is_dnerf_scene(data):
        return torch.unique(torch.as_tensor(read_split(data, "train")[2], dtype=torch.float32))
    times = pipeline.datamanager.train_dataset.cameras.times
    return torch.unique(times.reshape(-1).float().cpu())


@torch.no_grad()
def evaluate(
    pipeline: Any, data: Path, split: str, views: Optional[Tuple[Cameras, List[torch.Tensor]]] = None
) -> Dict[str, Any]:
    """Render every frame of `split` and average PSNR, SSIM and (if available, and the images take it) LPIPS;
    `views`: the split's cameras and images where the caller has read them (`split_views`)."""
    model = pipeline.model
    model.eval()
    cameras, images = views if views is not None else split_views(pipeline, data, split)
    lpips = make_lpips()
    psnrs, ssims, lpipss = [], [], []
    first_frame_s = None
    for i, gt in enumerate(images):
        started = time.perf_counter()
        out = model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))
        if i == 0:  # what a viewer waits for after loading: any work put off until a frame needs it
            synchronize(model.device)
            first_frame_s = time.perf_counter() - started
        pred = out["rgb"].clamp(0, 1)
        gt = gt.to(pred.device)
        psnrs.append(psnr(pred, gt))
        p, g = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
        ssims.append(float(model.ssim(g, p)))
        if lpips is not None and lpips_fits(pred):
            lpipss.append(float(lpips.to(pred.device)(g, p)))
    bg = model.background_color.tolist()
    return {
        "psnr": float(np.mean(psnrs)),
        "psnr_per_view": psnrs,
        "ssim": float(np.mean(ssims)),
        "lpips": float(np.mean(lpipss)) if lpipss else None,
        "num_gaussians": int(model.num_points),
        "split": split,
        "n_images": len(images),
        "first_frame_seconds": first_frame_s,
        "background": "black" if bg == [0.0, 0.0, 0.0] else "white" if bg == [1.0, 1.0, 1.0] else bg,
    }


@dataclass
class EvalArgs:
    """Score a garo-deform / deform-splatfacto run on a split of its scene."""

    load_config: Path
    """config.yml of the run."""
    split: Literal["train", "val", "test"] = "test"
    """Split to score (lego: val)."""
    output_path: Path = Path("eval.json")
    """Where to write the JSON."""
    data: Optional[Path] = None
    """Scene directory, if it moved since training."""
    fps: bool = True
    """Also time the split's renders by the FPS protocol (5 warm-up views, 3 passes) and record the model's size
    and the machine; with the switches the scores were rendered with."""
    model_set: List[str] = field(default_factory=list)
    """Model settings to score and time the run with, `NAME=VALUE` (recorded as `model_settings`), e.g.
    `time_table=False static_skip=False`: the plain render of a model whose switches are on."""


def run(args: EvalArgs) -> Dict[str, Any]:
    """Evaluate and write JSON; returns the result."""
    check_new_file(args.output_path, "--output-path", overwrite=True)  # before the whole evaluation runs
    settings = model_overrides(args.model_set, "--model-set")
    started = time.perf_counter()
    config, pipeline, ckpt, step = load_run(args.load_config, args.data, settings)
    apply_model_settings(pipeline.model, args.model_set)
    synchronize(pipeline.model.device)
    load_s = time.perf_counter() - started  # the checkpoint read, the model built, its time table built
    cameras, images = split_views(pipeline, scene_dir(config), args.split)
    result = evaluate(pipeline, scene_dir(config), args.split, (cameras, images))
    if args.fps:  # speed beside the error, on the same views
        model = pipeline.model
        result.update(measure_fps(model, cameras), ms_per_view_same_time=measure_same_time(model, cameras))
        result.update(model_size_mb=model_size_mb(model), fps_protocol=protocol(), machine=machine(model.device))
    result.update({"method": config.method_name, "step": int(step), "checkpoint": str(ckpt), "load_seconds": load_s})
    result["model_settings"] = settings
    # The switches these scores were rendered with, and their measured change against the plain render.
    result["render_switches"] = pipeline.model.render_switch_summary()
    # What compaction decided during training (None for a run without it).
    result["compaction"] = summary_for_json(pipeline.model.strategy_state.get("compact"))
    args.output_path.parent.mkdir(parents=True, exist_ok=True)
    with written_atomically(args.output_path) as partial:
        partial.write_text(json.dumps(result, indent=2))
    return result


def main() -> None:
    """Console entry point."""
    import tyro

    args = tyro.cli(EvalArgs)
    try:
        result = run(args)
    except GaroInputError as err:
        raise SystemExit(f"error: {err}") from None
    lp = "n/a" if result["lpips"] is None else f"{result['lpips']:.4f}"
    fps = f"  FPS {result['fps']:.1f}  {result['model_size_mb']:.1f} MB" if "fps" in result else ""
    print(
        f"{result['method']} step {result['step']} on {result['split']}: PSNR {result['psnr']:.2f}  "
        f"SSIM {result['ssim']:.4f}  LPIPS {lp}  Gaussians {result['num_gaussians']}{fps}  -> {args.output_path}"
    )
