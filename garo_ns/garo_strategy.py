"""GARO densification strategy: 3DGS's adaptive density control plus redundancy pruning.

A Gaussian is redundant when it is both
  * inactive: its mean view-space gradient norm over the iterations where it was visible is
    below tau_activity (at most n_max candidates, the least active), and
  * in a flat neighbourhood: the mean of 1 - |n_i . n_j| over its K nearest neighbours is below
    tau_curvature, with normals from the smallest-scale axis carried through the deformation.
At each GARO step at most floor(rho_max * N) redundant Gaussians are removed, flattest first.

As the paper places it, GARO runs inside adaptive density control: by default at every
refinement step (every `refine_every` steps after `refine_start_iter`, until `refine_stop_iter`),
just before the step's cloning, splitting and pruning. Activity is g_i, the mean view-space
gradient norm over the iterations in which Gaussian i was visible, read by default since the last
GARO step (`activity_window="garo_step"`), as densification's own gradient record restarts at every
refinement: that reading reproduces the paper's speed-up, while the mean over all of training
(`activity_window="training"`, the paper's wording) keeps early high gradients and prunes little. A
Gaussian made by cloning or splitting inherits its parent's record, as gsplat's ops copy every
per-Gaussian state row.
Geometry is read at the time of the GARO step's training camera: the model puts deformed
positions (`means3d`) and rotations (`quats3d`) into the rasterizer's `info`; the canonical scales
that choose the normal's axis are the strategy's own `params["scales"]`.

This strategy is the one place where the number of Gaussians changes: densification (gsplat's),
GARO (mode "off" turns it off: the D-3DGS baseline), pruning by contribution, whose per-Gaussian
contribution the model passes in (as gsplat's MCMC strategy takes the learning rate), and compaction
after densification (`compaction`, garo_ns.compaction): rounds of removal, each decided before it removes
from what leaving its candidates out of the render costs on training views (the model measures it). It reports
what it did in `state["garo_last"]`, `state["compact"]` and return values; logging is the caller's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, Literal, Optional, Tuple, Union

import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import remove
from torch import Tensor

from garo_ns.compaction.decision import CostFn, committed_cost, decide
from garo_ns.compaction.schedule import Compaction
from garo_ns.errors import check_ranges, finite_number
from garo_ns.redundancy.activity import mean_activity, record
from garo_ns.redundancy.normals import normals
from garo_ns.redundancy.select import least_contributing, select_redundant

Params = Union[Dict[str, torch.nn.Parameter], torch.nn.ParameterDict]
# State key of the compaction's summary (what each round did and why it stopped; it travels with checkpoints).
COMPACT_SUMMARY = "compact"
# The info key under which a step's gradient-norm sums pass from the activity record to the densification record.
_STEP_SUMS = "garo_step_sums"


@dataclass
class GaroStrategy(DefaultStrategy):
    """DefaultStrategy (clone, split, opacity and size pruning, opacity reset) plus GARO pruning.

    Args (beyond DefaultStrategy's):
        mode: "full" (activity then curvature), "oaa" (activity only), "gca" (curvature only,
            every visible Gaussian a candidate), "off" (no GARO: plain densification).
        tau_activity, n_max, tau_curvature, rho_max, k_neighbors: see the module docstring.
        garo_start_iter, garo_stop_iter, garo_every: GARO prunes at steps s with
            start <= s < stop and s % every == 0. None (the default) follows densification:
            every refinement step, i.e. refine_start_iter < s < refine_stop_iter, s % refine_every == 0.
        activity_window: "garo_step" (mean since the last GARO step, the default) or "training"
            (mean over all visible iterations so far).
        compaction: rounds of removal after densification (None: none); see `compact`.
        reset_at_start: also reset opacities at step 0. gsplat resets whenever
            step % reset_every == 0, step 0 included; 3DGS and D-3DGS first reset at reset_every,
            so by default (False) the initial opacities train untouched until then.
        max_gaussians: the most Gaussians densification may grow to (None: no limit). Where a refinement's
            candidates would pass it, only those of the highest gradients grow, as many as fit (`grow_budget`);
            `state["budget_held"]` counts the candidates held back at the last refinement.
    """

    mode: Literal["off", "oaa", "gca", "full"] = "full"
    tau_activity: float = 5e-5
    n_max: int = 10_000
    tau_curvature: float = 0.5
    rho_max: float = 0.02
    k_neighbors: int = 10
    garo_start_iter: Optional[int] = None
    garo_stop_iter: Optional[int] = None
    garo_every: Optional[int] = None
    activity_window: Literal["training", "garo_step"] = "garo_step"
    compaction: Optional[Compaction] = None
    reset_at_start: bool = False
    max_gaussians: Optional[int] = None

    def initialize_state(self, scene_scale: float = 1.0) -> Dict[str, Any]:
        """gsplat's state plus the keys this strategy owns. Per-Gaussian rows (None until first
        filled) are kept aligned with the Gaussians by every clone, split and removal:
        `garo_grad`/`garo_count` (activity record), `static`/`static_offset` (the static
        classification, filled by the model; `static_step` is when). `garo_last`: the counts of
        the last GARO step."""
        state = super().initialize_state(scene_scale)
        if self.mode != "off":
            state.update({"garo_grad": None, "garo_count": None, "garo_last": {}})
        state.update({"static": None, "static_offset": None, "static_step": -1, "budget_held": 0})
        if self.compaction is not None:
            state[COMPACT_SUMMARY] = self.compaction.initial_state()
        return state

    def garo_schedule(self) -> Tuple[int, int, int]:
        """(start, stop, every) of the GARO steps, with the unset ones taken from densification."""
        start = self.refine_start_iter + 1 if self.garo_start_iter is None else self.garo_start_iter
        stop = self.refine_stop_iter if self.garo_stop_iter is None else self.garo_stop_iter
        every = self.refine_every if self.garo_every is None else self.garo_every
        return start, stop, max(every, 1)

    def is_garo_step(self, step: int) -> bool:
        """Whether GARO prunes at this step."""
        if self.mode == "off":
            return False
        start, stop, every = self.garo_schedule()
        return start <= step < stop and step % every == 0

    # The hooks below take gsplat's strategy arguments (params, optimizers, state, ...) on purpose.
    def step_post_backward(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
        packed: bool = False,
    ) -> None:
        """GARO's activity and (at GARO steps) pruning, then gsplat's densification step."""
        sums = None
        if self.mode != "off" and step < self.garo_schedule()[1]:
            sums = self.update_activity(params, state, info, packed)
        if self.is_garo_step(step):
            keep = self.prune_redundant(params, optimizers, state, step, info)
            if keep is not None:
                info = restrict_info(info, keep, packed)
                sums = None  # they count the Gaussians before the removal
        if sums is not None and not packed:
            # The densification record adds the same sums: computed once a step (a shallow copy carries them).
            info = {**info, _STEP_SUMS: sums}
        if step == 0 and not self.reset_at_start and self.refine_start_iter >= 0 and self.refine_stop_iter > 0:
            # Step 0 never refines (refine_start_iter >= 0), so gsplat's step would only update the
            # gradient record and reset the opacities: do the first alone.
            self._update_state(params, state, info, packed=packed)
            return
        super().step_post_backward(params, optimizers, state, step, info, packed)

    def _grow_gs(
        self, params: Params, optimizers: Dict[str, torch.optim.Optimizer], state: Dict[str, Any], step: int
    ) -> Tuple[int, int]:
        """gsplat's growth (clone small, split large Gaussians of high gradient), within `max_gaussians`."""
        if self.max_gaussians is not None:
            keep, held = grow_budget(
                state["grad2d"] / state["count"].clamp_min(1),
                self.grow_grad2d,
                self.max_gaussians - len(params["means"]),
            )
            state["budget_held"] = held
            if held:  # the record is cleared after this refinement anyway
                state["grad2d"] = torch.where(keep, state["grad2d"], torch.zeros_like(state["grad2d"]))
        return super()._grow_gs(params, optimizers, state, step)

    def gradient_norms(self, params: Params, info: Dict[str, Any], packed: bool = False) -> Tuple[Tensor, Tensor]:
        """This iteration's NDC view-space gradient norm of each Gaussian, summed over the cameras
        that see it, and how many saw it ([N] each), normalised as the densification record is (`_norm_sums`;
        packed renders: gsplat's update run on a scratch state)."""
        if getattr(info["means2d"], "absgrad" if self.absgrad else "grad", None) is None:
            raise ValueError("info['means2d'] has no gradient: call retain_grad() before backward")
        if not packed:
            return self._norm_sums(info)
        scratch: Dict[str, Any] = {"grad2d": None, "count": None, "radii": None}
        self._update_state(params, scratch, info, packed)
        return scratch["grad2d"], scratch["count"]

    def _norm_sums(self, info: Dict[str, Any]) -> Tuple[Tensor, Tensor]:
        """Unpacked renders: the gradient norms in [-1, 1] screen units summed over the cameras that see each
        Gaussian, and how many do ([N] each), dense over [C, N] as gsplat normalises them."""
        for key in ("width", "height", "n_cameras", "radii", self.key_for_gradient):
            if key not in info:
                raise KeyError(f"info['{key}'] is required by the densification record")
        raw = getattr(info[self.key_for_gradient], "absgrad" if self.absgrad else "grad")
        # To [-1, 1] screen units per camera, as gsplat does (a product per axis: no host-built tensor).
        gx = raw[..., 0] * (info["width"] / 2.0 * info["n_cameras"])
        gy = raw[..., 1] * (info["height"] / 2.0 * info["n_cameras"])
        visible = info["radii"] > 0  # [C, N]
        norms = torch.where(visible, torch.hypot(gx, gy), torch.zeros_like(gx))
        return norms.sum(0), visible.sum(0).to(torch.float32)

    def _update_state(self, params: Params, state: Dict[str, Any], info: Dict[str, Any], packed: bool = False) -> None:
        """gsplat's densification record (gradient-norm sums, visibility counts, largest screen radius) with the
        same normalisation, computed densely over [C, N] for unpacked renders: gsplat selects the visible
        Gaussians with boolean indexing, which waits for the GPU three times every training step."""
        if packed:
            super()._update_state(params, state, info, packed)
            return
        sums, counts = info[_STEP_SUMS] if _STEP_SUMS in info else self._norm_sums(info)
        n, dev = len(params["means"]), sums.device
        for key in ("grad2d", "count"):
            if state[key] is None:
                state[key] = torch.zeros(n, device=dev)
        state["grad2d"] += sums
        state["count"] += counts.to(state["count"].dtype)
        if self.refine_scale2d_stop_iter > 0:
            if state["radii"] is None:
                state["radii"] = torch.zeros(n, device=dev)
            visible = info["radii"] > 0
            screen = torch.where(visible, info["radii"] / float(max(info["width"], info["height"])), 0.0)
            state["radii"] = torch.maximum(state["radii"], screen.amax(0))

    def update_activity(
        self, params: Params, state: Dict[str, Any], info: Dict[str, Any], packed: bool
    ) -> Tuple[Tensor, Tensor]:
        """Add this iteration's gradient norms of the visible Gaussians to the activity record; returns the
        iteration's sums and counts (`gradient_norms`)."""
        n = len(params["means"])
        dev = params["means"].device
        if state["garo_grad"] is None or state["garo_grad"].shape[0] != n:
            state["garo_grad"] = torch.zeros(n, device=dev)
            state["garo_count"] = torch.zeros(n, device=dev)
        sums = self.gradient_norms(params, info, packed)
        record(state["garo_grad"], state["garo_count"], *sums)
        return sums

    def prune_redundant(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        info: Dict[str, Any],
    ) -> Tensor | None:
        """Remove redundant Gaussians; returns the kept mask (None when nothing was removed)."""
        with torch.no_grad():  # a block, not a decorator: mutmut mutates undecorated methods only
            start = time.perf_counter()
            n = len(params["means"])
            points = info.get("means3d")
            quats = info.get("quats3d")
            # Without the model's geometry (or after a size change) use the canonical Gaussians.
            if points is None or points.shape[0] != n:
                points = params["means"].detach()
            if quats is None or quats.shape[0] != n:
                quats = params["quats"].detach()
            scales = torch.exp(params["scales"].detach())
            result = select_redundant(
                mean_activity(state["garo_grad"], state["garo_count"]),
                state["garo_count"],
                points,
                normals(quats, scales) if self.mode != "oaa" else points,
                self.mode,
                self.tau_activity,
                self.n_max,
                self.tau_curvature,
                self.rho_max,
                self.k_neighbors,
            )
            prune = result["prune"]
            keep = None
            if prune.numel() > 0:
                mask = torch.zeros(n, dtype=torch.bool, device=params["means"].device)
                mask[prune] = True
                remove(params=params, optimizers=optimizers, state=state, mask=mask)
                keep = ~mask
            if self.activity_window == "garo_step":  # a fresh window for the next GARO step
                state["garo_grad"].zero_()
                state["garo_count"].zero_()
            if params["means"].is_cuda:
                torch.cuda.synchronize()
            state["garo_last"] = {
                "step": step,
                "candidates": int(result["candidates"]),
                "redundant": int(result["redundant"]),
                "pruned": int(prune.numel()),
                "seconds": time.perf_counter() - start,
                "num_gaussians": len(params["means"]),
            }
            return keep

    @torch.no_grad()
    def prune_by_contribution(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        contribution: Tensor,
        ratio: float,
    ) -> int:
        """Remove the floor(ratio * N) Gaussians with the smallest `contribution` [N] (e.g. their
        summed blending weight over the training views); returns how many were removed."""
        mask = least_contributing(contribution, ratio)
        if bool(mask.any()):
            remove(params=params, optimizers=optimizers, state=state, mask=mask)
        return int(mask.sum())

    def compact(
        self,
        params: Params,
        optimizers: Dict[str, torch.optim.Optimizer],
        state: Dict[str, Any],
        step: int,
        cost: Optional[CostFn],
        importance: Callable[[], Tensor],
        last_step: Optional[int] = None,
    ) -> Optional[Dict[str, Any]]:
        """The compaction round of `step`, if one falls on it, or the end of compaction at `last_step`
        (garo_ns.compaction.schedule says what a round does). `cost(mask)` gives each guard view's PSNR
        loss, in dB, of rendering the Gaussians now without those of `mask` (None: there are no training
        views); `importance` a score [N] of each (the lowest are the candidates). The round decides
        before it removes (garo_ns.compaction.decision): nothing is removed unless its measured cost is
        within bounds. Returns the round's record (None when nothing ran); a record with `stop` ends the
        compaction, whose summary is `state["compact"]`."""
        c = self.compaction
        summary = state.get(COMPACT_SUMMARY) if c is not None else None
        if c is None or summary is None or summary.get("reason") is not None:
            return None
        at_round = c.is_round(step, self.refine_stop_iter)
        at_end = last_step is not None and step >= last_step
        if not (at_round or at_end):
            return None
        n = len(params["means"])
        summary.setdefault("spent_db", 0.0)  # a summary written before the budget existed
        if summary["num_gaussians_start"] is None:
            summary["num_gaussians_start"] = n
        event: Dict[str, Any] = {
            "round": len(summary["rounds"]),
            "step": step,
            "num_before": n,
            "share": None,
            "cost_mean_db": None,
            "cost_worst_db": None,
            "removed": 0,
            "num_after": n,
            "tries": [],
        }
        if at_end:  # every kept round was measured when made: nothing is left to check
            if not summary["rounds"]:
                first = c.first_step(self.refine_stop_iter)
                return self._stop(state, event, "training_ended", f"before the first round (step {first})")
            return self._stop(state, event, "training_ended", f"at step {step}")
        if n == 0:
            return self._stop(state, event, "empty_model", "nothing to compact")
        if event["round"] >= c.max_rounds:
            return self._stop(state, event, "max_rounds", f"{c.max_rounds} rounds")
        if n <= c.min_gaussians:
            return self._stop(state, event, "min_gaussians", f"{n} <= {c.min_gaussians}")
        if cost is None:
            return self._stop(state, event, "no_training_views", "the model was given no training data")
        with torch.no_grad():
            decision = decide(importance(), n, c, summary["spent_db"], cost)
        tries = decision["tries"]
        event["tries"] = tries
        if tries:
            last = tries[-1]
            event.update(share=last["share"], cost_mean_db=last["cost_mean_db"], cost_worst_db=last["cost_worst_db"])
        if decision["mask"] is None:
            return self._stop(state, event, decision["stop"], decision["detail"])
        with torch.no_grad():
            remove(params=params, optimizers=optimizers, state=state, mask=decision["mask"])
        event.update(removed=tries[-1]["count"], num_after=len(params["means"]))
        summary["spent_db"] += committed_cost(tries[-1]["cost_worst_db"])
        summary["rounds"].append(event)
        summary["num_gaussians_end"] = event["num_after"]
        return event

    def _stop(self, state: Dict[str, Any], event: Dict[str, Any], reason: str, detail: str) -> Dict[str, Any]:
        """End the compaction: record the last round (nothing removed in it) and why it stopped."""
        summary = state[COMPACT_SUMMARY]
        event["stop"] = reason
        summary["rounds"].append(event)
        summary.update(reason=reason, detail=detail, stopped_step=event["step"], num_gaussians_end=event["num_after"])
        return event


