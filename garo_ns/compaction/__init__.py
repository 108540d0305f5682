"""Compaction after densification: rounds that remove the least important Gaussians while the PSNR on a
fixed set of training views stays within a tolerance, so each scene ends with the budget it needs.

* `schedule`: the settings (when, how much per round, the tolerance) and the state they start from;
* `importance`: which Gaussians matter least (blending weight over the training views, volume-weighted);
* `guard`: the training-view PSNR that judges each round (training data only, never the eval split);
* `report`: what each round did, for the log, the checkpoint and `garo-eval`.

The rounds themselves run in `GaroStrategy.compact`, the one place that changes the number of Gaussians.
"""

from garo_ns.compaction.importance import importance
from garo_ns.compaction.schedule import Compaction

__all__ = ["Compaction", "importance"]
