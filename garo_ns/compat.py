"""Fixes for nerfstudio 1.1.5 that every `ns-*` command needs; applied when the plugin is imported.

nerfstudio imports plugin entry points before it parses arguments or loads a checkpoint, so
importing `garo_ns.config` is early enough for all of them: checkpoints that load under torch >= 2.6,
one-line input errors, a bad dataset or checkpoint reported before ns-train prints and saves its
configuration (no run folder left behind, nor after a failed set-up), a run folder of each run's own (`claim_run_dir`),
and crash-safe checkpoint writing and loading (`garo_ns.state.checkpoints`).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from types import TracebackType
from typing import Any, Dict, Optional, Type

import numpy as np
import torch

from garo_ns.errors import GaroError, GaroInputError

_installed = False


def allow_numpy_scalars_in_checkpoints() -> None:
    """torch >= 2.6 loads with weights_only=True and rejects the numpy scalars that nerfstudio's
    schedulers leave in checkpoints (`_last_lr`). Allow exactly those types, nothing broader."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4 has no weights_only allow-list and loads them anyway
        return
    try:  # numpy >= 2 moved the module; numpy 1.x keeps it under np.core
        from numpy._core.multiarray import scalar
    except ImportError:
        from numpy.core.multiarray import scalar
    safe: list = [scalar, np.dtype]
    if torch.__version__ >= "2.6":  # (function, name) entries; also the first torch that loads weights_only
        # A checkpoint names the function by the module of the numpy that wrote it: allow both names, so a run
        # trained under numpy 2 (a GPU machine) loads under numpy 1.x (a laptop) and the other way round.
        safe[0:1] = [(scalar, f"{m}.multiarray.scalar") for m in ("numpy._core", "numpy.core")]
    safe += [type(np.dtype(t)) for t in (np.float64, np.float32, np.int64, np.int32, np.bool_)]
    add(safe)


OUT_OF_MEMORY = (
    "out of GPU memory; the run's last complete checkpoint is kept (resume with --load-dir). Fewer Gaussians need "
    "less: lower --pipeline.model.max-gaussians, or train at a smaller image size"
)


def _excepthook(kind: Type[BaseException], err: BaseException, tb: Optional[TracebackType]) -> None:
    if isinstance(err, GaroError):
        print(f"error: {err}", file=sys.stderr)
        return
    if isinstance(err, torch.OutOfMemoryError):  # one line: the traceback tells a user nothing they can act on
        print(f"error: {OUT_OF_MEMORY} ({str(err).splitlines()[0][:160]})", file=sys.stderr)
        return
    _previous_hook(kind, err, tb)


_previous_hook = sys.excepthook


def check_dataset(config: Any) -> None:
    """Validate the dataset of a TrainerConfig when its dataparser is one of the plugin's (`check_data`).

    Raises GaroInputError; other dataparsers are left to nerfstudio.
    """
    datamanager = getattr(getattr(config, "pipeline", None), "datamanager", None)
    check = getattr(getattr(datamanager, "dataparser", None), "check_data", None)
    if callable(check):
        check(getattr(datamanager, "data", None))  # ns-train's --data alias lands on the datamanager


