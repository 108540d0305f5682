"""Which render switches a model uses when its config leaves them to the plugin (None: "auto").

A finished model renders fast without flags. Outside a training run (ns-viewer, ns-render,
garo-eval, the benchmark loading a checkpoint) the exact switches (`cuda_graph`, `lean_raster`: same
arithmetic, fewer launches) are on wherever CUDA runs, and the approximate `static_skip` is on when,
measured at the end of training on training views spread over time, it changes the render by at most
`bound_db` against the plain render of the same view, on every view checked (`view_change_db`). A
loaded model says in one line which switches it uses and what each approximate one was measured to
change. During a training run, and so for a viewer attached to one, every switch left to auto stays
off: what the user watches is what trains. A switch set explicitly is used as set, in both cases.

The approximate switches `resolve` measures are `static_skip` and the time table; the deformation MLP
always runs in fp32 (the reduced-precision fields were deleted: benchmarks/HISTORY.md).
"""

from __future__ import annotations

import hashlib
import math
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Callable, Dict, Iterator, List, Literal, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garo_ns.render.backend import Backend, resolve_backend
from garo_ns.render.frame import FrameSettings
from garo_ns.render.graphs import versions
from garo_ns.render.time_table import TableSpec, TimeTable, spec_for

EXACT = ("cuda_graph", "lean_raster")
"""Switches that change no pixel: on by default outside training wherever CUDA runs."""

DEFAULT_BOUND_DB = 0.02
"""Largest change (dB, `worst_view_change_db`) on any checked training view for which an approximate
switch is turned on by default: well below what a viewer can see, and the bound the benchmark holds
render paths to."""

DEFAULT_SWITCH_VIEWS = 32
"""Training views the approximate switches are measured on (all of them when there are fewer), spread
over time: one bad frame of a motion is what the bound must catch."""

APPROXIMATE = "static_skip"
"""The approximate switch `resolve` measures, and the name its loss is recorded under. Records written while
MLP precisions were measured too (since deleted) also hold an entry for each: kept as measured, never used."""

TABLE = "time_table"
"""The time table (garo_ns.render.time_table): measured like `static_skip`, with every measured view halfway
between two keyframes of the table's spacing."""

Measure = Callable[[FrameSettings], float]
"""Renders training views with the given switches and returns the largest change (dB) of any view
against the same views rendered plain (`worst_view_change_db`)."""


def resolve(
    requested: Mapping[str, Any],
    training_run: bool,
    cuda: bool,
    measure: Optional[Measure] = None,
    bound_db: float = DEFAULT_BOUND_DB,
) -> Tuple[FrameSettings, Dict[str, float]]:
    """The switches to render with, and the measured change (dB) of each approximate switch tried.

    Args:
        requested: the config's value of each FrameSettings field; None leaves it to this function.
        training_run: whether the model belongs to a run that is training (or will train).
        cuda: whether the model renders on CUDA (graphs and the lean path need it).
        measure: see `Measure`; without one the approximate switches left to auto stay off.
        bound_db: see DEFAULT_BOUND_DB.
    """
    if not (bound_db >= 0 and math.isfinite(bound_db)):
        raise ValueError(f"the render switches' PSNR bound must be a finite number >= 0, got {bound_db}")
    names = {f.name for f in fields(FrameSettings)}
    unknown = set(requested) - names
    if unknown:
        raise ValueError(f"unknown render switches {sorted(unknown)}; known: {sorted(names)}")
    settings = FrameSettings(**{k: v for k, v in requested.items() if v is not None})
    fast = not training_run
    for name in EXACT:
        if requested.get(name) is None:
            settings = replace(settings, **{name: fast and cuda})
    tried: Dict[str, float] = {}
    if not fast or measure is None:
        return settings, tried

    if requested.get(APPROXIMATE) is None:
        trial = replace(settings, static_skip=True, time_table=False)
        tried[APPROXIMATE] = float(measure(trial))
        if tried[APPROXIMATE] <= bound_db:  # False for NaN too
            settings = replace(settings, static_skip=True)
    if requested.get(TABLE) is None:
        # Measured alone: with the table on, every Gaussian's offsets come from it (static ones included).
        tried[TABLE] = float(measure(replace(settings, time_table=True, static_skip=False)))
        if tried[TABLE] <= bound_db:
            settings = replace(settings, time_table=True)
    return settings, tried


def replay(tried: Mapping[str, float]) -> Measure:
    """A Measure answering from losses `resolve` recorded earlier (at the end of training, where the
    training views are at hand); a trial never measured counts as an infinite loss."""
    return lambda trial: float(tried.get(TABLE if trial.time_table else APPROXIMATE, math.inf))