def garo_scalars(state: Dict[str, Any], step: int) -> Dict[str, float]:
    """What the GARO step of `step` did, as scalars to log (`garo/<count>`); empty when none ran."""
    last = state.get("garo_last") or {}
    if last.get("step") != step:
        return {}
    return {
        f"garo/{key}": float(last[key]) for key in ("candidates", "redundant", "pruned", "seconds", "num_gaussians")
    }


# The rasterizer's info entries with one value per Gaussian and camera: [C, N, ...] unpacked, [nnz, ...] packed.
_PER_VIEW_KEYS = ("radii", "depths", "conics", "opacities", "compensations")


def grow_budget(grads: Tensor, threshold: float, room: int) -> Tuple[Tensor, int]:
    """Which Gaussians may grow ([N] bool) when at most `room` may (each clone or split adds one), and how many of
    those above `threshold` are held back: all of them when they fit, else the `room` of the highest gradients."""
    high = grads > threshold
    n_high = int(high.sum())
    room = max(int(room), 0)
    if n_high <= room:
        return high, 0
    keep = torch.zeros_like(high)
    if room > 0:
        keep[torch.topk(torch.where(high, grads, torch.full_like(grads, -1.0)), room).indices] = True
    return keep, n_high - room


def restrict_info(info: Dict[str, Any], keep: Tensor, packed: Optional[bool] = None) -> Dict[str, Any]:
    """The rasterizer's info restricted to the kept Gaussians (`keep` [N], bool), so that
    DefaultStrategy's bookkeeping after GARO sees consistent sizes. Unpacked, the per-view entries are
    [C, N, ...] and lose the removed columns; packed, they are [nnz, ...], one row per visible (camera,
    Gaussian) pair: the removed Gaussians' rows go and `gaussian_ids` are renumbered to the kept order.
    `packed` None: packed when the info has `gaussian_ids` (gsplat leaves them None unpacked)."""
    packed = info.get("gaussian_ids") is not None if packed is None else packed
    out = dict(info)
    m2d = info["means2d"]
    if packed:
        rows = keep[info["gaussian_ids"]]  # [nnz]: the pairs whose Gaussian stays
        new_ids = torch.cumsum(keep.long(), 0) - 1  # old index -> index among the kept
        for key in (*_PER_VIEW_KEYS, "camera_ids"):
            if isinstance(info.get(key), Tensor):
                out[key] = info[key][rows]
        out["gaussian_ids"] = new_ids[info["gaussian_ids"][rows]]
    else:
        rows = (slice(None), keep)  # [C, N] -> [C, kept]
        for key in _PER_VIEW_KEYS:
            if isinstance(info.get(key), Tensor) and info[key].dim() >= 2:
                out[key] = info[key][rows]
    filtered = m2d.detach()[rows].clone()
    filtered.grad = None if m2d.grad is None else m2d.grad[rows].clone()
    out["means2d"] = filtered
    for key in ("means3d", "quats3d", "scales3d"):
        if isinstance(info.get(key), Tensor) and info[key].shape[0] == keep.shape[0]:
            out[key] = info[key][keep]
    return out


