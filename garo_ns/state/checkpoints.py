"""Checkpoints: crash-safe files for nerfstudio's trainer, and the model's state as earlier versions wrote it.

Files (the trainer is patched by `garo_ns.compat.install`): nerfstudio 1.1.5 writes `step-XXXXXXXXX.ckpt`
in place and, with `save_only_latest_checkpoint` (its default), deletes every other checkpoint right after.
A process killed during the write leaves a partial file; its loaders then pick the highest step in the
folder whatever state it is in. Here:

* a checkpoint is written to a temporary file in the same folder, flushed and fsync'd, then renamed
  over its final name (`os.replace`, atomic on POSIX) and the folder is fsync'd; older checkpoints are
  deleted only after that, so a complete checkpoint is on disk at every moment;
* the temporary file is named `partial-0.step-XXXXXXXXX.ckpt.<pid>`: nerfstudio's own loaders (ns-viewer,
  ns-eval, ns-render, ns-export) read the step of a file in that folder as the text between its first
  '-' and first '.', so a leftover of an interrupted write reads as step 0 and never wins over a real
  checkpoint (nor breaks their parsing); it is removed once a newer checkpoint is complete;
* `ns-train --load-dir` takes the newest *complete* `step-*.ckpt`, skipping (with one line each) files
  that are cut short, such as those stock nerfstudio leaves when killed during its in-place write.

The model's state (`GaroModel.load_state_dict` and its extra state): a checkpoint holds as many
Gaussians as it was trained to, so the model's are resized before loading; very old splatfacto
checkpoints name the Gaussians without `gauss_params.`; fields written before the deformation field
had its time network have none; the strategy's running state comes back key by key; a config naming a
render precision (a setting since deleted) renders with the exact fp32 field, with a warning.
"""

from __future__ import annotations

import functools
import os
import re
import sys
import time
import zipfile
from pathlib import Path
from typing import Any, BinaryIO, Callable, Dict, List, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from garo_ns.errors import GaroInputError, GaroTrainingError

CHECKPOINT_NAME = re.compile(r"^step-(\d+)\.ckpt$")
PARTIAL_PREFIX = "partial-0."
GAUSSIAN_KEYS = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")  # splatfacto's
# Test hook: "STEP:SECONDS" makes the write of the checkpoint of step STEP (and later ones) pause for
# SECONDS after its first bytes are on disk, so that a test can kill the process mid-write.
SLOW_WRITE_ENV = "GARO_CHECKPOINT_SLOW_WRITE"


def checkpoint_name(step: int) -> str:
    """nerfstudio's file name for the checkpoint of `step`."""
    return f"step-{step:09d}.ckpt"


def is_complete(path: Path) -> bool:
    """True when `path` is a whole checkpoint file.

    torch.save writes a zip archive whose central directory comes last, so a file cut short at any
    point has no readable directory. (nerfstudio 1.x never writes torch's legacy non-zip format.)
    """
    try:
        with zipfile.ZipFile(path) as archive:
            return len(archive.infolist()) > 0
    except (OSError, zipfile.BadZipFile):
        return False


def list_checkpoints(folder: Path) -> List[Tuple[int, Path]]:
    """(step, path) of every file named like a checkpoint in `folder`, newest first (complete or not)."""
    found = []
    for entry in Path(folder).iterdir():
        match = CHECKPOINT_NAME.match(entry.name)
        if match and entry.is_file():
            found.append((int(match.group(1)), entry))
    return sorted(found, reverse=True)