def measure_on_views(render: Callable[[int, Optional[FrameSettings]], Tensor], targets: Sequence[Tensor]) -> Measure:
    """A Measure over views: `render(i, None)` is view i rendered plain (fp32, every Gaussian),
    `render(i, trial)` the same view with the trial's switches; `targets[i]` its ground truth."""
    gt = torch.stack([t.float() for t in targets])
    reference = torch.stack([render(i, None).float() for i in range(len(targets))])
    return lambda trial: worst_view_change_db(
        reference, torch.stack([render(i, trial).float() for i in range(len(gt))]), gt
    )


def view_change_db(reference: Tensor, trial: Tensor, targets: Tensor) -> Tensor:
    """Per view, how far (dB, >= 0) `trial` renders are from the plain `reference` renders of the same
    views, with `targets` their ground truth ([V, H, W, 3] each, values in [0, 1]): the larger of

    * the change of PSNR against the ground truth, in either direction (a switch that makes a view
      "better" changed it as much as one that makes it worse), and
    * 10 log10(1 + MSE(trial, reference) / MSE(reference, targets)): the PSNR change the trial's pixel
      change would cause if it were unrelated to the plain render's error. It is the PSNR of one render
      against the other, put on the scale of the view's own error, and is zero only when no pixel
      changes, so a trial cannot pass by moving pixels in a way that happens to leave its error
      against this ground truth as it was.
    """
    dims = tuple(range(1, reference.dim()))
    mse_plain = ((reference - targets) ** 2).mean(dim=dims).clamp_min(1e-12)
    mse_trial = ((trial - targets) ** 2).mean(dim=dims).clamp_min(1e-12)
    mse_change = ((trial - reference) ** 2).mean(dim=dims)
    shift = (10 * torch.log10(mse_trial / mse_plain)).abs()
    spread = 10 * torch.log10(1 + mse_change / mse_plain)
    return torch.maximum(shift, spread)


def worst_view_change_db(reference: Tensor, trial: Tensor, targets: Tensor) -> float:
    """The largest `view_change_db` over views; a trial render that is not finite anywhere counts as
    an infinite change."""
    if not bool(torch.isfinite(trial).all()):
        return math.inf
    return float(view_change_db(reference, trial, targets).max())