def check_inputs(config: Any) -> None:
    """Everything `ns-train` can check before it creates the run folder: the dataset (`check_dataset`) and
    the checkpoint it is asked to load, if any (present, whole, nerfstudio's). Raises GaroInputError."""
    from garo_ns.errors import GaroConfigError
    from garo_ns.state import checkpoints

    steps = getattr(config, "max_num_iterations", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise GaroConfigError(f"--max-num-iterations must be an int >= 1, got {steps!r}")
    check_dataset(config)
    path = checkpoints.checkpoint_to_load(config)
    if path is not None:
        checkpoints.check_checkpoint_file(path, getattr(getattr(config, "pipeline", None), "model", None))


def _remove_empty_run_dir(base_dir: Path, output_dir: Path) -> None:
    """Delete a run folder that holds nothing but its config.yml, and the folders between it and
    `output_dir` that this leaves empty (never `output_dir` itself)."""
    base_dir, output_dir = Path(base_dir).resolve(), Path(output_dir).resolve()
    if output_dir not in base_dir.parents:
        return
    if not base_dir.is_dir() or any(p.name != "config.yml" for p in base_dir.iterdir()):
        return
    shutil.rmtree(base_dir)
    for parent in base_dir.parents:
        if parent == output_dir:
            break
        try:
            parent.rmdir()
        except OSError:
            break


_claimed: Dict[int, Path] = {}  # id of a config -> the run folder it claimed (a config saved twice stays in it)


def claim_run_dir(config: Any) -> Path:
    """Create `config`'s run folder for this run alone and return it.

    nerfstudio names a run folder by a timestamp of one-second resolution and writes into it whether or not
    another run already did: two runs started in the same second (a sweep in a shell loop) or given the same
    `--timestamp` would share it, the second's config.yml over the first's and each run's checkpoint clean-up
    deleting the other's checkpoints. Here the folder is made with an exclusive `mkdir`; where it exists, the run
    takes the timestamp with `-2`, `-3`, ... appended (said in one line) and writes nothing into the existing one.
    """
    base = Path(config.get_base_dir())
    if _claimed.get(id(config)) == base.resolve():
        return base
    stem = str(config.timestamp)
    for attempt in range(1, 10_000):
        if attempt > 1:
            config.timestamp = f"{stem}-{attempt}"
            base = Path(config.get_base_dir())
        try:
            base.parent.mkdir(parents=True, exist_ok=True)
            base.mkdir()
        except FileExistsError:
            if base.is_dir():
                continue  # another run's folder (or one from earlier): never written into
            raise GaroInputError(f"{base} is a file, not a folder: choose another --output-dir") from None
        except NotADirectoryError:
            raise GaroInputError(
                f"cannot create the run folder {base}: a part of its path is a file (--output-dir {config.output_dir})"
            ) from None
        if attempt > 1:
            print(f"{base.parent / stem} belongs to another run: this run writes to {base}", file=sys.stderr)
        _claimed[id(config)] = base.resolve()
        return base
    raise GaroInputError(f"{base.parent}: no free run folder for timestamp {stem}")


def _patch_trainer_entry() -> bool:
    """Fail on a bad dataset before ns-train prints and saves its configuration, and clean up after a
    bad dataset found later (during Trainer.setup). Needs nerfstudio's trainer module fully imported."""
    trainer_module = sys.modules.get("nerfstudio.engine.trainer")
    if trainer_module is None or not hasattr(trainer_module, "Trainer"):
        return False
    from nerfstudio.configs.experiment_config import ExperimentConfig

    original_print = ExperimentConfig.print_to_terminal

    def print_to_terminal(self: Any) -> None:
        # ns-train calls this right before save_config creates the run folder: the earliest point
        # after the command line is parsed.
        check_inputs(self)
        original_print(self)

    ExperimentConfig.print_to_terminal = print_to_terminal
    original_save = ExperimentConfig.save_config

    def save_config(self: Any) -> None:
        claim_run_dir(self)  # before the first file of the run is written
        original_save(self)

    ExperimentConfig.save_config = save_config
    trainer_cls = trainer_module.Trainer
    original_setup = trainer_cls.setup

    def setup(self: Any, *args: Any, **kwargs: Any) -> None:
        try:
            original_setup(self, *args, **kwargs)
        except Exception:  # whatever stopped it, a run folder holding only its config.yml is no run
            _remove_empty_run_dir(self.base_dir, self.config.output_dir)
            raise

    trainer_cls.setup = setup
    return True


def _patch_finished_viewer() -> bool:
    """`ns-viewer` on a finished run: show the step the model was saved at and no Pause/Resume Training buttons
    (nerfstudio 1.1.5 shows "Step: 0" and "Pause Training" there, as for a training just started). Needs
    nerfstudio's viewer module fully imported."""
    module = sys.modules.get("nerfstudio.viewer.viewer")
    if module is None or not hasattr(module, "Viewer"):
        return False
    viewer_cls = module.Viewer
    original_update = viewer_cls.update_scene

    def update_scene(self: Any, step: int, num_rays_per_batch: Optional[int] = None) -> None:
        if getattr(self, "trainer", None) is None:  # ns-viewer: a saved model, nothing trains
            self.pause_train.visible = False
            self.resume_train.visible = False
            self.stats_markdown.content = self.make_stats_markdown(step, None)
        original_update(self, step, num_rays_per_batch)

    viewer_cls.update_scene = update_scene
    return True


_entry_patched = False
_viewer_patched = False


def install() -> None:
    """Apply the fixes once per process; those on nerfstudio's trainer as soon as its module is imported
    (the plugin's entry points can load while nerfstudio is still importing it)."""
    global _installed, _previous_hook, _entry_patched, _viewer_patched
    from garo_ns.state import checkpoints

    checkpoints.install()
    if not _entry_patched:
        _entry_patched = _patch_trainer_entry()
    if not _viewer_patched:
        _viewer_patched = _patch_finished_viewer()
    if _installed:
        return
    _installed = True
    allow_numpy_scalars_in_checkpoints()
    # Bad input gets one line, not a traceback wall; every other error keeps its traceback.
    _previous_hook = sys.excepthook
    sys.excepthook = _excepthook
