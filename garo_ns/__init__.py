"""garo_ns: deformable 3D Gaussian splatting with GARO redundancy pruning, for nerfstudio.

The package root holds the plugin's face (`config`, `garo_model`, `garo_strategy`), the deformation field and what
every command needs (`compat`, `errors`); every other module lives in a room named for its job
(docs/architecture.md draws them).

Modules that lived at the root before the rooms (issue 72) still import under their old paths for one release,
each with one DeprecationWarning: a saved `config.yml` or checkpoint names classes by module path, and a user's
script may import them. The old name is an alias of the moved module, not a copy.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from typing import Any, Optional, Sequence

__version__ = "0.1.0"

MOVED = {
    **{
        f"garo_ns.{name}": f"garo_ns.engine.{name}"
        for name in (
            "adam",
            "fused_ssim",
            "initialisation",
            "losses",
            "metrics",
            "recipe",
            "ssim",
            "train_graphs",
            "training_data",
        )
    },
    "garo_ns.checkpoints": "garo_ns.state.checkpoints",
    "garo_ns.storage": "garo_ns.state.storage",
    "garo_ns.static": "garo_ns.render.static",
    "garo_ns.collector": "garo_ns.ops.collector",
    "garo_ns.dense": "garo_ns.ops.dense",
    "garo_ns.quaternions": "garo_ns.ops.quaternions",
}
"""Old module path -> where the module lives now (to be removed in the release after 0.1)."""


class _MovedModule(types.ModuleType):
    """The old path's module: every attribute read and written is the moved module's, so a class named by the
    old path (a yaml tag, a pickle) is the same class, and a test that patches through it patches the real one."""

    def __init__(self, old: str, target: types.ModuleType) -> None:
        super().__init__(old, target.__doc__)
        object.__setattr__(self, "_target", target)

    def __getattr__(self, name: str) -> Any:
        return getattr(object.__getattribute__(self, "_target"), name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name.startswith("__") and name.endswith("__"):  # the import system's own bookkeeping stays here
            object.__setattr__(self, name, value)
        else:
            setattr(object.__getattribute__(self, "_target"), name, value)

    def __dir__(self) -> list:
        return dir(object.__getattribute__(self, "_target"))


class _MovedLoader(importlib.abc.Loader):
    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        new = MOVED[spec.name]
        # stacklevel 2: the warnings module skips importlib's own frames, so this names the importing line.
        warnings.warn(
            f"{spec.name} moved to {new}; the old path is removed in the next release", DeprecationWarning, stacklevel=2
        )
        return _MovedModule(spec.name, importlib.import_module(new))

    def exec_module(self, module: types.ModuleType) -> None:
        pass  # the moved module ran when it was imported


class _MovedFinder(importlib.abc.MetaPathFinder):
    """Finds the old paths in `MOVED` (only those: every other name is left to the ordinary finders)."""

    def find_spec(
        self, fullname: str, path: Optional[Sequence[str]] = None, target: Optional[types.ModuleType] = None
    ) -> Optional[importlib.machinery.ModuleSpec]:
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, _MovedLoader())


if not any(isinstance(finder, _MovedFinder) for finder in sys.meta_path):
    sys.meta_path.insert(0, _MovedFinder())