@dataclass
class RenderSettings:
    """The rasterizer and the render-time speed switches, part of the model config. Each switch is
    measured by the benchmark. None (the default) leaves a switch to `resolve`: off in a training run
    (and for a viewer attached to it); for a finished model, the exact ones (cuda_graph, lean_raster)
    on where CUDA runs, static_skip on when its change against the plain render on training views,
    measured at the end of training, is within switch_bound_db, and the time table likewise. A value set is
    used as set."""

    rasterizer: Backend = "auto"
    """'cuda' (gsplat kernels), 'reference' (pure torch), or 'auto': cuda when it can run."""
    static_skip: Optional[bool] = None
    """When not training, Gaussians classified static skip the MLP; their offsets are frozen at
    their time average (the classification itself always runs during training; it is cheap)."""
    time_table: Optional[bool] = None
    """When not training, take the Gaussians at a time from a table of the deformation field's offsets at
    keyframe times, interpolated between the two (or four) around the time (garo_ns.render.time_table): the
    MLP leaves the frame, except for the few Gaussians whose motion the table cannot follow. None: on for a
    finished model when its change against the plain render, measured at the end of training on training
    views each placed halfway between two keyframes, is within switch_bound_db."""
    time_table_keys_per_frame: int = 2
    """Keyframe intervals per gap between consecutive training times (keys sit halfway between them) of the
    first table tried at the end of training; while a table misses the bound, one with twice the keys is tried,
    up to time_table_max_keys_per_frame and within the memory budget."""
    time_table_max_keys_per_frame: int = 64
    """The densest table tried at the end of training, or as many keys as time_table_budget_mb holds if fewer. The
    change halfway between keys about halves per doubling (ReLU kinks in the trajectories): 0.0056, 0.0027 and
    0.0016 dB on the worst test view of a jumpingjacks GARO model at 16, 32 and 64 keys per frame
    (benchmarks/results/time_table_orders_jumpingjacks_H200.json); with 32 keys the faster recipe's jumpingjacks
    models changed their training views by 0.0215 and 0.022 dB, just over the bound."""
    time_table_margin: float = 0.5
    """The keyframe ladder stops at the first table whose change on the training views is within this share of
    switch_bound_db (then tries fewer keys between it and the rung before, `trimmed_rung`; else it takes the table
    that changed them least, judged against the whole bound): the
    training views are a sample, and a test view can change more (mutant's compacted model at 40k: 0.021 dB on a
    test view against 0.0104 on the training views, 4 keys per frame). More keys cost memory, not frame time: a
    frame reads two keys whatever their number (benchmarks/results/time_table_orders_jumpingjacks_H200.json). A rung
    whose build samples the field more often than its preview (`TimeTable.preview`: only the keys around the measured
    views and midpoints) is previewed first, and built only if its preview comes within the margin."""
    time_table_budget_mb: float = 6144.0
    """Largest time table in MB (int16: 20 bytes per moving Gaussian and key, so 32 keys per frame of 200
    frames take 4.4 GB at 34k Gaussians). At the end of training a model that would need more gets fewer
    keyframes; a loaded model whose recorded table exceeds it renders through the network (and says so)."""
    time_table_window_mb: Optional[float] = None
    """Largest time table in MB that a finished model holds while it renders (None: the whole table). A larger table
    is held a window of time at a time: the keys of the stretch of time around the frame being shown, at the same
    times as the whole table's (so the same frames there), as many as this holds; when the time leaves the window,
    the next one is built before that frame (a pause of the window's build). Less memory and a quicker first frame
    after a load (docs/rendering.md). The end of training measures the whole table, within time_table_budget_mb."""
    time_table_precision: Literal["int16", "int8", "fp16", "fp32"] = "int16"
    """Storage of the table's fine residuals (each key less the mid-range offsets and less the line between its two
    fp32 anchors); int16 with a scale per Gaussian and channel resolves each Gaussian's bends evenly at fp16's size."""
    time_table_try_int8: bool = True
    """When the memory budget caps an int16 ladder before a table comes within the margin, go on with int8 fine
    residuals (same scales, 127 levels: about 1.8x the keys in the same bytes), measured like every rung and taken
    only if a table changes the training views less. Jumpingjacks' compacted model at 40k missed the bound by
    0.0023 dB at the most int16 keys 6 GB hold, its error falling about as 1/K
    (benchmarks/results/table40k_jumpingjacks2_H200.json)."""
    time_table_tf32: bool = False
    """Build time tables (and their previews) with TF32 matrix products on CUDA (`tf32_products` in
    garo_ns.render.time_table): 2.17x less build time on an H200 (benchmarks/results/table_sampling_tf32_H200.json),
    but the rounding stays in every key. Measured as built, TF32 tables of 40k models missed the bound at any number
    of keys: their change stopped falling with more keys, at 0.028 to 0.078 dB on standup's three models and 0.027 on
    jumpingjacks' compacted one (`intervals_previewed_db` in benchmarks/results/table1_*_H200.json at 1e910ef), so
    they are off by default. No effect on a CPU."""
    time_table_cache: bool = True
    """A loaded model writes its whole time table to `<run>/time_tables/` at its first load and reads it at later
    loads instead of building it (garo_ns.render.table_cache): a file the size of the table (jumpingjacks'
    `garo-deform` at 40k: 2.6 GB) for a load without the build. Named by a hash of the model's values and the table,
    so other values build (and write) their own; nothing is overwritten. False: nothing read or written."""
    time_table_tolerance: float = 0.03
    """Largest interpolation error at keyframe midpoints (positions in scene extents; rotation offsets absolute;
    scales as log-scale offsets under `deform-scale-offset log`, in scene extents under `linear`) for a Gaussian to
    be tabled; those over it stay on the network."""
    cache_deformation: bool = True
    """When not training, reuse the deformed Gaussians if the same time is rendered again and no
    parameter changed (the viewer re-renders one time for every camera move). Exact."""
    cuda_graph: Optional[bool] = None
    """When not training on CUDA, run everything between the time and the rasterizer (MLP,
    composition, activations) as one captured CUDA graph instead of dozens of kernel launches;
    captured again when the Gaussians or the render switches change. Same arithmetic as without.
    With `lean_raster` too, the camera's share (projection, view directions, visibility) is a
    second graph, fed the camera's matrices."""
    lean_raster: Optional[bool] = None
    """When not training on CUDA, call gsplat's kernels directly instead of its general Python
    wrapper (garo_ns.render.backend.rasterize_lean): same kernels and pixels, less Python per frame."""
    frame_graph: bool = False
    """With `cuda_graph` and `lean_raster` on: the camera's whole share of a frame (projection, colours, tile lists,
    compositing) as one graph replay, its tile lists at a fixed length and cut to the pairs whose pixels can show
    (garo_ns.render.frame_graph); the same pixels but for the colours' float rounding. Not measured yet: off."""
    switch_bound_db: float = DEFAULT_BOUND_DB
    """Largest change against the plain render (dB, garo_ns.render.switches.view_change_db), on any
    training view measured at the end of training, with which an approximate switch left to None is
    turned on for a finished model."""
    switch_views: int = DEFAULT_SWITCH_VIEWS
    """Training views, spread over time, on which the approximate switches are measured at the end of
    training (all of them when there are fewer)."""

    def requested_switches(self) -> Dict[str, Any]:
        """The config's value of each render switch (None: left to `resolve`)."""
        return {k: getattr(self, k) for k in FrameSettings.__dataclass_fields__}

    def renders_on_cuda(self, device: torch.device) -> bool:
        """Whether rendering on `device` uses gsplat's CUDA kernels."""
        return resolve_backend(self.rasterizer, device) == "cuda"


