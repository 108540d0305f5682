"""When compaction runs, how much each round removes, and how much training-view PSNR it may cost.

A round at step s (start <= s, s - start a multiple of `every`, at most `max_rounds` removals):
  1. measure the guard PSNR P (fixed training views, each at its own time);
  2. if P has fallen more than `tolerance_db` below the best P of the rounds so far, the last removal
     did not recover in the fine-tuning since: put back the Gaussians as they were before it, stop;
  3. remove the `fraction` least important Gaussians (never below `min_gaussians`) and measure again;
     if that removal alone cost more than `tolerance_db`, put them back at once and stop.
Training between rounds is the fine-tuning. At the last training step a removal still waiting for its
check (2) gets it, so the model that training ends with keeps the tolerance. Both checks compare
renders of one model state against another at the same step or against the best measured so far, so
the tolerance bounds the loss on the training views that compaction caused, as far as training views
can tell it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Dict, Optional

from garo_ns.errors import GaroConfigError

# Why a compaction stopped: the summary's `reason`, one of these.
REASONS = {
    "tolerance": "a removal cost more training-view PSNR than the tolerance; it was undone",
    "max_rounds": "the largest number of rounds was reached",
    "min_gaussians": "the model is down to the smallest number of Gaussians allowed",
    "nothing_to_remove": "a round's share of the Gaussians rounds down to none",
    "empty_model": "the model has no Gaussians",
    "no_training_views": "no training views to judge the rounds with",
    "training_ended": "training ended first",
}


@dataclass
class Compaction:
    """Settings of the compaction rounds (see the module docstring for what a round does).

    Args:
        start: step of the first round (it measures the reference, then removes); None: where
            densification stops, so the Gaussians left are the ones densification settled on.
        every: steps of fine-tuning between rounds.
        fraction: share of the current Gaussians a round removes (the least important ones).
        tolerance_db: training-view PSNR a removal may cost, in dB (>= 0; raise it for a smaller model).
        max_rounds: most removals; rounds after the last one only check it.
        min_gaussians: never fewer Gaussians than this.
        guard_views: training views the PSNR is measured on (evenly spread over time).
        volume_beta: exponent of the volume weighting of the importance (LightGaussian's; 0: off).
    """

    start: Optional[int] = None
    every: int = 1000
    fraction: float = 0.15
    tolerance_db: float = 0.2
    max_rounds: int = 15
    min_gaussians: int = 1000
    guard_views: int = 16
    volume_beta: float = 0.1

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, prefix: str = "compact-") -> None:
        """Raise GaroConfigError, naming the flag, for a setting out of its range (NaN included)."""
        checks = {
            "tolerance-db": _finite(self.tolerance_db) and self.tolerance_db >= 0,
            "fraction": _finite(self.fraction) and 0 < self.fraction < 1,
            "every": self.every >= 1,
            "max-rounds": self.max_rounds >= 0,
            "min-gaussians": self.min_gaussians >= 0,
            "guard-views": self.guard_views >= 1,
            "volume-beta": _finite(self.volume_beta) and self.volume_beta >= 0,
            "start": self.start is None or self.start >= 0,
        }
        limits = {
            "tolerance-db": "a number of dB >= 0",
            "fraction": "in (0, 1)",
            "every": ">= 1",
            "max-rounds": ">= 0",
            "min-gaussians": ">= 0",
            "guard-views": ">= 1",
            "volume-beta": "a number >= 0",
            "start": "a step >= 0 or None",
        }
        for name, ok in checks.items():
            if not ok:
                value = getattr(self, name.replace("-", "_"))
                raise GaroConfigError(f"--pipeline.model.{prefix}{name} must be {limits[name]}, got {value!r}")

    def first_step(self, densify_stop: int) -> int:
        """Step of the first round."""
        return densify_stop if self.start is None else self.start

    def is_round(self, step: int, densify_stop: int) -> bool:
        """Whether a round (a check, and a removal unless it is past `max_rounds`) falls on `step`."""
        offset = step - self.first_step(densify_stop)
        return offset >= 0 and offset % self.every == 0 and offset // self.every <= self.max_rounds

    def removal_count(self, n: int) -> int:
        """How many of `n` Gaussians a round removes: floor(fraction * n), never below `min_gaussians` left."""
        return max(0, min(math.floor(self.fraction * n), n - self.min_gaussians))

    def initial_state(self) -> Dict[str, Any]:
        """The summary a compaction starts from (a plain dict: it travels with checkpoints)."""
        return {
            "settings": asdict(self),
            "reference_psnr": None,
            "best_psnr": None,
            "final_psnr": None,
            "num_gaussians_start": None,
            "num_gaussians_end": None,
            "rounds": [],
            "stopped_step": None,
            "reason": None,
            "detail": None,
        }


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


@dataclass
class CompactionSettings:
    """Compaction after densification (garo-compact), part of the model config."""

    compact: bool = False
    """After densification, remove the least important Gaussians in rounds, with fine-tuning in between,
    until a round costs more training-view PSNR than `compact_tolerance_db`: each scene gets the budget
    its training views need. Each round is logged; the summary goes into checkpoints and garo-eval."""
    compact_tolerance_db: float = Compaction.tolerance_db
    """Training-view PSNR a removal may cost, in dB; a larger value gives a smaller, faster model."""
    compact_start: Optional[int] = None
    """Step of the first round; None: `stop_split_at`, where densification ends."""
    compact_every: int = Compaction.every
    """Steps of fine-tuning between rounds."""
    compact_fraction: float = Compaction.fraction
    """Share of the Gaussians a round removes (by blending weight over the training views x volume^beta)."""
    compact_max_rounds: int = Compaction.max_rounds
    """Most rounds of removal."""
    compact_min_gaussians: int = Compaction.min_gaussians
    """Compaction never leaves fewer Gaussians than this."""
    compact_guard_views: int = Compaction.guard_views
    """Training views the guard measures PSNR on (evenly spread over time; the eval split is never read)."""
    compact_volume_beta: float = Compaction.volume_beta
    """Exponent of the volume in the importance (LightGaussian's global significance; 0: weight alone)."""

    def compaction(self) -> Compaction:
        """The compaction settings of this config; raises GaroConfigError for one out of range."""
        return Compaction(**{k: getattr(self, f"compact_{k}") for k in Compaction.__dataclass_fields__})
