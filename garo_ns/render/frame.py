"""The Gaussians at a time, and the fast path that renders a finished model outside training.

During training every frame is the plain D-3DGS composition in fp32 (`compose`). Outside training
(the viewer, `ns-render`, `garo-eval`, the benchmark) `FramePath` renders the same model with the
render switches: static Gaussians with frozen offsets (only the dynamic ones go through the MLP), the
time table (`garo_ns.render.time_table`), a cache of the last time rendered, and CUDA graphs of the
deformation and of the camera's projection. The MLP always runs in fp32, as trained. It holds only
caches: everything it renders from is passed in, so it knows nothing of the model.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from time import perf_counter
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor

from garo_ns.deformation import DeformationField, ScaleOffset, log_scale_offset
from garo_ns.render import table_cache
from garo_ns.render.backend import Backend, rasterize, resolve_backend
from garo_ns.render.frame_graph import FrameGraph, capture_errors
from garo_ns.render.graphs import InputGraph, TimeGraph, graphs_available, parameter_list, versions
from garo_ns.render.kernels import Front, lean_front
from garo_ns.render.table_lookup import fused_available, table_splats
from garo_ns.render.time_table import (
    TableSpec,
    TimeTable,
    build_bytes,
    fitting_intervals,
    row_scales,
    scale_rows,
    scratch_limit,
    tf32_products,
    window_spec,
)
from garo_ns.render.view import RenderView


class Canonical(NamedTuple):
    """The model's parameters as stored: canonical Gaussians (log-scales, opacity logits, SH)."""

    means: Tensor
    quats: Tensor
    log_scales: Tensor
    opacities: Tensor
    features_dc: Tensor
    features_rest: Tensor


