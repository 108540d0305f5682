"""User-facing errors of the plugin, printed as one line by the `ns-*` commands (see compat)."""

from __future__ import annotations

import math
from typing import Any, Mapping, Tuple


class GaroError(Exception):
    """An error whose message is the whole story: no traceback is shown for it. The message is one line: a control
    character from the input it names (a newline in a file name) is shown escaped."""

    def __init__(self, *args: Any) -> None:
        if len(args) == 1 and isinstance(args[0], str):
            args = (one_line(args[0]),)
        super().__init__(*args)


def one_line(text: str) -> str:
    """`text` with each unprintable character (newline, tab, ...) written as its escape; the rest as it is (a
    non-ASCII letter in a path stays readable)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class GaroInputError(GaroError, ValueError):
    """Bad input, named by path: dataset, checkpoint or run config."""


class GaroTrainingError(GaroError, RuntimeError):
    """Training cannot go on (e.g. a non-finite loss); earlier checkpoints are left untouched."""


class GaroConfigError(GaroError):
    """A setting out of its range, named by its flag; raised before training starts.

    Not a ValueError on purpose: tyro catches ValueErrors raised while it builds a config from the command
    line and redraws them as a multi-line box; this one reaches the plugin's one-line handler instead."""


def finite_number(value: Any) -> bool:
    """Whether `value` is an int or float and finite (NaN and infinities fail a range check)."""
    return isinstance(value, (int, float)) and math.isfinite(value)


def check_ranges(settings: Any, checks: Mapping[str, Tuple[bool, str]], flag_prefix: str = "") -> None:
    """Raise GaroConfigError for the first failed check, naming its flag (`--pipeline.model.<prefix><name>`),
    the range (`checks[name] = (ok, range in words)`) and the value (`settings.<name with _ for ->`)."""
    for name, (ok, limit) in checks.items():
        if not ok:
            value = getattr(settings, name.replace("-", "_"))
            raise GaroConfigError(f"--pipeline.model.{flag_prefix}{name} must be {limit}, got {value!r}")