@dataclass
class GaroSettings:
    """GARO's settings and the expert pruning by contribution, part of the model config."""

    garo_mode: Literal["off", "oaa", "gca", "full"] = "full"
    """off: plain densification (the D-3DGS baseline); oaa: activity only (the paper's "w/o GCA");
    gca: curvature only, every visible Gaussian a candidate (the paper's "w/o OAA"); full: activity
    candidates filtered by curvature (the paper's method)."""
    tau_activity: float = GaroStrategy.tau_activity
    """Candidates are Gaussians whose mean view-space gradient norm is below this (the paper's)."""
    n_max: int = GaroStrategy.n_max
    """At most this many candidates (the least active) per GARO step (the paper's)."""
    tau_curvature: float = GaroStrategy.tau_curvature
    """Candidates whose curvature is below this are redundant (the paper's)."""
    rho_max: float = GaroStrategy.rho_max
    """At most floor(rho_max * N) Gaussians are pruned per GARO step (the paper's default)."""
    k_neighbors: int = GaroStrategy.k_neighbors
    """Neighbours for the curvature estimate (the paper's K)."""
    garo_start: Optional[int] = None
    """First step at which GARO may prune; None: the first refinement step (after `warmup_length`)."""
    garo_stop: Optional[int] = None
    """GARO prunes up to (not including) this step; None: `stop_split_at`, where densification ends."""
    garo_every: Optional[int] = None
    """GARO prunes every this many steps; None: `refine_every` (every densification step, as the paper)."""
    garo_activity_window: Literal["training", "garo_step"] = GaroStrategy.activity_window
    """garo_step: g_i is the mean since the previous GARO step, as densification's gradient record
    restarts at every refinement (the reading that reproduces the paper's speed-up: jumpingjacks at
    40k, 1.90x FPS at -0.21 dB); training: the mean over every iteration of training in which
    Gaussian i was visible (the paper's text; it pruned 1.3% by 8k steps)."""
    prune_contribution_ratio: float = 0.0
    """Expert knob: at each of `prune_contribution_steps`, prune this fixed fraction of the Gaussians
    with the smallest summed blending weight over the training views (0: off). The same share for
    every scene; `compact` chooses each scene's share from its training views instead."""
    prune_contribution_steps: Tuple[int, ...] = (20000, 30000)
    """Steps of the contribution pruning (after densification has ended, so the rest can adapt)."""

    def validate_garo(self) -> None:
        """Raise GaroConfigError, naming the flag, for a GARO setting out of its range (NaN included): a
        rho_max above 1 or a negative threshold would not fail later, it would prune what the user did not
        ask for."""

        def step(value: Optional[int], low: int) -> bool:
            return value is None or value >= low

        checks = {
            "rho-max": (finite_number(self.rho_max) and 0 <= self.rho_max <= 1, "in [0, 1]"),
            "tau-activity": (finite_number(self.tau_activity) and self.tau_activity >= 0, "a number >= 0"),
            "tau-curvature": (finite_number(self.tau_curvature) and self.tau_curvature >= 0, "a number >= 0"),
            "n-max": (self.n_max >= 0, ">= 0"),
            "k-neighbors": (self.k_neighbors >= 1, ">= 1"),
            "garo-start": (step(self.garo_start, 0), "a step >= 0 or None"),
            "garo-stop": (step(self.garo_stop, 0), "a step >= 0 or None"),
            "garo-every": (step(self.garo_every, 1), ">= 1 or None"),
            "prune-contribution-ratio": (
                finite_number(self.prune_contribution_ratio) and 0 <= self.prune_contribution_ratio < 1,
                "in [0, 1)",
            ),
        }
        check_ranges(self, checks)

    def garo_arguments(self) -> Dict[str, Any]:
        """GaroStrategy's GARO arguments from these settings."""
        return dict(
            mode=self.garo_mode,
            tau_activity=self.tau_activity,
            n_max=self.n_max,
            tau_curvature=self.tau_curvature,
            rho_max=self.rho_max,
            k_neighbors=self.k_neighbors,
            garo_start_iter=self.garo_start,
            garo_stop_iter=self.garo_stop,
            garo_every=self.garo_every,
            activity_window=self.garo_activity_window,
        )