def latest_complete_step(folder: Path) -> Tuple[int, List[Path]]:
    """The step of the newest complete checkpoint in `folder`, and the newer incomplete files skipped.

    Raises GaroInputError when the folder is missing or holds no complete checkpoint.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise GaroInputError(f"cannot load the checkpoint: no checkpoint folder {folder}")
    skipped = []
    for step, path in list_checkpoints(folder):
        if is_complete(path):
            return step, skipped
        skipped.append(path)
    detail = f" ({', '.join(p.name for p in skipped)} incomplete)" if skipped else ""
    raise GaroInputError(f"cannot load the checkpoint: no complete step-*.ckpt in {folder}{detail}")


def checkpoint_to_load(config: Any) -> Optional[Path]:
    """The file `ns-train` will load (`--load-dir` with `--load-step` or its newest complete checkpoint, or
    `--load-checkpoint`), None when it loads none. Raises GaroInputError when that file is missing."""
    load_dir, load_file = getattr(config, "load_dir", None), getattr(config, "load_checkpoint", None)
    if load_dir is not None:
        load_dir = Path(load_dir)
        step = config.load_step
        if step is None:
            step = latest_complete_step(load_dir)[0]
        elif not load_dir.is_dir():
            raise GaroInputError(f"cannot load the checkpoint: no checkpoint folder {load_dir}")
        path = load_dir / checkpoint_name(step)
        if not path.is_file():
            raise GaroInputError(f"cannot load the checkpoint: no {path.name} in {load_dir} (--load-step {step})")
        return path
    if load_file is not None:
        if not Path(load_file).is_file():
            raise GaroInputError(f"cannot load the checkpoint: no file {load_file}")
        return Path(load_file)
    return None


def check_checkpoint_file(path: Path, model_config: Any = None) -> None:
    """Raise GaroInputError (naming `path`) unless it is a whole nerfstudio checkpoint: a torch archive that
    loads weights-only into a dict with the step and the pipeline's state, and, given the model's settings
    (`model_config`, the plugin's), whose Gaussians and deformation field fit a model built from them.
    The tensors are memory-mapped, not read, so this costs little even for a large checkpoint."""
    path = Path(path)
    if not is_complete(path):
        raise GaroInputError(f"cannot load the checkpoint {path}: not a whole checkpoint file (cut short or not one)")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as err:  # pickled objects weights_only refuses, or a zip that torch did not write
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise GaroInputError(f"cannot load the checkpoint {path}: {reason}") from None
    if not isinstance(state, dict) or not isinstance(state.get("pipeline"), dict):
        raise GaroInputError(f"cannot load the checkpoint {path}: it holds no pipeline state (not nerfstudio's)")
    if not isinstance(state.get("step"), int) or isinstance(state.get("step"), bool):
        raise GaroInputError(f"cannot load the checkpoint {path}: it records no step")
    if callable(getattr(model_config, "make_deformation", None)):
        given = model_state(state["pipeline"])
        try:
            check_fit(expected_state(model_config, given), given)
        except GaroInputError as err:
            raise GaroInputError(
                f"cannot load the checkpoint {path}: {resume_hint(path, model_config, given) or err}"
            ) from None


def run_config_of(checkpoint: Path) -> Optional[Path]:
    """The config.yml of the run a checkpoint was written by (`RUN/nerfstudio_models/step-*.ckpt`), if it is there."""
    path = Path(checkpoint).parent.parent / "config.yml"
    return path if path.is_file() else None


def shape_settings(trained: Any, current: Any, given: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """The settings of `trained` (a model config) that a model built from `current` needs to have the Gaussians'
    and the deformation field's tensor shapes of one built from `trained`: those the two differ in that change a
    shape (the field's depth, width, skip layer, the SH degree, ...), name -> `trained`'s value. `given`: the
    checkpoint's state, when there is one (see `expected_state`)."""
    from dataclasses import fields, replace

    differ = {}
    for f in fields(current):
        if f.init and not f.name.startswith("_") and hasattr(trained, f.name):
            if getattr(trained, f.name) != getattr(current, f.name):
                differ[f.name] = getattr(trained, f.name)

    def shapes(settings: Dict[str, Any]) -> Optional[Dict[str, Tuple[int, ...]]]:
        try:
            state = expected_state(replace(current, **settings), given)
        except Exception:  # a mix of the two configs that its own checks refuse
            return None
        return {k: tuple(v.shape) for k, v in state.items()}

    target = shapes(differ)
    # Needed: a setting left as `current` has it changes a shape (one that matters only together with another,
    # such as the skip layer with the depth, too).
    return {name: v for name, v in differ.items() if shapes({k: w for k, w in differ.items() if k != name}) != target}


def as_flags(settings: Dict[str, Any]) -> str:
    """Model settings as ns-train's flags (`--pipeline.model.deform-depth 4 ...`)."""
    words = []
    for name, value in settings.items():
        text = " ".join(str(v) for v in value) if isinstance(value, (list, tuple)) else str(value)
        words.append(f"--pipeline.model.{name.replace('_', '-')} {text}")
    return " ".join(words)


def resume_hint(path: Path, model_config: Any, given: Dict[str, Any]) -> Optional[str]:
    """What to add to the command, in one line, where the checkpoint's own run (its config.yml) trained a model
    of shapes the command's settings miss and those settings fit the checkpoint; None otherwise."""
    from dataclasses import replace

    import yaml

    config_path = run_config_of(path)
    if config_path is None:
        return None
    try:
        trained = yaml.load(config_path.read_text(), Loader=yaml.Loader).pipeline.model
        settings = shape_settings(trained, model_config, given)
        check_fit(expected_state(replace(model_config, **settings), given), given)
    except Exception:  # an unreadable or foreign config.yml, or settings that still do not fit: no hint
        return None
    if not settings:
        return None
    return (
        f"its run ({config_path}) trained a model of other settings than this command's; to resume it, add "
        f"{as_flags(settings)} to the command"
    )


def model_state(pipeline_state: Dict[str, Any]) -> Dict[str, Any]:
    """The model's part of a pipeline's state, its keys as the model names them (nerfstudio's `_model.`
    prefix, and DDP's `module.`, removed; very old Gaussian names upgraded)."""
    state = {k[len("_model.") :]: v for k, v in pipeline_state.items() if k.startswith("_model.")}
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module.") :]: v for k, v in state.items()}
    upgrade_gaussian_keys(state)
    return state


def expected_state(model_config: Any, given: Optional[Dict[str, Any]] = None) -> Dict[str, Tensor]:
    """The Gaussians' (one of each) and the deformation field's tensors a model built from `model_config`
    has, for a checkpoint holding `given` (a field without a time network for one written before it; None:
    the field as configured)."""
    from dataclasses import replace

    from garo_ns.engine.initialisation import initial_gaussians

    config = model_config
    if getattr(config, "deform_time_net", 0) and given is not None and not has_time_net(given):
        config = replace(config, deform_time_net=0)
    gaussians = initial_gaussians(None, True, 4, 1.0, config.sh_degree)
    expected = {f"gauss_params.{k}": v for k, v in gaussians.items()}
    expected.update({f"deformation.{k}": v for k, v in config.make_deformation().state_dict().items()})
    return expected


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # some platforms cannot open folders; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class _SlowFile:
    """File wrapper for the test hook: pauses once, after the first write reached the disk."""

    def __init__(self, f: BinaryIO, delay: float) -> None:
        self._f, self._delay, self._paused = f, delay, False

    def write(self, data: Any) -> int:
        n = self._f.write(data)
        if not self._paused:
            self._paused = True
            self._f.flush()
            os.fsync(self._f.fileno())
            time.sleep(self._delay)
        return n

    def flush(self) -> None:
        self._f.flush()


def _slow_write_delay(step: int) -> float:
    spec = os.environ.get(SLOW_WRITE_ENV, "")
    if not spec:
        return 0.0
    first, seconds = spec.split(":")
    return float(seconds) if step >= int(first) else 0.0


def _disk_full(err: BaseException) -> bool:
    """Whether a write failed for want of space: OSError ENOSPC, or torch's zip writer's message for it."""
    import errno

    if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(err)
    return isinstance(err, RuntimeError) and ("unexpected pos" in text or "No space left" in text)


def save_atomically(state: Dict[str, Any], folder: Path, step: int, keep_only_latest: bool) -> Path:
    """Write `state` as the checkpoint of `step` in `folder`; with `keep_only_latest`, then delete the others.

    At every moment the folder holds at least the previous complete checkpoint or the new one.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    final = folder / checkpoint_name(step)
    partial = folder / f"{PARTIAL_PREFIX}{final.name}.{os.getpid()}"
    delay = _slow_write_delay(step)
    try:
        with open(partial, "wb") as f:
            torch.save(state, _SlowFile(f, delay) if delay > 0 else f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(partial, final)
    except BaseException as err:
        partial.unlink(missing_ok=True)
        if _disk_full(err):
            kept = [p.name for _, p in list_checkpoints(folder)]
            raise GaroTrainingError(
                f"the disk holding {folder} is full: the checkpoint of step {step} could not be written"
                + (f"; {kept[-1]} is kept" if kept else "")
                + ". Free space and resume with --load-dir"
            ) from None
        raise
    _fsync_dir(folder)
    if keep_only_latest:
        for _, path in list_checkpoints(folder):
            if path != final:
                path.unlink(missing_ok=True)
    # Leftovers of writes that a crash interrupted: never loaded, removed once a newer checkpoint is whole.
    for entry in folder.glob(f"{PARTIAL_PREFIX}*"):
        if entry != partial:
            entry.unlink(missing_ok=True)
    return final


def _trainer_save_checkpoint(self: Any, step: int) -> None:
    """Trainer.save_checkpoint with nerfstudio 1.1.5's content, written crash-safe."""
    pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
    watch = getattr(pipeline.model, "loss_watch", None)
    if watch is not None:  # a non-finite loss since the last check stops training before it can be saved
        watch.check()
    state = {
        "step": step,
        "pipeline": pipeline.state_dict(),
        "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
        "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
        "scalers": self.grad_scaler.state_dict(),
    }
    save_atomically(state, self.checkpoint_dir, step, self.config.save_only_latest_checkpoint)


def _resolve_load_step(config: Any) -> Optional[int]:
    """Pin `config.load_step` to the newest complete checkpoint when the caller asked for the latest."""
    if config.load_dir is None or config.load_step is not None:
        return None
    step, skipped = latest_complete_step(Path(config.load_dir))
    for path in skipped:
        print(f"skipping incomplete checkpoint {path} (its write was interrupted)")
    config.load_step = step
    return step


_patched = False
_eval_patched = False


def _patch_eval_loader() -> bool:
    """Make nerfstudio's `eval_load_checkpoint` (ns-viewer, ns-eval, ns-render, garo-eval) load the newest complete
    checkpoint and check it first, so a truncated or foreign file is one line naming it, not torch's traceback.
    Needs nerfstudio's eval_utils module fully imported; returns whether it is patched."""
    global _eval_patched
    if _eval_patched:
        return True
    module = sys.modules.get("nerfstudio.utils.eval_utils")
    original = getattr(module, "eval_load_checkpoint", None)
    if original is None:
        return False
    _eval_patched = True

    def eval_load_checkpoint(config: Any, pipeline: Any) -> Tuple[Path, int]:
        pinned = _resolve_load_step(config)
        try:
            path = checkpoint_to_load(config)
            if path is not None:
                model_config = getattr(getattr(config, "pipeline", None), "model", None)
                check_checkpoint_file(path, model_config)
                keep_tables_beside(getattr(pipeline, "model", None), path)
            try:
                return original(config, pipeline)
            except GaroInputError as err:  # the model's state does not fit (check_fit)
                raise GaroInputError(f"cannot load the checkpoint {path}: {err}") from None
        finally:
            if pinned is not None:
                config.load_step = None

    module.eval_load_checkpoint = functools.update_wrapper(eval_load_checkpoint, original)
    return True


def keep_tables_beside(model: Any, checkpoint: Path) -> None:
    """A model loaded to render from `checkpoint` keeps its time tables on disk beside its run
    (garo_ns.render.table_cache): set before the load, whose end builds (or now reads) the table."""
    from garo_ns.render import table_cache

    if hasattr(model, "frame") and hasattr(model, "switches"):
        model.checkpoint_file = Path(checkpoint)
        model.frame.table_file = functools.partial(table_cache.model_table_file, model)


def install() -> bool:
    """Patch nerfstudio's Trainer once its module is fully imported, and its eval loader once eval_utils is;
    returns whether the Trainer is patched.

    `garo_ns.compat.install` calls this on every import of the plugin's entry points. The first call can
    come while nerfstudio is still importing the trainer module (its dataparser registry loads plugins
    from inside that import), when the patch cannot be applied yet; the method registry, which loads
    `garo_ns.config` before any training starts, comes later, after the trainer module is complete.
    ns-viewer, ns-eval and ns-render load the plugin from inside the import of eval_utils, so its loader is
    patched from the model's set-up (`GaroModel.populate_modules` calls this), which runs before it loads.
    """
    global _patched
    _patch_eval_loader()
    if _patched:
        return True
    trainer_module = sys.modules.get("nerfstudio.engine.trainer")
    if trainer_module is None or not hasattr(trainer_module, "Trainer"):
        return False
    _patched = True
    trainer_cls = trainer_module.Trainer
    check_main_thread = getattr(trainer_module, "check_main_thread", lambda fn: fn)
    trainer_cls.save_checkpoint = functools.update_wrapper(
        check_main_thread(_trainer_save_checkpoint), _trainer_save_checkpoint
    )
    original_load = trainer_cls._load_checkpoint

    def _load_checkpoint(self: Any) -> None:
        pinned = _resolve_load_step(self.config)
        path = checkpoint_to_load(self.config)
        if path is not None:
            check_checkpoint_file(path, self.config.pipeline.model)
        try:
            original_load(self)
        except GaroInputError as err:  # the model's state does not fit (garo_ns.state.checkpoints.check_fit)
            raise GaroInputError(f"cannot load the checkpoint {path}: {err}") from None
        finally:
            if pinned is not None:  # leave the config as the user gave it ("the latest")
                self.config.load_step = None

    trainer_cls._load_checkpoint = _load_checkpoint
    return True


# --- the model's state as earlier versions wrote it ------------------------------------------------------------


def upgrade_gaussian_keys(state_dict: Dict[str, Any]) -> None:
    """Rename, in place, the Gaussians of very old splatfacto checkpoints (`means`, ...) to `gauss_params.*`."""
    if "means" in state_dict:
        for key in GAUSSIAN_KEYS:
            state_dict[f"gauss_params.{key}"] = state_dict.pop(key)


def resize_gaussians(params: nn.ParameterDict, n: int) -> None:
    """Give every Gaussian parameter `n` rows (zeros, to be loaded over), keeping the Parameter objects,
    so optimizers built before loading stay bound to the loaded Gaussians."""
    for param in params.values():
        param.data = param.data.new_zeros((n,) + tuple(param.shape[1:]))


def check_fit(expected: Dict[str, Any], given: Dict[str, Any]) -> None:
    """Raise GaroInputError, naming the first key, when the checkpoint's state `given` lacks one of the
    Gaussians' or the deformation field's tensors of `expected` (the model's own state) or holds one of
    another shape: a checkpoint of another method or of an incompatible version. (nerfstudio would load
    the rest non-strictly, leaving that part as initialised; torch would print a wall of keys.)"""
    core = [k for k in expected if k.startswith(("gauss_params.", "deformation."))]
    missing = [k for k in core if k not in given]
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise GaroInputError(
            f"it has no {missing[0]}{more}: a checkpoint of another method or version, not of this model"
        )
    for key in core:
        want, got = expected[key], given[key]
        if not isinstance(want, Tensor):
            continue
        # The Gaussians' count is the checkpoint's (the model resizes to it); every other extent must agree.
        fits = isinstance(got, Tensor) and (
            got.shape[1:] == want.shape[1:] if key.startswith("gauss_params.") else got.shape == want.shape
        )
        if not fits:
            shape = tuple(got.shape) if isinstance(got, Tensor) else type(got).__name__
            dims = [str(d) for d in want.shape]
            if key.startswith("gauss_params.") and dims:
                dims[0] = "N"  # any number of Gaussians
            mine = f"({', '.join(dims)})"
            raise GaroInputError(
                f"{key} is {shape}, this model's is {mine}: a checkpoint of other settings or of another version "
                "(load it with the config.yml it was trained with)"
            )


def has_time_net(state_dict: Dict[str, Any]) -> bool:
    """Whether the checkpoint's deformation field has D-3DGS's time network (later versions always write one)."""
    return any(k.startswith("deformation.time_net.") for k in state_dict)


def field_for(state_dict: Dict[str, Any], field: nn.Module, settings: Any) -> nn.Module:
    """The deformation field the checkpoint's weights fit: `field`, or, for a checkpoint written before
    the time network was part of the recipe, a field built without it (`settings.deform_time_net` set to
    0), so the run renders as it was trained (an optimizer built earlier is not bound to the new field)."""
    if getattr(field, "time_net", None) is None or has_time_net(state_dict):
        return field
    from nerfstudio.utils.rich_utils import CONSOLE

    CONSOLE.print("[yellow]Checkpoint has no deformation time network: loading the field without it[/yellow]")
    settings.deform_time_net = 0
    return settings.make_deformation().to(next(field.parameters()).device)


def scale_offset_for(state_dict: Dict[str, Any], settings: Any) -> str:
    """The scale composition the checkpoint's Gaussians and field were trained with (`deform_scale_offset`, which
    checkpoints record in the model's extra state since 2026-11-27), adopted by `settings` where it says otherwise: a
    run resumed, imported or rendered under a method whose default has changed since (garo-deform took `linear`
    from `log`) composes its scales as they were trained instead of rendering wrong sizes. A checkpoint without the
    record keeps `settings`' composition, which its own config.yml names."""
    from garo_ns.deformation import SCALE_OFFSETS

    extra = state_dict.get("_extra_state")
    saved = extra.get("scale_offset") if isinstance(extra, dict) else None
    if saved is None or saved == settings.deform_scale_offset:
        return settings.deform_scale_offset
    if saved not in SCALE_OFFSETS:
        raise GaroInputError(f"it records deform_scale_offset {saved!r}, which is none of {SCALE_OFFSETS}")
    from nerfstudio.utils.rich_utils import CONSOLE

    CONSOLE.print(
        f"[yellow]Checkpoint trained with deform_scale_offset {saved!r} (the config says "
        f"{settings.deform_scale_offset!r}): composing scales as it was trained[/yellow]"
    )
    settings.deform_scale_offset = saved
    return saved


# Settings deleted after they were measured (benchmarks/HISTORY.md), each with whether an old value asked for something
# the model no longer does, and what it does instead.
DELETED_SETTINGS: Dict[str, Tuple[Callable[[Any], bool], str]] = {
    "render_precision": (lambda v: v not in (None, "fp32"), "the model renders with the exact fp32 field instead"),
    "train_tiles_without_wait": (bool, "training builds its tile lists with gsplat's isect_tiles"),
}


def upgrade_render_settings(settings: Any) -> List[str]:
    """Drop, in place, the deleted settings an older config.yml holds (`DELETED_SETTINGS`: nothing may read them),
    and return a warning for each whose value asked for what the model no longer does (render_precision other than
    fp32: bf16, fp16-fused and tf32 were deleted first, then fp16 with the setting itself; tile lists built without
    a host read, slower where timed)."""
    state = vars(settings)
    warnings = []
    for name, (mattered, instead) in DELETED_SETTINGS.items():
        if name not in state:
            continue
        value = state.pop(name)
        if mattered(value):
            warnings.append(f"{name}={value} was deleted (benchmarks/HISTORY.md); {instead}")
    return warnings


def restore_strategy_state(state: Dict[str, Any], saved: Dict[str, Any], device: Union[str, torch.device]) -> None:
    """Put the strategy state `saved` with a checkpoint back into `state`, tensors on `device`; only the
    keys that `state` has (a checkpoint's obsolete keys are dropped, keys it lacks keep their start value)."""
    for key, value in saved.items():
        if key in state:
            state[key] = value.to(device) if isinstance(value, Tensor) else value


def fit_model_to(model: Any, state_dict: Dict[str, Any]) -> None:
    """Make `model` (a GaroModel) take `state_dict`'s shapes before it loads it: older checkpoints' keys renamed,
    the scale composition the Gaussians were trained with adopted, the Gaussians resized in place (same Parameter
    objects, so optimizers built before loading stay bound to them) and the field rebuilt where its time network
    differs. GaroInputError where the checkpoint cannot fit (another model's, another SH degree)."""
    upgrade_gaussian_keys(state_dict)
    model.frame.scale_offset = scale_offset_for(state_dict, model.config)
    check_fit({k: v for k, v in model.state_dict().items() if k.startswith("gauss_params.")}, state_dict)
    resize_gaussians(model.gauss_params, state_dict["gauss_params.means"].shape[0])
    model.deformation = field_for(state_dict, model.deformation, model.config)
    check_fit(model.state_dict(), state_dict)


def extra_state(model: Any) -> Dict[str, Any]:
    """What a checkpoint holds of `model` besides its parameters: the densification strategy's running state (the
    compaction's summary too), the render switches' measurement, and the scale composition the Gaussians were
    trained with (`scale_offset_for`)."""
    return {
        "strategy_state": dict(model.strategy_state),
        "render_switches": model.switches.record,
        "scale_offset": model.config.deform_scale_offset,
    }


def restore_extra_state(model: Any, state: Optional[Dict[str, Any]]) -> None:
    """Put `extra_state`'s record back into `model`. torch calls this before it loads the Gaussians and the field,
    so what the record decides is said by the model's `load_state_dict`, once every parameter is in."""
    restore_strategy_state(model.strategy_state, (state or {}).get("strategy_state") or {}, model.device)
    model.switches.record = (state or {}).get("render_switches")
