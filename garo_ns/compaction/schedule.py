"""When compaction runs, how much each round may remove, and how much training-view PSNR it may cost.

A round at step s (start <= s, s - start a multiple of `every`, at most `max_rounds` of them) decides
before it removes (garo_ns.compaction.decision): it renders the guard views as they are and with the
round's candidates (the `fraction` least important Gaussians) left out of the render, and removes them
only if the worst view's PSNR loss is within `round_bound_db` and within what is left of `budget_db`;
otherwise it tries half the share, down to `min_fraction`, and stops when even that costs too much.
Both renders of a comparison are of the same step and the same field, so fine-tuning noise between
rounds (a training-view PSNR that swings by a dB from one reading to the next) never decides a round.
The committed rounds' costs, each as measured when made, add up to at most `budget_db`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Dict, List, Optional

from garo_ns.errors import check_ranges, finite_number

# Why a compaction stopped: the summary's `reason`, one of these.
REASONS = {
    "round_bound": "even the smallest share of a round cost more training-view PSNR than a round may; nothing removed",
    "budget": "even the smallest share of a round cost more than was left of the total budget; nothing removed",
    "max_rounds": "the largest number of rounds was reached",
    "min_gaussians": "the model is down to the smallest number of Gaussians allowed",
    "nothing_to_remove": "a round's share of the Gaussians rounds down to none",
    "empty_model": "the model has no Gaussians",
    "no_training_views": "no training views to measure the rounds with",
    "training_ended": "training ended first",
}


@dataclass
class Compaction:
    """Settings of the compaction rounds (see the module docstring for what a round does).

    Args:
        start: step of the first round; None: where densification stops, so the Gaussians left are
            the ones densification settled on.
        every: steps of fine-tuning between rounds.
        fraction: share of the current Gaussians a round tries to remove first (the least important).
        min_fraction: the smallest share a round tries (the share halves from `fraction` down to it).
        round_bound_db: worst guard view's PSNR loss one round may cost, in dB, as measured before removing.
        budget_db: the committed rounds' costs (each the worst view's, as measured) add up to at most this.
        max_rounds: most rounds.
        min_gaussians: never fewer Gaussians than this.
        guard_views: training views the cost is measured on (evenly spread over time).
        volume_beta: exponent of the volume weighting of the importance (LightGaussian's; 0: off).
    """

    start: Optional[int] = None
    every: int = 1000
    fraction: float = 0.15
    min_fraction: float = 0.02
    round_bound_db: float = 0.1
    budget_db: float = 0.3
    max_rounds: int = 15
    min_gaussians: int = 1000
    guard_views: int = 16
    volume_beta: float = 0.1

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, prefix: str = "compact-") -> None:
        """Raise GaroConfigError, naming the flag, for a setting out of its range (NaN included)."""
        checks = {
            "round-bound-db": (finite_number(self.round_bound_db) and self.round_bound_db >= 0, "a number of dB >= 0"),
            "budget-db": (finite_number(self.budget_db) and self.budget_db >= 0, "a number of dB >= 0"),
            "fraction": (finite_number(self.fraction) and 0 < self.fraction < 1, "in (0, 1)"),
            "min-fraction": (
                finite_number(self.min_fraction) and 0 < self.min_fraction <= self.fraction,
                f"in (0, compact-fraction={self.fraction}]",
            ),
            "every": (self.every >= 1, ">= 1"),
            "max-rounds": (self.max_rounds >= 0, ">= 0"),
            "min-gaussians": (self.min_gaussians >= 0, ">= 0"),
            "guard-views": (self.guard_views >= 1, ">= 1"),
            "volume-beta": (finite_number(self.volume_beta) and self.volume_beta >= 0, "a number >= 0"),
            "start": (self.start is None or self.start >= 0, "a step >= 0 or None"),
        }
        check_ranges(self, checks, prefix)

    def first_step(self, densify_stop: int) -> int:
        """Step of the first round."""
        return densify_stop if self.start is None else self.start

    def is_round(self, step: int, densify_stop: int) -> bool:
        """Whether a round falls on `step` (its count is the summary's to keep: see `max_rounds`)."""
        offset = step - self.first_step(densify_stop)
        return offset >= 0 and offset % self.every == 0

    def shares(self) -> List[float]:
        """The shares a round tries, in order: `fraction`, halved while above `min_fraction`, then it."""
        out = [self.fraction]
        while out[-1] > self.min_fraction:
            out.append(max(out[-1] / 2, self.min_fraction))
        return out

    def removal_count(self, n: int, share: Optional[float] = None) -> int:
        """How many of `n` Gaussians a share (default `fraction`) removes: floor(share * n), never below
        `min_gaussians` left."""
        share = self.fraction if share is None else share
        return max(0, min(math.floor(share * n), n - self.min_gaussians))

    def initial_state(self) -> Dict[str, Any]:
        """The summary a compaction starts from (a plain dict: it travels with checkpoints)."""
        return {
            "settings": asdict(self),
            "spent_db": 0.0,
            "num_gaussians_start": None,
            "num_gaussians_end": None,
            "rounds": [],
            "stopped_step": None,
            "reason": None,
            "detail": None,
        }


def last_training_step(start_step: int, max_num_iterations: int) -> int:
    """The last step nerfstudio's trainer runs: it runs `max_num_iterations` steps from `start_step` (0 for a
    fresh run, the loaded step + 1 for a resumed one), so a resumed run ends later than its first part did."""
    return int(start_step) + int(max_num_iterations) - 1


@dataclass
class CompactionSettings:
    """Compaction after densification (garo-compact), part of the model config."""

    compact: bool = False
    """After densification, remove the least important Gaussians in rounds, with fine-tuning in between.
    Each round first measures what its removal would cost (the guard's training views rendered with and
    without the candidates, at the same step) and removes only within `compact_round_bound_db` and the
    total `compact_budget_db`: each scene gets the budget its training views need. Each round is logged;
    the summary goes into checkpoints and garo-eval."""
    compact_round_bound_db: float = Compaction.round_bound_db
    """Worst training view's PSNR loss one round may cost, in dB, measured before it removes."""
    compact_budget_db: float = Compaction.budget_db
    """Total PSNR loss (the sum of the committed rounds' worst-view costs) compaction may spend, in dB; a
    larger value gives a smaller, faster model."""
    compact_start: Optional[int] = None
    """Step of the first round; None: `stop_split_at`, where densification ends."""
    compact_every: int = Compaction.every
    """Steps of fine-tuning between rounds."""
    compact_fraction: float = Compaction.fraction
    """Share of the Gaussians a round tries to remove first (by blending weight over the training views x
    volume^beta); halved while it costs too much."""
    compact_min_fraction: float = Compaction.min_fraction
    """The smallest share a round tries before compaction stops."""
    compact_max_rounds: int = Compaction.max_rounds
    """Most rounds of removal."""
    compact_min_gaussians: int = Compaction.min_gaussians
    """Compaction never leaves fewer Gaussians than this."""
    compact_guard_views: int = Compaction.guard_views
    """Training views each round's cost is measured on (evenly spread over time; the eval split is never
    read); the worst of them decides."""
    compact_volume_beta: float = Compaction.volume_beta
    """Exponent of the volume in the importance (LightGaussian's global significance; 0: weight alone)."""

    def compaction(self) -> Compaction:
        """The compaction settings of this config; raises GaroConfigError for one out of range."""
        return Compaction(**{k: getattr(self, f"compact_{k}") for k in Compaction.__dataclass_fields__})