class Splats(NamedTuple):
    """What the rasterizer takes: means, quaternions, scales, opacities [N] and SH colours [N, K, 3].
    `graph`: the capture number of the CUDA graph whose buffers these are (the next replay overwrites
    them), None for ordinary tensors."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    graph: Optional[int] = None

    def select(self, keep: Tensor) -> "Splats":
        """The Gaussians where `keep` is true (ordinary tensors)."""
        return Splats(*(x[keep] for x in self[:5]))


@dataclass
class FrameSettings:
    """The render switches (the model config's fields of the same names)."""

    static_skip: bool = False
    cache_deformation: bool = True
    cuda_graph: bool = False
    lean_raster: bool = False
    time_table: bool = False


Deformed = Tuple[Tensor, Tensor, Tensor]  # means, quaternions (unnormalised), log-scales
# (canonical positions [N, 3], time) -> (d_xyz, d_rot, d_log_scale): a DeformationField or a stand-in for one.
OffsetField = Callable[[Tensor, Union[float, Tensor]], Tuple[Tensor, Tensor, Tensor]]


def compose(
    field: OffsetField, canonical: Canonical, time: Union[float, Tensor], scale_offset: ScaleOffset = "log"
) -> Deformed:
    """Every Gaussian moved by the field at `time`, as D-3DGS composes it: the MLP reads detached
    canonical positions; offsets are added to the positions, to the normalised quaternions and to the
    scales as `scale_offset` says (garo_ns.deformation.log_scale_offset)."""
    d_xyz, d_rot, d_scale = field(canonical.means.detach(), time)
    log_scales = canonical.log_scales + log_scale_offset(canonical.log_scales, d_scale, scale_offset)
    return canonical.means + d_xyz, F.normalize(canonical.quats, dim=-1) + d_rot, log_scales


def activate(canonical: Canonical, deformed: Deformed) -> Splats:
    """The rasterizer's inputs from deformed geometry and the canonical appearance."""
    means, quats, log_scales = deformed
    colors = torch.cat([canonical.features_dc[:, None, :], canonical.features_rest], dim=1)
    return Splats(means, quats, torch.exp(log_scales), torch.sigmoid(canonical.opacities).squeeze(-1), colors)


def rows_splats(rows: Tensor, opacities: Tensor, colors: Tensor, scale_offset: ScaleOffset = "log") -> Splats:
    """The rasterizer's inputs from a tabled frame's rows [N, 10] (means, quaternions, scale rows as the table's
    `scale_offset` holds them: garo_ns.render.time_table.scale_rows) and the opacities and colours made with its
    table."""
    scales = row_scales(rows[:, 7:], scale_offset)
    return Splats(rows[:, :3].contiguous(), rows[:, 3:7].contiguous(), scales, opacities, colors)


@torch.no_grad()
def table_rows(canonical: Canonical, table: TimeTable) -> Optional[Tuple[Tensor, Optional[Tensor], Tensor, Tensor]]:
    """What `TimeTable.frame_rows` and a tabled frame read besides the table (None where the parameters are not
    fp32: those frames take the reference path): the canonical means, normalised quaternions and scale rows
    (garo_ns.render.time_table.scale_rows) plus the table's base [N, 10], the network Gaussians' canonical rows,
    the opacities and the colours."""
    if canonical.means.dtype != torch.float32:
        return None
    scales = scale_rows(canonical.log_scales, table.scale_offset)
    rows = torch.cat([canonical.means, F.normalize(canonical.quats, dim=-1), scales], dim=-1).detach()
    network_rows = rows[table.network].clone() if table.network.numel() else None
    splats = activate(canonical, (canonical.means, canonical.quats, canonical.log_scales))
    return rows.add_(table.base), network_rows, splats.opacities.detach(), splats.colors.detach()


class FramePath:
    """Caches and CUDA graphs of the render-time frame (one per model)."""

    def __init__(self) -> None:
        self._deformed: Optional[Tuple[Any, Splats]] = None
        self._static: Optional[Tuple[Any, Tensor, Deformed, Deformed]] = None
        self._graph = TimeGraph()
        self._camera_graph = InputGraph()
        self._table: Optional[Tuple[Any, Optional[TimeTable]]] = None
        # What a tabled frame reads besides the table, made with it: the canonical rows plus the table's base,
        # the network Gaussians' canonical rows, opacities and colours (the same every frame).
        self._table_rows: Optional[Tuple[Tensor, Optional[Tensor], Tensor, Tensor]] = None
        self.table_info: Optional[Dict[str, Any]] = None  # the last table built (or why it failed)
        # Tables that could not be built, by spec, with why: the frame renders through the network instead, and the
        # render switches say so (SwitchDecision.table_failure) rather than report the table in use.
        self.table_failures: Dict[Any, str] = {}
        # Set while the render switches are measured: the table's frames put each time halfway between keys.
        self.halfway = False
        # Set while they preview a table (TimeTable.preview): what a table would render halfway, without its keys.
        self.preview = False
        self.scale_offset: ScaleOffset = "log"  # the model's deform_scale_offset
        self.table_tf32 = False  # the model's time_table_tf32: tables built with TF32 products on CUDA
        # The model's time_table_budget_mb: a build's fp32 scratch gets what the budget leaves after the table
        # and its copies (`build_bytes`), so that the whole build stays within it (None: no cap but free memory).
        self.table_budget_mb: Optional[float] = None
        # The model's time_table_window_mb: a larger table is held a window of time at a time (`window`).
        self.table_window_mb: Optional[float] = None
        self._whole: Optional[TableSpec] = None  # the table `_table` holds, or holds a window of
        self._frame_graph = FrameGraph()
        self._frame_graph_failed = False  # its capture was refused once: the lean path renders from then on
        self._fit: Optional[Tuple[Any, int]] = None  # the intervals a window holds, for (spec, Gaussians, budget)
        # Where a loaded model keeps the whole table of a spec on disk (garo_ns.render.table_cache), or None.
        self.table_file: Callable[[TableSpec], Optional[Path]] = lambda spec: None

    def configure(self, config: Any) -> None:
        """Take the model config's settings that the frame path reads (`deform_scale_offset`, `time_table_tf32`,
        `time_table_budget_mb`, `time_table_window_mb`): at the model's construction, and again when a loaded model's
        config is changed."""
        self.scale_offset = config.deform_scale_offset
        self.table_tf32 = config.time_table_tf32
        self.table_budget_mb = config.time_table_budget_mb
        self.table_window_mb = getattr(config, "time_table_window_mb", None)

    def splats(
        self,
        field: DeformationField,
        canonical: Canonical,
        static: Optional[Tensor],
        static_offset: Optional[Tensor],
        time: float,
        settings: FrameSettings,
        table: Optional[TableSpec] = None,
        params: Optional[Tuple[Any, ...]] = None,
    ) -> Splats:
        """The Gaussians at `time` with the render switches. `static`/`static_offset`: the static
        classification (None: none yet, every Gaussian goes through the MLP). `table`: the time table to use
        when `settings.time_table` is on (None, or a table that cannot be built: the network renders). `params`:
        as `time_table` takes it."""
        if static is not None and (static_offset is None or static.shape[0] != canonical.means.shape[0]):
            static = None
        # Outside the training times' range a table has no keys that bracket the time: such a frame (a viewer's
        # time slider past the last training frame, a held-out last frame) goes through the network, exact.
        inside = table is not None and table.t_lo <= float(time) <= table.t_hi
        if settings.time_table and inside and not torch.is_grad_enabled():
            tabled = self.time_table(field, canonical, table, float(time), params)
            if tabled is not None:
                table_key = self._table[0]  # type: ignore[index]  # the spec, the parameters' versions, the scales
                cache_key = ("table", float(time), self.halfway, table_key)
                if settings.cache_deformation and self._deformed is not None and self._deformed[0] == cache_key:
                    return self._deformed[1]
                device = canonical.means.device
                if self.halfway or self._table_rows is None:  # the switch measurement's probe: the reference path
                    out = activate(canonical, tabled.deformed(field, canonical, float(time), self.halfway))
                elif settings.cuda_graph and tabled.graphable and graphs_available(device):
                    rows, _, opacities, colors = self._table_rows

                    def step(t: Tensor) -> Splats:
                        if fused_available(tabled, rows):
                            return Splats(*table_splats(tabled, rows, t), opacities, colors)
                        return rows_splats(tabled.rows_at(rows, t), opacities, colors, tabled.scale_offset)

                    # The network's graph and this one share a TimeGraph: one capture counter names the buffers
                    # the camera's projection graph reads (Splats.graph). The table's key changes with its tensors.
                    out = self._graph(("table", table_key), step, time, device, reuse=settings.cache_deformation)
                    return Splats(*out[:5], graph=self._graph.captures)
                else:
                    rows, network_rows, opacities, colors = self._table_rows
                    d = tabled.frame_rows(rows, network_rows, field, canonical.means.detach(), float(time))
                    out = rows_splats(d, opacities, colors, tabled.scale_offset)
                self._deformed = (cache_key, out) if settings.cache_deformation else None
                return out
        key = versions([*canonical, *parameter_list(field), *([static_offset] if static is not None else [])])
        device = canonical.means.device
        if settings.cuda_graph and graphs_available(device) and not torch.is_grad_enabled():

            def step(t: Tensor) -> Splats:
                return activate(canonical, self.deform(field, canonical, static, static_offset, t, settings, key, True))

            out = self._graph(self.graph_key(settings, key), step, time, device, reuse=settings.cache_deformation)
            return Splats(*out[:5], graph=self._graph.captures)
        cache_key = (float(time), settings.static_skip, key, self.scale_offset)
        if settings.cache_deformation and self._deformed is not None and self._deformed[0] == cache_key:
            return self._deformed[1]
        out = activate(canonical, self.deform(field, canonical, static, static_offset, time, settings, key))
        self._deformed = (cache_key, out) if settings.cache_deformation else None
        return out

    def built_info(self, spec: TableSpec) -> Optional[Dict[str, Any]]:
        """What the table of `spec` was built as (`table_info`), if it is the table built last; else None."""
        if self._table is not None and self._table[1] is not None and self._whole == spec and self.table_info:
            return None if self.table_info.get("preview") else self.table_info
        return None

    @property
    def table(self) -> Optional[TimeTable]:
        """The time table built last (None before any, or when it could not be built)."""
        return self._table[1] if self._table is not None else None

    def scratch_bytes(self, spec: TableSpec, xyz: Tensor) -> int:
        """The fp32 scratch a build of `spec` may hold: a quarter of free memory, and no more than the budget
        leaves after the build's own tensors (0: the build takes two passes of the field instead)."""
        free = scratch_limit(xyz.device)
        if self.table_budget_mb is None:
            return free
        n = xyz.shape[0]
        left = self.table_budget_mb * 2**20 - build_bytes(spec.intervals, n, spec.precision, spec.anchor_every)
        return max(0, min(free, int(left)))

    def window(self, spec: TableSpec, time: Optional[float], gaussians: int) -> Tuple[Optional[TableSpec], int]:
        """The table to build for a frame at `time` (None: the start of the range) from the table of `spec`, and how
        many midpoints its build checks: `spec` itself, or under `time_table_window_mb` the window around `time` of
        as many of its intervals as the budget holds (`window_spec`: the same keys there), checked at the whole
        table's density of midpoints; None where the budget holds fewer than two intervals. While the render
        switches are measured (`halfway`, `preview`) the whole table: their views range over all training times."""
        samples = 64  # TimeTable.build's default
        if self.table_window_mb is None or self.halfway or self.preview:
            return spec, samples
        key = (spec, gaussians, self.table_window_mb)
        if self._fit is None or self._fit[0] != key:  # a search over sizes: once per table, not every frame
            self._fit = (key, fitting_intervals(spec.intervals, gaussians, *key[2:], spec.precision, spec.anchor_every))
        fit = self._fit[1]
        if fit == 0:
            return None, samples
        t, samples = spec.t_lo if time is None else float(time), max(2, -(-samples * fit // spec.intervals))
        if self._table is not None and self._whole == spec and self._table[1] is not None:
            held = self._table[0][0]  # the window built last: kept while the time stays inside it
            if held.intervals == fit and held.t_lo <= t <= held.t_hi:
                return held, samples
        return window_spec(spec, t, fit), samples

    def time_table(
        self,
        field: DeformationField,
        canonical: Canonical,
        spec: TableSpec,
        time: Optional[float] = None,
        params: Optional[Tuple[Any, ...]] = None,
    ) -> Optional[TimeTable]:
        """The table of `spec` for these parameters (or its window around `time`: `window`), built on first use (and
        again when they change, or the time leaves the window); None when it cannot be built (out of memory, ...):
        the reason is in `table_info` and the network renders. While `preview` is set, the table's
        `TimeTable.preview` instead (halfway frames only). `params`: the versions of `canonical` and the field's
        parameters, where the caller has taken them (`SwitchDecision.one_frame`)."""
        params = versions([*canonical, *parameter_list(field)]) if params is None else params
        whole = spec
        built_spec, samples = self.window(whole, time, canonical.means.shape[0])
        if built_spec is None:
            reason = f"time_table_window_mb {self.table_window_mb:g} holds fewer than two of its intervals"
            self._table, self._table_rows, self._whole, self.table_info = None, None, whole, {"error": reason}
            self.table_failures[whole] = reason
            return None
        spec = built_spec
        key = (spec, params, self.scale_offset, self.preview, self.table_tf32)
        if self._table is None or self._table[0] != key or self._whole != whole:
            self._table, self._table_rows = None, None  # the old table's memory first
            self._whole = whole
            start = perf_counter()
            try:
                xyz = canonical.means.detach()
                # A loaded model's table, or its window: read from the whole table's file where one was written
                # (garo_ns.render.table_cache).
                path = None if self.preview or self.halfway else self.table_file(whole)
                window = None if spec == whole else spec
                built, note = table_cache.read(path, xyz.device, window) if path is not None else (None, None)
                read, written = built is not None, False
                if built is None:
                    with tf32_products(self.table_tf32):
                        if self.preview:
                            built = TimeTable.preview(spec, field, xyz, scale_offset=self.scale_offset)
                        else:
                            built = TimeTable.build(
                                spec,
                                field,
                                xyz,
                                midpoint_samples=samples,
                                scale_offset=self.scale_offset,
                                scratch_bytes=self.scratch_bytes(spec, xyz),
                            )
                    built.tf32 = self.table_tf32
                    if path is not None and note is None and window is None:  # an unreadable file stays as it is
                        note = table_cache.write(built, path)
                        written = note is None
                self.table_info = {**built.info, "build_s": perf_counter() - start}
                if path is not None:
                    self.table_info["file"] = {"path": str(path), "read": read, "written": written}
                    if note is not None:
                        self.table_info["file"]["note"] = note
                if spec != whole:  # a window: which stretch of which table
                    self.table_info["window"] = {"t_lo": spec.t_lo, "t_hi": spec.t_hi, "of_intervals": whole.intervals}
                # A preview renders halfway frames only (the reference path): no frame rows for it.
                self._table_rows = None if self.preview else table_rows(canonical, built)  # type: ignore[arg-type]
                self.table_failures.pop(whole, None)
            except (RuntimeError, MemoryError) as err:  # torch's out-of-memory is a RuntimeError
                built, self.table_info = None, {"error": f"{type(err).__name__}: {err}"[:300]}
                self.table_failures[whole] = self.table_info["error"]
            self._table = (key, built)
        return self._table[1]

    def graph_key(self, settings: FrameSettings, key: Tuple[Any, ...]) -> Tuple[Any, ...]:
        """What the deformation graph reads besides the time: the static switch, the parameters (`key`) and
        how the scale offsets compose."""
        return (settings.static_skip, key, self.scale_offset)

    def deform(
        self,
        field: DeformationField,
        canonical: Canonical,
        static: Optional[Tensor],
        static_offset: Optional[Tensor],
        time: Union[float, Tensor],
        settings: FrameSettings,
        key: Tuple[Any, ...],
        in_place: bool = False,
    ) -> Deformed:
        """`compose` with the fp32 field, with `static_skip` the MLP on the dynamic Gaussians only.
        `in_place` writes the dynamic rows into the cached frozen tensors (for a CUDA graph, whose
        outputs the next replay overwrites anyway; the static rows never change)."""
        if not settings.static_skip or static is None:
            return compose(field, canonical, time, self.scale_offset)
        dynamic, frozen, moving = self._static_split(canonical, static, static_offset, key)
        d_xyz, d_rot, d_scale = field(moving[0], time)
        d_log_scale = log_scale_offset(moving[2], d_scale, self.scale_offset)
        moved = (moving[0] + d_xyz, moving[1] + d_rot, moving[2] + d_log_scale)
        if in_place:
            return tuple(f.index_copy_(0, dynamic, m) for f, m in zip(frozen, moved))  # type: ignore[return-value]
        return tuple(f.index_copy(0, dynamic, m) for f, m in zip(frozen, moved))  # type: ignore[return-value]

    def _static_split(
        self, canonical: Canonical, static: Tensor, offset: Tensor, key: Tuple[Any, ...]
    ) -> Tuple[Tensor, Deformed, Deformed]:
        """Indices of the dynamic Gaussians, every Gaussian with its frozen offsets applied, and the
        dynamic Gaussians' canonical geometry (what the MLP and its offsets start from). Recomputed
        only when the parameters change, so a frame gathers nothing."""
        if self._static is None or self._static[0] != key:
            device = canonical.means.device
            dynamic = torch.nonzero(~static.to(device)).squeeze(-1)
            off = offset.to(device)
            quats = F.normalize(canonical.quats, dim=-1)
            frozen = (canonical.means + off[:, :3], quats + off[:, 3:7], canonical.log_scales + off[:, 7:])
            moving = (canonical.means.detach()[dynamic], quats[dynamic], canonical.log_scales[dynamic])
            self._static = (key, dynamic, frozen, moving)
        return self._static[1:]

    def rasterize(
        self,
        splats: Splats,
        view: RenderView,
        sh_degree: int,
        backgrounds: Optional[Tensor],
        render_mode: str,
        backend: Backend,
        lean_raster: bool,
        frame_graph: bool = False,
    ) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
        """Rasterize outside training. With `lean_raster`, gsplat's kernels are called directly; and
        when `splats` are a CUDA graph's buffers, the camera's projection of them replays as a
        second graph, fed the camera's matrices (`front`); with `frame_graph` too, the camera's whole share of the
        frame is one graph (garo_ns.render.frame_graph)."""
        one = frame_graph and not self._frame_graph_failed and lean_raster and splats.graph is not None
        one = one and not torch.is_grad_enabled()
        if one and render_mode in ("RGB", "RGB+ED") and resolve_backend(backend, splats.means.device) == "cuda":
            background = backgrounds if backgrounds is not None else splats.means.new_zeros(1, 3)
            args = (splats.graph, splats[:5], sh_degree, view.viewmat, view.K, view.width, view.height, background)
            try:
                return self._frame_graph(*args, render_mode == "RGB+ED")
            except capture_errors() as error:  # a capture this device or build refuses: the lean path renders instead
                self._frame_graph.release()
                self._frame_graph_failed = True
                print(f"frame_graph: off for this model, its capture failed ({str(error).splitlines()[0]})")
        front = self.front(splats, view) if lean_raster and render_mode in ("RGB", "RGB+ED") else None
        return render_splats(splats, view, sh_degree, backgrounds, render_mode, backend, lean_raster, front)

    def front(self, splats: Splats, view: RenderView) -> Optional[Front]:
        """The lean path's projection of `splats` for `view` by replay of the camera's CUDA graph, with the tile
        lists cut to each splat's alpha reach (inside the graph the cut costs no launches); None where `splats` are
        no graph's buffers or autograd is on (the lean path then projects them itself, with projection's squares)."""
        if splats.graph is None or torch.is_grad_enabled():
            return None
        means, quats, scales, opacities = splats[:4]
        return self._camera_graph(
            (splats.graph, view.width, view.height),
            lambda viewmat, K: lean_front(
                means, quats, scales, viewmat, K, view.width, view.height, True, opacities=opacities
            ),
            view.viewmat,
            view.K,
        )


# Arguments as `FramePath.rasterize` on purpose: the training path, without the frame path's graphs.
def render_splats(
    splats: Splats,
    view: RenderView,
    sh_degree: int,
    backgrounds: Optional[Tensor],
    render_mode: str,
    backend: Backend,
    lean: bool = False,
    front: Any = None,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Rasterize `splats` for `view`: render [1, H, W, C], alpha [1, H, W, 1] and the rasterizer's info."""
    return rasterize(
        means=splats.means,
        quats=splats.quats,
        scales=splats.scales,
        opacities=splats.opacities,
        colors=splats.colors,
        viewmats=view.viewmat,
        Ks=view.K,
        width=view.width,
        height=view.height,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode=render_mode,  # type: ignore[arg-type]
        backend=backend,
        lean=lean,
        front=front,
    )
