"""User-facing errors of the plugin, printed as one line by the `ns-*` commands (see compat)."""


class GaroError(Exception):
    """An error whose message is the whole story: no traceback is shown for it."""


class GaroInputError(GaroError, ValueError):
    """Bad input, named by path: dataset, checkpoint or run config."""


class GaroTrainingError(GaroError, RuntimeError):
    """Training cannot go on (e.g. a non-finite loss); earlier checkpoints are left untouched."""


class GaroConfigError(GaroError, ValueError):
    """A setting out of its range, named by its flag; raised before training starts."""