CPU_TABLE_EVALUATIONS = 2e6
"""The most Gaussians (passes of the deformation field times Gaussians) a time table's build may run the field on
where a CPU renders and the table is not asked for: a few minutes at the 4,900 a second of D-3DGS's field measured
on a 2-core CPU running other jobs (about 20 times a CPU frame of 5,000 Gaussians)."""

MEASURE_VERSION = "view_change_db"
"""Names the check a record's losses come from (`worst_view_change_db`). Records written before it
(a one-sided PSNR loss on 16 views, which a render could pass by changing pixels without raising its
error) are not trusted: their approximate switches stay off unless set."""


def table_ladder(model: Any, cfg: RenderSettings) -> Tuple[List[TableSpec], str]:
    """The tables the end of training may measure, sparsest first, and why there is none if so: from
    `time_table_keys_per_frame` keys per frame, doubling up to `time_table_max_keys_per_frame` or as many as the budget
    holds; where the budget caps an int16 ladder first, int8 rungs go on from there (`time_table_try_int8`)."""
    precisions = [cfg.time_table_precision]
    if cfg.time_table_try_int8 and cfg.time_table_precision == "int16":
        precisions.append("int8")
    specs: List[TableSpec] = []
    why = ""
    keys = max(1, cfg.time_table_keys_per_frame)
    top = max(cfg.time_table_max_keys_per_frame, cfg.time_table_keys_per_frame)
    gaps = max(int(model.train_times.numel()) - 1, 1) if model.train_times is not None else 1
    for precision in precisions:
        capped = False
        while keys <= top and not capped:
            spec, reason = spec_for(
                model.train_times,
                keys,
                model.num_points,
                cfg.time_table_budget_mb,
                precision,
                cfg.time_table_tolerance,
                model.scene_extent,
            )
            if spec is None or (specs and spec.intervals <= specs[-1].intervals):  # nothing denser fits
                why, capped = reason or why, True
                break
            specs.append(spec)
            capped = spec.intervals < keys * gaps  # the budget held fewer keys than asked for
            keys *= 1 if capped else 2
        if not capped:  # the densest table asked for fits: no other precision needed
            break
    return specs, why


TRIM_AIM = 0.8
"""Where between 0 and the margin a trimmed rung (`trimmed_rung`) aims its change: the fit between two rungs is a
guess, and a trimmed rung that misses the margin costs the table one more build."""


def trimmed_rung(
    over: TableSpec, over_db: float, within: TableSpec, within_db: float, margin: float
) -> Optional[TableSpec]:
    """A rung between two neighbours of the ladder, `over` the margin and `within` it: the intervals at which the
    change, fitted as a power of the intervals through the two (log-log), comes to TRIM_AIM of the margin, where that
    saves at least a sixth of `within`'s keys; None otherwise. The ladder doubles its keys, so its first rung within
    the margin can hold up to twice the keys needed: the change fell as about 1/K^1.7 to 1/K^2.2 near the bound
    (standup's fp32 rungs, benchmarks/results/table_precision_standup_fp32_H200.json)."""
    target = TRIM_AIM * margin
    if over.precision != within.precision or not (over_db > margin >= within_db > 0):
        return None
    slope = math.log(over_db / within_db) / math.log(within.intervals / over.intervals)
    intervals = math.ceil(over.intervals * (over_db / target) ** (1.0 / min(max(slope, 0.5), 3.0)))
    if not over.intervals < intervals <= within.intervals * 5 / 6:
        return None
    return replace(within, intervals=intervals)


def rung_name(spec: TableSpec, cfg: RenderSettings) -> str:
    """A ladder rung's name in the record: its intervals, and its precision where not the configured one."""
    return str(spec.intervals) if spec.precision == cfg.time_table_precision else f"{spec.intervals} {spec.precision}"


