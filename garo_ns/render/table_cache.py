"""A loaded model's time table, kept on disk beside its run: built once, read at every later load.

A table is a fixed function of the model's values and its spec, yet a load built it from the deformation field
every time: jumpingjacks' 40k `garo-deform` loaded in 15.8 s on an H200, most of it its 2.6 GB table's build
(benchmarks/results/frame_jumpingjacks_H200.json), and a model trained on a GPU and opened on a CPU had to build
its whole table there. The first load of a run that renders with a table now writes it to `<run>/time_tables/`,
named by the checkpoint's step and a hash of what the table is made from: the model's values (their fingerprint,
as the render-switch record names them), the table's spec, the scale composition and whether TF32 products built
it. A later load with the same hash reads the file instead of sampling the field; other values (a compact file,
fp16 storage, an edit) or another spec hash to another name and build afresh. A table read is the table written,
key for key, on whatever device it was built.

Nothing is overwritten: an existing file is read or, when unreadable, left as it is (the table is built and not
written). A write goes to a temporary name in the same folder and is linked to its name when complete (a link,
unlike a rename, refuses a name already taken), so a reader never sees half a file. A file that cannot be written
(disk full, a read-only folder) costs nothing but the next load's build. `--pipeline.model.time-table-cache False`
turns it off: nothing read, nothing written.

Under `time_table_window_mb` a window is cut from the file (`TimeTable.window_of`): the whole table's keys and
anchors of that stretch, read from the mapped file, so a window costs a read of its own bytes instead of a build
from the field (jumpingjacks: 1.3 FPS through the test views in time order, each window built; window_jumpingjacks_
H200.json), and its frames are the whole table's. Without a file the window is built from the field, and nothing is
written: writing needs the whole table in memory, which the window exists to avoid.

A finished training run writes the table its render choice took (`keep_trained_table`), so the first load reads it.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Optional, Tuple

import torch

from garo_ns.render.time_table import TableSpec, TimeTable

FOLDER = "time_tables"


def table_file(
    checkpoint: Optional[Path], spec: TableSpec, fingerprint: Optional[str], scale_offset: str, tf32: bool
) -> Optional[Path]:
    """Where the table of `spec` for a model loaded from `checkpoint` lives: `<run>/time_tables/<step>-<hash>.pt`
    (the run's folder holds `nerfstudio_models/`), the hash of the values' `fingerprint`, the spec, the scale
    composition and the build's products (`tf32`); None without a checkpoint or a fingerprint."""
    if checkpoint is None or fingerprint is None:
        return None
    checkpoint = Path(checkpoint)
    made_of = json.dumps([fingerprint, spec.to_dict(), scale_offset, bool(tf32)], sort_keys=True)
    digest = hashlib.sha1(made_of.encode()).hexdigest()[:16]
    return checkpoint.parent.parent / FOLDER / f"{checkpoint.stem}-{digest}.pt"


def read(path: Path, device: Any, window: Optional[TableSpec] = None) -> Tuple[Optional[TimeTable], Optional[str]]:
    """(the table in `path` on `device`, None) or (None, why not): a missing file is no reason, an unreadable one
    is (it is left as it is). `window`: only that stretch of it (`TimeTable.window_of`), read from the mapped file."""
    if not path.is_file():
        return None, None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        return (
            TimeTable.from_state(state, device) if window is None else TimeTable.window_of(state, window, device)
        ), None
    except Exception as err:  # a truncated or foreign file: the table is built instead
        return None, f"{path} could not be read ({type(err).__name__}: {err})"[:300]


def write(table: TimeTable, path: Path) -> Optional[str]:
    """Write `table` to `path` unless a file is there already; None, or why it was not written."""
    exists = f"{path} exists: left as it is"
    if path.exists():
        return exists
    partial = path.with_name(f"{path.name}.partial-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(partial, "wb") as f:
            torch.save(table.state(), f)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(partial, path)  # unlike a rename, refuses a name that exists (another process wrote it meanwhile)
        except FileExistsError:
            return exists
        return None
    except OSError as err:  # disk full, a read-only folder: the next load builds the table again
        return f"{path} could not be written ({type(err).__name__}: {err})"[:300]
    finally:
        try:
            partial.unlink(missing_ok=True)
        except OSError:  # its folder could not be made: there is no partial file
            pass


def model_table_file(model: Any, spec: TableSpec, checkpoint: Optional[Path] = None) -> Optional[Path]:
    """`table_file` for a model loaded from `checkpoint` (default: the one its loader names, `checkpoint_file`), or
    None: caching off, a model not loaded from a checkpoint (a training run), or no values to fingerprint."""
    if not getattr(model.config, "time_table_cache", False):
        return None
    checkpoint = checkpoint or getattr(model, "checkpoint_file", None)
    config, fingerprint = model.config, model.switches.fingerprint()
    return table_file(checkpoint, spec, fingerprint, config.deform_scale_offset, config.time_table_tf32)


def keep_trained_table(model: Any, checkpoint: Path) -> Optional[str]:
    """At the end of a training run whose render choice took a time table: write that table, where the measurement
    left it built, for the finished model's loads (`checkpoint`: the run's last checkpoint, about to be saved with
    the values the table was built from). A line to print, or None where there is nothing to say."""
    spec = model.switches.table_spec()
    finished = model.switches.settings(model.config, False, model.device)  # the switches it will load with
    if spec is None or not finished.time_table or model.frame.built_info(spec) is None:
        return None  # no table taken, or the one taken is not the one in memory (a preview, an earlier rung)
    path = model_table_file(model, spec, checkpoint)
    if path is None:
        return None
    note = write(model.frame.table, path)
    return f"Time table written to {path} for the finished model's loads" if note is None else f"Time table: {note}"
