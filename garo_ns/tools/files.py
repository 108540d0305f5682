"""Files the tools write: whole or not at all, and never over a file they were not asked to replace.

A file is written under a temporary name in its own folder (`.<name>.partial-<pid>`), flushed to disk and renamed
over its final name (atomic on POSIX): a disk that fills or a process killed mid-write leaves no half file under the
final name, and the previous file, if any, stays whole until the new one is. Checkpoints follow the same rule in
garo_ns.state.checkpoints.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

from garo_ns.errors import GaroInputError


@contextlib.contextmanager
def written_atomically(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path` to write to; once the block ends without error it is synced and renamed
    over `path`, otherwise removed."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        yield partial
        with open(partial, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


def check_new_file(path: Path, flag: str, overwrite: bool = False) -> Path:
    """`path` if the tool may write it: not a folder, its folder not a file, and not an existing file unless
    `overwrite` (the user named it for replacing). GaroInputError naming `flag` otherwise, before any work."""
    path = Path(path)
    if path.is_dir():
        raise GaroInputError(f"{flag} {path} is a folder: give a file name")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise GaroInputError(f"{flag} {path}: {parent} is a file, not a folder")
            break
    if path.exists() and not overwrite:
        raise GaroInputError(f"{flag} {path} exists: choose another name, or remove it first")
    return path