class SwitchDecision:
    """The switches one model renders with outside training: the changes measured at the end of its
    training (`record`, kept in checkpoints) and the settings they give, decided once per change of
    the config, the record or the bound (a frame asks twice). `step`: the model's current step; a record
    measured at another step describes another state of the model and is not trusted."""

    def __init__(
        self, step: Optional[Callable[[], int]] = None, params: Optional[Callable[[], Sequence[Tensor]]] = None
    ) -> None:
        self.record: Optional[Dict[str, Any]] = None
        self._step = step
        # The tensors a measurement describes (the Gaussians and the field): a record names their fingerprint, and
        # one whose tensors now hold other values (fp16 storage, a compact file, an edit) is not trusted.
        self._params = params
        self._fingerprint_of: Optional[Tuple[Any, str]] = None  # (their versions, the fingerprint)
        self._frame_versions: Optional[Tuple[Any, ...]] = None  # their versions, taken once for a frame (`one_frame`)
        self._spec_of: Optional[Tuple[Any, TableSpec]] = None  # (the record's spec, as a TableSpec)
        # What the frame path built for a spec (its keys, order, Gaussians on the network), or None: the load line
        # names the table in use, which a load on another device may build otherwise than the record says.
        self.table_built: Callable[[TableSpec], Optional[Dict[str, Any]]] = lambda spec: None
        self._cache: Optional[Tuple[Any, Any, FrameSettings]] = None
        self._measuring: Optional[TableSpec] = None  # the table being measured at the end of training
        self.table_override: Optional[TableSpec] = None  # a table to render with instead of the record's
        # Why a table could not be built (the model's frame path knows), or None: such a table is not in use.
        self.table_failure: Callable[[TableSpec], Optional[str]] = lambda spec: None

    def failed_table(self, spec: Optional[TableSpec] = None) -> Optional[str]:
        """Why the table to render with (`spec`, default `table_spec()`) could not be built, or None (built, not yet
        tried, or no table)."""
        spec = self.table_spec() if spec is None else spec
        return self.table_failure(spec) if spec is not None else None

    def parameters_changed(self) -> None:
        """Forget what was decided from the parameters: call after replacing their values (a checkpoint or compact
        file loaded, storage rounding undone), so the next frame compares the record with the values now held.
        A frame does not look at the parameters itself: that would cost every frame a pass over them."""
        self._cache = None
        self._fingerprint_of = None

    @contextmanager
    def one_frame(self, tensors: Sequence[Tensor]) -> Iterator[Tuple[Any, ...]]:
        """Inside, the measured tensors' versions are these `tensors`' (the same list `params` gives), taken once: a
        frame asks for its switches and its table several times, and listing the parameters and their versions
        each time was most of a tabled frame's host time. Yields the versions, for the frame's own caches."""
        self._frame_versions = versions(tensors)
        try:
            yield self._frame_versions
        finally:
            self._frame_versions = None

    def fingerprint(self) -> Optional[str]:
        """A hash of the measured tensors' values (None without them); computed again only when one changed."""
        if self._params is None:
            return None
        tensors = None if self._frame_versions is not None else list(self._params())
        # Of the parameters themselves: a detached view would be a new tensor every call.
        key = self._frame_versions if tensors is None else versions(tensors)
        if self._fingerprint_of is None or self._fingerprint_of[0] != key:
            tensors = list(self._params()) if tensors is None else tensors
            digest = hashlib.sha1()
            for t in tensors:
                digest.update(t.detach().float().contiguous().cpu().numpy().tobytes())
            self._fingerprint_of = (key, digest.hexdigest()[:16])
        return self._fingerprint_of[1]

    def distrust(self) -> Optional[str]:
        """Why the record is not trusted, or None (no record, or a trusted one)."""
        if not self.record:
            return None
        if self.record.get("measure") != MEASURE_VERSION:
            return "measured by an older one-sided check"
        if self._step is not None and self.record.get("step") != self._step():
            return f"measured at step {self.record.get('step')}, the model is at step {self._step()}"
        recorded = self.record.get("params")
        if recorded is not None and self._params is not None and recorded != self.fingerprint():
            return "the parameters changed since they were measured (fp16 storage, a compact file, an edit)"
        return None

    def trusted_record(self) -> Optional[Dict[str, Any]]:
        """The record, when it was measured with the current check (see MEASURE_VERSION) on this state of
        the model (the same step)."""
        return self.record if self.record and self.distrust() is None else None

    def table_spec(self) -> Optional[TableSpec]:
        """The time table to render with when `time_table` is on: the one being measured, else the trusted
        record's."""
        return self._record_spec(self.trusted_record())

    def _record_spec(self, record: Optional[Dict[str, Any]]) -> Optional[TableSpec]:
        """The table `table_spec` gives where `record` is the trusted record (or None)."""
        if self._measuring is not None or self.table_override is not None:
            return self._measuring or self.table_override
        spec = ((record or {}).get(TABLE) or {}).get("spec")
        if not spec:
            return None
        if self._spec_of is None or self._spec_of[0] is not spec:  # made once per record, not every frame
            self._spec_of = (spec, TableSpec(**spec))
        return self._spec_of[1]

    def _table_refusal(self, config: RenderSettings, device: Optional[torch.device] = None) -> Optional[str]:
        """Why a recorded table is not used on load although it met the bound, or None."""
        table = (self.trusted_record() or {}).get(TABLE) or {}
        info = table.get("info") or {}
        if table.get("spec") and info.get("gaussians") and device is not None and torch.device(device).type != "cuda":
            # A CPU runs the field at thousands of Gaussians a second: a table built for a GPU (hundreds of passes
            # over tens of thousands of Gaussians) would keep the first frame waiting an hour for frames that the
            # network renders in seconds.
            evaluations = TimeTable.field_passes(TableSpec(**table["spec"])) * int(info["gaussians"])
            if evaluations > CPU_TABLE_EVALUATIONS:
                return (
                    f"on a CPU its build would run the deformation field on {evaluations:.2g} Gaussians before the "
                    f"first frame (more than {CPU_TABLE_EVALUATIONS:.0g}); frames render through the network "
                    "(--pipeline.model.time-table True builds it anyway)"
                )
        if table.get("spec") and "anchor_every" not in table["spec"]:
            return "it was measured with the table layout before anchors (whole int16 residuals); re-measure it"
        linear = getattr(config, "deform_scale_offset", "log") == "linear"
        if table.get("spec") and linear and "scale_offset" not in info:
            # Such a table interpolated this model's scale offsets made log-scale offsets, with most Gaussians on
            # the network: what was measured is not the table a load builds now (garo_ns.render.time_table).
            return "it was measured when tables held linear scale offsets as log-scale offsets; re-measure it"
        if info.get("mb", 0.0) > config.time_table_budget_mb:
            return f"its {info['mb']:.0f} MB exceed time_table_budget_mb {config.time_table_budget_mb:g}"
        return None

    def settings(self, config: RenderSettings, training_run: bool, device: torch.device) -> FrameSettings:
        """The switches to render with (see `resolve`)."""
        requested, bound = config.requested_switches(), config.switch_bound_db
        record = self.trusted_record()  # once: parameters changed since (seen by their versions) turn it off
        failure = self.failed_table(self._record_spec(record))
        key = (
            tuple(requested.values()),
            training_run,
            bound,
            torch.device(device).type,
            config.rasterizer,
            config.time_table_budget_mb,
            getattr(config, "deform_scale_offset", "log"),  # `_table_refusal` reads it
            self._step() if self._step else None,
            record is not None,
            failure,
        )
        if self._cache is not None and self._cache[0] == key and self._cache[1] is self.record:
            return self._cache[2]
        measure = replay(record["tried"]) if record else None
        settings = resolve(requested, training_run, config.renders_on_cuda(device), measure, bound_db=bound)[0]
        if settings.time_table and requested.get(TABLE) is None and self._table_refusal(config, device):
            settings = replace(settings, time_table=False)
        if settings.time_table and failure:  # asked for or chosen, but the network renders
            settings = replace(settings, time_table=False)
        self._cache = (key, self.record, settings)
        return settings

    def summary(self, config: RenderSettings, training_run: bool, device: torch.device) -> Dict[str, Any]:
        """What a user is told on load, and garo-eval records: the switches in use, each approximate
        switch's measured change against the plain render, the bound and where the measurement comes from,
        and the time table's keyframes, memory and why it is off where it is."""
        record = self.trusted_record()
        in_use = self.settings(config, training_run, device)
        table = dict((record or {}).get(TABLE) or {})
        failure = self.failed_table()
        if failure:
            table["off"] = f"it could not be built ({failure}): frames render through the network"
        elif in_use.time_table and self.table_spec() is None:
            table["off"] = "no table recorded for this model (trained before it existed, or not measured)"
        elif not in_use.time_table and record and not training_run:
            refusal = self._table_refusal(config, device)
            measured = record["tried"].get(TABLE)
            if refusal:
                table["off"] = refusal
            elif measured is not None and not measured <= config.switch_bound_db:
                table.setdefault("off", f"its change {measured:.4f} dB is over the bound {config.switch_bound_db} dB")
        spec = self.table_spec() if in_use.time_table else None
        built = self.table_built(spec) if spec is not None else None
        if built:  # the table this model renders with (keys, order, MB, build seconds), maybe not the record's
            table["built"] = built
        return {
            "in_use": asdict(in_use),
            # Only what `resolve` measures now: an older record's precision entries decide nothing.
            "measured_db": {k: v for k, v in record["tried"].items() if k in (APPROXIMATE, TABLE)} if record else {},
            "bound_db": config.switch_bound_db,
            "measured_at_step": record["step"] if record else None,
            "measured_views": record["views"] if record else None,
            "untrusted_record": self.distrust(),
            TABLE: table or None,
        }

    def line(self, config: RenderSettings, training_run: bool, device: torch.device) -> str:
        """One line naming the switches in use and each approximate switch's measured change."""
        info = self.summary(config, training_run, device)
        used = info["in_use"]
        on = [k for k in ("static_skip", "cache_deformation", "cuda_graph", "lean_raster") if used[k]]
        table = info[TABLE] or {}
        spec = self.table_spec() if used["time_table"] else None
        built = self.table_built(spec) if spec is not None else None
        if used["time_table"] and (built or "info" in table):
            t = built or table["info"]  # the table this model renders with, where it has been built
            recorded = table.get("info") or {}
            # What the line says of each: the order and the Gaussians on the network (a window's spec is its own).
            said = ("network", "order")
            differs = (
                built
                and recorded
                and [built.get(k, built["spec"].get(k)) for k in said]
                != [recorded.get(k, recorded["spec"].get(k)) for k in said]
            )
            window = ""
            if "window" in t:
                window = f"a window of {t['spec']['intervals']} of {t['window']['of_intervals']} intervals, "
            kept = t.get("file") or {}  # the table's file beside the run (garo_ns.render.table_cache)
            if kept.get("read") or kept.get("written"):
                window += f"{'read from' if kept['read'] else 'written to'} {kept['path']}, "
            on.insert(
                0,
                f"time_table ({t['keys']} keys, {t['spec']['order']}, {t['mb']:.0f} MB, {window}"
                + f"{t['network']} of {t['gaussians']} Gaussians on the network"
                + (
                    f"; measured as {recorded['spec']['order']} with {recorded['network']} on the network)"
                    if differs
                    else ")"
                ),
            )
        names = ", ".join(on) or "none"
        if info["measured_db"]:
            changes = ", ".join(f"{k} {v:.4f} dB" for k, v in info["measured_db"].items())
            where = f"measured on {info['measured_views']} training views at step {info['measured_at_step']}"
            measured = f"{changes} ({where}; bound {info['bound_db']} dB)"
        elif info["untrusted_record"]:
            measured = f"none trusted ({info['untrusted_record']}; approximate switches off unless set)"
        else:
            measured = "none measured (approximate switches off unless set)"
        off = f"; time table off: {table['off']}" if "off" in table else ""
        return f"Render switches: {names}; change against the plain render: {measured}{off}"

    def measure(
        self,
        config: RenderSettings,
        device: torch.device,
        render: Callable[[int, Optional[FrameSettings]], Tensor],
        targets: Sequence[Tensor],
        step: int,
    ) -> str:
        """Measure on training views how much each approximate switch left to the plugin changes the
        plain render (`render` and `targets` as in `measure_on_views`), keep it as the record, and
        return the line to tell the user."""
        measure = measure_on_views(render, targets)
        requested, bound = config.requested_switches(), config.switch_bound_db
        tried = resolve(requested, False, config.renders_on_cuda(device), measure, bound_db=bound)[1]
        self.record = {"step": step, "views": len(targets), "tried": tried, "measure": MEASURE_VERSION}
        if self._params is not None:
            self.record["params"] = self.fingerprint()
        losses = ", ".join(f"{k} {v:.4f} dB" for k, v in tried.items()) or "none left to the plugin"
        return f"Render switches on {len(targets)} training views (worst change against plain): {losses}"

    @torch.no_grad()
    def measure_on_training_views(self, model: Any, guard: Any, step: int) -> str:
        """`measure` on a model's training views: `guard` (a compaction TrainingViewGuard over
        `switch_views` views) renders and holds the ground truth; the exact switches stay off in the
        trials (they change no pixel), and the time table's trial places each view halfway between two
        of its keyframes. A failed measurement leaves no record (one from an earlier state would describe
        another model) and says so: it must never cost a training run its final checkpoint."""
        was_training = model.training
        model.eval()  # no time noise
        self.record = None
        cfg = model.config
        specs, why = table_ladder(model, cfg)
        spec = specs[0] if specs else None
        self._measuring = spec
        model.frame.halfway = True
        try:
            failed: Dict[str, str] = {}  # trials that could not render (out of memory, ...): off, said why

            def render(i: int, trial: Optional[FrameSettings]) -> Tensor:
                switches = None if trial is None else replace(trial, cuda_graph=False, lean_raster=False)
                if switches is not None and switches.time_table and spec is None:
                    return torch.full_like(guard.targets(model)[i], math.nan)  # an infinite change: off
                if switches is None:
                    image = guard.render(model, i, switches)
                else:
                    # A trial that fails at run time counts as an infinite change (that switch off) and keeps
                    # the others measured; a programming error is not caught.
                    try:
                        image = guard.render(model, i, switches)
                    except (RuntimeError, MemoryError) as err:
                        on = [k for k, v in asdict(switches).items() if v is True]
                        failed[", ".join(on) or "trial"] = f"{type(err).__name__}: {str(err).splitlines()[0][:120]}"
                        return torch.full_like(guard.targets(model)[i], math.nan)
                if switches is not None and switches.time_table and model.frame.table_failures.get(spec):
                    return torch.full_like(image, math.nan)  # not built: the network rendered, not the table
                return image

            targets = guard.targets(model)
            ladder: Dict[str, float] = {}  # the rungs built, each measured as built
            build_s: Dict[str, float] = {}  # each built rung's build: most of what the choice costs
            previews: Dict[str, float] = {}  # every rung tried, measured as its preview
            preview_s: Dict[str, float] = {}
            if cfg.time_table is None and len(specs) > 1:  # the fewest keys within the margin, else the best
                probe = measure_on_views(render, targets)
                margin = cfg.switch_bound_db * cfg.time_table_margin

                def try_rung(candidate: TableSpec) -> float:
                    """The rung's change, measured as built, or as previewed where its preview misses the margin."""
                    nonlocal spec
                    self._measuring = spec = candidate
                    name = rung_name(candidate, cfg)
                    # A rung's preview is its table less the keys' storage rounding: where it samples the field
                    # fewer times than the build, a table whose preview misses the margin is not built (the
                    # rounding only adds to its change).
                    if TimeTable.field_passes(candidate, preview=True) < TimeTable.field_passes(candidate):
                        model.frame.preview = True
                        try:
                            previews[name] = probe(FrameSettings(time_table=True))
                        finally:
                            model.frame.preview = False
                        preview_s[name] = float((model.frame.table_info or {}).get("build_s", math.nan))
                        if previews[name] > margin:
                            return previews[name]
                    ladder[name] = probe(FrameSettings(time_table=True))
                    build_s[name] = float((model.frame.table_info or {}).get("build_s", math.nan))
                    return ladder[name]

                for c, candidate in enumerate(specs):
                    within_db = try_rung(candidate)
                    if within_db <= margin:
                        # Fewer keys between this rung and the one before, where their fit says they suffice.
                        over = specs[c - 1] if c else None
                        over_db = {**previews, **ladder}.get(rung_name(over, cfg), math.nan) if over else math.nan
                        trim = trimmed_rung(over, over_db, candidate, within_db, margin) if over else None
                        if trim is not None and try_rung(trim) > margin:
                            self._measuring = spec = candidate  # the fit missed: the ladder's rung stands
                        break
                else:  # none within the margin: the least change, as built where built, else as previewed
                    measured = {**previews, **ladder}
                    best = min(specs, key=lambda s: measured[rung_name(s, cfg)])
                    self._measuring = spec = best
            line = self.measure(cfg, model.device, render, targets, step)
            if failed:
                line += "; off, failed to render: " + "; ".join(f"{k} ({v})" for k, v in failed.items())
                if self.record is not None:
                    self.record["failed"] = dict(failed)
            built = model.frame.table_info
            if self.record is not None and cfg.time_table is not False:
                failure = model.frame.table_failures.get(spec) if spec else None
                if failure:
                    entry: Dict[str, Any] = {"off": f"it could not be built ({failure})"}
                elif cfg.time_table and spec is not None:
                    # Forced on: not measured against the bound, but the finished model must know which table
                    # it trained for, or a load would find none to build.
                    entry = {"spec": spec.to_dict(), "forced": True}
                    if built and built.get("spec") == spec.to_dict():
                        entry["info"] = built
                else:
                    entry = {"spec": built["spec"], "info": built} if spec and built else {"off": why}
                rungs = {"intervals_tried_db": ladder, "build_s": build_s}
                rungs.update(intervals_previewed_db=previews, preview_s=preview_s)
                self.record[TABLE] = {**entry, **rungs} if previews or ladder else entry
            return line
        except (RuntimeError, MemoryError) as err:  # the plain renders themselves failed: nothing to compare with
            self.record = None
            return f"[yellow]Render switches not measured ({err}); they stay off unless set[/yellow]"
        finally:
            self._measuring = None
            model.frame.halfway = False
            model.train(was_training)
