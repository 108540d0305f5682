"""Compaction after densification: rounds that remove the least important Gaussians, each only after
measuring what the removal costs on a fixed set of training views, within a bound per round and a total
budget, so each scene ends with the number of Gaussians it needs.

* `schedule`: the settings (when, how much per round, the bounds) and the state they start from;
* `importance`: which Gaussians matter least (blending weight over the training views, volume-weighted);
* `guard`: the training views a round is measured on (training data only, never the eval split);
* `decision`: a round's choice of share, from renders with and without its candidates at the same step;
* `training`: a round inside nerfstudio's training loop;
* `report`: what each round did, for the log, the checkpoint and `garo-eval`.

The rounds themselves run in `GaroStrategy.compact`, the one place that changes the number of Gaussians.

May import: `render` (a round's measurement renders), `redundancy`, `ops` and the root's `errors`.
"""

from garo_ns.compaction.importance import importance
from garo_ns.compaction.schedule import Compaction

__all__ = ["Compaction", "importance"]
