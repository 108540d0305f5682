"""Time as a table: the deformation field's offsets sampled at keyframe times, interpolated at render time.

A finished model's deformation MLP is a fixed function of (Gaussian, time). Outside training the table
holds its offsets (position, rotation, scale) at `K` keyframes and a frame interpolates between the
keyframes around its time, so the network leaves the frame: a few gathers and multiply-adds per Gaussian
instead of an 8-layer MLP.

* **Keyframes** are evenly spaced over the training times' range with `keys_per_frame` intervals per gap
  between training frames, and shifted by half a spacing: evenly spaced training times (D-NeRF's) then lie
  exactly halfway between two keyframes, where linear interpolation errs most, and no keyframe coincides
  with a training (and so with a D-NeRF test) time. Two extra keys pad each end for the cubic order. They hold
  the field's value at the range's end reflected, 2 f(end) - f(mirror time), not the field beyond the range:
  either order weighs the keys around an end symmetrically, so the range's first and last times (each halfway
  between the last key inside and the first beyond) come out as the field's own value there, where keys sampled
  beyond had pulled them toward motion at times the field never trained on (`key_offsets`).
* **Storage**: per Gaussian the offsets at the middle of the range (fp32, `base`); for the Gaussians whose
  offsets change at all (`moving`; the rest keep the base) every `anchor_every`-th key's residual from the base
  in fp32 (`anchors`), and each key's fine residual from the line between the anchors around it: int16 with a
  scale per Gaussian and channel by default, or fp16, or fp32. The fine residuals are the motion's bends over a
  few keys, hundreds of times smaller than the motion itself, so int16 resolves them far below what a key
  spacing leaves to interpolation; stored whole (from the base), int16's step grew with each Gaussian's range of
  motion and, measured on 40k models, held the error above 0.02 dB from 16 keys per frame on.
  int8 keys (same scales, 127 levels) take about half the bytes per key, so a memory budget holds nearly twice
  the keys. Where the field bends sharply (its ReLUs' kinks) a table's error falls only about as 1/K with the
  keys K (jumpingjacks' compacted model at 40k: 0.0297 dB at 6368 intervals, 0.0223 at 8195), so more keys in the
  same bytes may outweigh int8's coarser step: the render switches try int8 when the budget caps int16's keys
  short of the bound, and take whichever table changes the training views less (garo_ns.render.switches).
* **Gaussians the table cannot follow** (a trajectory that bends between keyframes more than the
  tolerance allows at the midpoints checked at build time) stay on the network: each frame runs the MLP
  on those few only (`network`).
* **Order**: linear or cubic (Catmull-Rom), chosen at build time as the one that leaves fewer Gaussians on
  the network (linear on a tie: it reads half the keys).
* **Scales** are held as the model composes them (garo_ns.deformation.log_scale_offset), so that what is
  interpolated is the field's own smooth output: log-scale offsets under `log`; under `linear` the offsets of
  the activated scale, which a frame adds to the scale itself (its rows hold scales, not log-scales). Made
  log-scale offsets first, `linear`'s offsets bend wherever one nearly cancels a small Gaussian's scale
  (log |s + d| falls to the floor and back between two keys): on 40k models 72 to 90% of the Gaussians stayed
  on the network. A scale's error is then judged in scene units, as a position's is.

The decision to render through the table is measured like the other approximate render switches
(garo_ns.render.switches), with each measured view placed halfway between two keyframes of the table's
spacing (`deformed_at(..., halfway=True)`).
"""

from __future__ import annotations

import bisect
import math
import struct
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

from garo_ns.deformation import ScaleOffset, check_scale_offset, linear_scales, log_scale_offset

Order = Literal["linear", "cubic"]
ORDERS: Tuple[Order, ...] = ("linear", "cubic")
CHANNELS = 10  # d_xyz 3, d_rot 4, d_log_scale 3
PAD = 2  # keys beyond each end of the range, so a cubic segment always has its four


@dataclass(frozen=True)
class TableSpec:
    """Everything needed to rebuild a table from the model (kept in the render-switch record)."""

    t_lo: float
    t_hi: float
    intervals: int
    order: Order = "linear"
    precision: Literal["int16", "int8", "fp16", "fp32"] = "int16"
    tolerance: float = 1e-4
    """Largest interpolation error at the checked midpoints for a Gaussian to stay in the table: in
    units of the scene extent for positions, absolute for quaternion and log-scale offsets."""
    extent: float = 1.0
    anchor_every: int = 16
    """Keys per fp32 anchor (the first and the last key are anchors too)."""
    range_lo: Optional[float] = None
    range_hi: Optional[float] = None
    """The range whose ends the keys beyond it are reflected through (None: t_lo, t_hi). A window (`window_spec`)
    keeps its whole table's, so that its keys are the whole table's."""

    @property
    def spacing(self) -> float:
        return (self.t_hi - self.t_lo) / self.intervals if self.t_hi > self.t_lo else 1.0

    def key_times(self) -> Tensor:
        """The keyframe times: t_lo + (k - PAD + 0.5) * spacing for k = 0 .. intervals + 2 PAD - 1."""
        k = torch.arange(self.intervals + 2 * PAD, dtype=torch.float64)
        return (self.t_lo + (k - PAD + 0.5) * self.spacing).float()

    def segment(self, time: float) -> Tuple[int, float]:
        """(i, f): `time` lies at fraction f between keys i and i + 1 (times outside the range clamp to it)."""
        t = min(max(float(time), self.t_lo), self.t_hi)
        u = (t - self.t_lo) / self.spacing + PAD - 0.5
        i = min(max(int(math.floor(u)), PAD - 1), self.intervals + PAD - 1)
        return i, u - i

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)

    def ends(self) -> Tuple[float, float]:
        """The range of times whose ends the keys beyond it reflect through (`range_lo`, `range_hi`)."""
        lo = self.t_lo if self.range_lo is None else self.range_lo
        return lo, self.t_hi if self.range_hi is None else self.range_hi

    def anchor_keys(self) -> List[int]:
        """Indices of the anchor keys: every `anchor_every`-th and the last."""
        n = self.intervals + 2 * PAD
        keys = list(range(0, n, max(int(self.anchor_every), 1)))
        return keys if keys[-1] == n - 1 else keys + [n - 1]


def weights(order: Order, f: float) -> Tuple[Tuple[int, ...], Tuple[float, ...]]:
    """Key offsets (relative to segment start i) and their weights for fraction `f` of a segment."""
    if order == "linear":
        return (0, 1), (1.0 - f, f)
    f2, f3 = f * f, f * f * f  # Catmull-Rom through keys i-1 .. i+2
    return (-1, 0, 1, 2), (
        0.5 * (-f + 2 * f2 - f3),
        0.5 * (2 - 5 * f2 + 3 * f3),
        0.5 * (f + 4 * f2 - 3 * f3),
        0.5 * (-f2 + f3),
    )


def interpolate(keys: Tensor, order: Order, i: int, f: float) -> Tensor:
    """The keys [K, M, C] interpolated at fraction f of segment i, in fp32 [M, C]."""
    offsets, w = weights(order, f)
    out = keys[i + offsets[0]].float() * w[0]
    for o, wk in zip(offsets[1:], w[1:]):
        out.add_(keys[i + o].float(), alpha=wk)
    return out


Q16 = 32767.0  # int16 keys: a residual of the Gaussian's own largest size maps to +-Q16
# The largest stored integer of each integer precision.
LEVELS = {"int16": Q16, "int8": 127.0}


class Codec:
    """How fine residuals are stored: fp32, fp16, or an integer (int16, int8) with a scale per Gaussian and channel
    (a residual of at most `spread` stored to spread / 32767, or / 127: uniform resolution over the Gaussian's own
    fine residuals)."""

    def __init__(self, precision: str, spread: Optional[Tensor] = None) -> None:
        self.precision = precision
        self.dtype = {"fp16": torch.float16, "fp32": torch.float32, "int16": torch.int16, "int8": torch.int8}[precision]
        self.levels = LEVELS.get(precision)
        self.scale = (spread.clamp_min(1e-12) / self.levels) if self.levels and spread is not None else None

    def encode(self, r: Tensor) -> Tensor:
        if self.scale is None:
            return r.to(self.dtype)
        return torch.round(r / self.scale).clamp_(-self.levels, self.levels).to(self.dtype)

    def interpolate(self, keys: Tensor, order: Order, i: int, f: float, rows: Optional[Tensor] = None) -> Tensor:
        """`interpolate` of stored keys, back in fp32 (`rows`: which Gaussians' scales the keys hold)."""
        out = interpolate(keys, order, i, f)
        if self.scale is None:
            return out
        return out * (self.scale if rows is None else self.scale[rows])

    def select(self, rows: Tensor) -> None:
        if self.scale is not None:
            self.scale = self.scale[rows].contiguous()


def field_offsets(field: Any, xyz: Tensor, times: Sequence[float], chunk: int = 1 << 18) -> Tensor:
    """The field's offsets [T, N, 10] at each time, for canonical positions `xyz` [N, 3] (no gradients)."""
    out = torch.empty(len(times), xyz.shape[0], CHANNELS, device=xyz.device)
    for k, d in iter_field_offsets(field, xyz, times, chunk):
        out[k] = d
    return out


SAMPLER_TIMES = 8
"""Times from which `iter_field_offsets` samples a field through its `time_sampler` (the positions' share of the
encoding's layers made once): below it, making that share costs about what it saves."""


@contextmanager
def tf32_products(enabled: bool) -> Iterator[None]:
    """Inside, when `enabled`, CUDA's fp32 matrix products take TF32 inputs (10-bit mantissas, fp32 sums) on tensor
    cores; the previous setting is back after. A table's build is mostly the field's products; the probe that
    measures its change (`offsets_halfway`) samples the field in TF32 too when the table was built so
    (`TimeTable.tf32`), so a TF32 table is judged with its own rounding. No effect on a CPU."""
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = was or bool(enabled)
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = was


def iter_field_offsets(
    field: Any, xyz: Tensor, times: Sequence[float], chunk: int = 1 << 18
) -> Iterator[Tuple[int, Tensor]]:
    """(k, the field's offsets [N, 10] at times[k]) for each k in order, as `field_offsets` gives them, holding
    a few times' offsets at once rather than all of them. A field that takes one time per row
    (`times_per_row`, e.g. garo_ns.deformation.DeformationField) gets several times in one call of up to `chunk`
    rows: a table's keys on a model of some 10^4 Gaussians are thousands of small calls otherwise, bound by
    their launches. One with a `time_sampler` (DeformationField) is sampled through it from SAMPLER_TIMES times on:
    the same offsets up to the order of sums, without the position encoding's share of each call."""
    n = xyz.shape[0]
    per_call = max(1, chunk // max(n, 1)) if getattr(field, "times_per_row", False) else 1
    with torch.no_grad():
        sampled = hasattr(field, "time_sampler") and per_call > 1 and len(times) >= SAMPLER_TIMES
        sample = field.time_sampler(xyz) if sampled else None
        for k0 in range(0, len(times), per_call):
            group = [float(t) for t in times[k0 : k0 + per_call]]
            if len(group) == 1 and sample is None:
                d = torch.empty(n, CHANNELS, device=xyz.device)
                for s in range(0, n, chunk):
                    d[s : s + chunk] = torch.cat(field(xyz[s : s + chunk], group[0]), dim=-1).float()
                yield k0, d
                continue
            t = torch.tensor(group, dtype=xyz.dtype, device=xyz.device)
            if sample is not None:
                d = torch.cat(sample(t), dim=-1).float()
            else:
                d = torch.cat(field(xyz.repeat(len(group), 1), t.repeat_interleave(n)[:, None]), dim=-1).float()
            for j, block in enumerate(d.view(len(group), n, CHANNELS)):
                yield k0 + j, block


Reflection = Tuple[List[Tuple[float, float]], float, float]


def key_time(spec: TableSpec, k: int) -> float:
    """Key k's time in float64 (`TableSpec.key_times` rounds the same sum to fp32)."""
    return spec.t_lo + (k - PAD + 0.5) * spec.spacing


def reflection(spec: TableSpec, t: float) -> Reflection:
    """A key at time `t` as the field's values: (ends, sign, s), the key being sum(w * f(end) for w, end in ends)
    + sign * f(s), s inside the spec's range (`TableSpec.ends`). Inside, the field at t; beyond an end, the field
    there reflected, 2 f(end) - f(2 end - t) (again through the other end while that lies beyond it too). An s on
    a key of the spec's grid is that key's own time as `key_times` gives it, so that a key and the key reflected to
    it sample the field at the same input. A range of one time gives every key the field's value at it."""
    lo, hi = spec.ends()
    if hi <= lo:
        return [], 1.0, lo
    ends: List[Tuple[float, float]] = []
    sign = 1.0
    while not lo <= t <= hi:
        end = lo if t < lo else hi
        ends.append((2.0 * sign, end))
        sign, t = -sign, 2.0 * end - t
    on_key = key_time(spec, round((t - spec.t_lo) / spec.spacing + PAD - 0.5))
    if abs(on_key - t) <= 1e-6 * spec.spacing:
        t = struct.unpack("f", struct.pack("f", on_key))[0]  # rounded to fp32 as `key_times` rounds it
    return ends, sign, t


def reflected(plan: Reflection, value: Tensor, at: Callable[[float], Tensor]) -> Tensor:
    """A `reflection`'s key from `value` (the field at its s) and `at(end)` (the field at each end it names)."""
    ends, sign, _ = plan
    out = value * sign
    for w, e in ends:
        out.add_(at(e), alpha=w)
    return out


def key_offsets(
    field: Any, xyz: Tensor, spec: TableSpec, keys: Optional[Sequence[int]] = None
) -> Iterator[Tuple[int, Tensor]]:
    """(k, key k's offsets [N, 10]) for each of `keys` (default: all of the spec's), in no fixed order: the field's
    at the key's time inside the range, reflected through the range's end beyond it (`reflection`). The keys inside
    come as `iter_field_offsets` gives them, a few times at a time; those beyond are made from the ends' values
    (held, two rows) and the key their time reflects to, as that key comes by."""
    keys = list(range(spec.intervals + 2 * PAD)) if keys is None else [int(k) for k in keys]
    plans = {k: reflection(spec, key_time(spec, k)) for k in keys}
    inside = [k for k in keys if not plans[k][0]]
    streamed = {plans[k][2] for k in inside}
    held_times = sorted({e for k in keys for _, e in plans[k][0]})
    held_times += sorted({plans[k][2] for k in keys if plans[k][0] and plans[k][2] not in streamed})
    held = dict(zip(held_times, field_offsets(field, xyz, held_times))) if held_times else {}
    waiting: Dict[float, List[int]] = {}
    for k in keys:
        if plans[k][0]:
            if plans[k][2] in held:
                yield k, reflected(plans[k], held[plans[k][2]], held.__getitem__)
            else:
                waiting.setdefault(plans[k][2], []).append(k)
    for j, d in iter_field_offsets(field, xyz, [plans[k][2] for k in inside]):
        k = inside[j]
        for b in waiting.pop(plans[k][2], []):
            yield b, reflected(plans[b], d, held.__getitem__)
        yield k, d


def reflected_offsets(field: Any, xyz: Tensor, spec: TableSpec, times: Sequence[float]) -> Tensor:
    """The offsets [T, N, 10] a key at each of `times` would hold (`reflection`), all at once: the field's inside
    the spec's range, reflected through its end beyond it; each distinct time the field is sampled at, once."""
    plans = [reflection(spec, float(t)) for t in times]
    need = sorted({e for ends, _, _ in plans for _, e in ends} | {s for _, _, s in plans})
    at = dict(zip(need, field_offsets(field, xyz, need)))
    out = torch.empty(len(times), xyz.shape[0], CHANNELS, device=xyz.device)
    for j, plan in enumerate(plans):
        out[j] = reflected(plan, at[plan[2]], at.__getitem__)
    return out


def choose_order(spec: TableSpec, err: Dict[str, Tensor]) -> Tuple[TableSpec, Tensor, Dict[str, int]]:
    """From each order's midpoint errors (`midpoint_errors`): `spec` with the order that leaves the fewest Gaussians
    over the tolerance (the spec's own on a tie), the indices of those it leaves to the network, and how many each
    order would leave."""
    off = {o: int((err[o] > spec.tolerance).sum()) for o in ORDERS}
    order: Order = min(ORDERS, key=lambda o: (off[o], o != spec.order))
    network = torch.nonzero(err[order] > spec.tolerance).squeeze(-1)
    return TableSpec(**{**spec.to_dict(), "order": order}), network, off


def midpoint_segments(spec: TableSpec, samples: int) -> List[int]:
    """The segments (0 .. intervals, from segment PAD - 1 on) whose midpoints `midpoint_errors` checks: up to
    `samples`, evenly spread, from the segment next to each end where the keys beyond reflect through it."""
    n_seg = spec.intervals + 1  # segments PAD-1 .. intervals+PAD-1 hold the range
    lo, hi = spec.ends()
    first = 1 if lo == spec.t_lo and n_seg >= 3 else 0
    last = n_seg - 2 if hi == spec.t_hi and n_seg >= 3 else n_seg - 1
    return torch.linspace(first, last, min(samples, last - first + 1)).round().long().unique().tolist()


def midpoint_errors(
    spec: TableSpec,
    field: Any,
    xyz: Tensor,
    base: Tensor,
    interp: Callable[[Order, int, float], Tensor],
    samples: int,
    scale_offset: ScaleOffset = "log",
) -> Dict[str, Tensor]:
    """Per Gaussian, the largest error of each order's interpolation of the stored keys (`base` plus
    `interp(order, i, f)`, the stored residuals of every Gaussian interpolated) against the field at up to
    `samples` segment midpoints spread over the range, the worst place for an interpolant between two keys:
    the larger of the position error divided by the scene extent, the rotation error and the scale error (of
    the log-scales under `log`; under `linear`, of the scales, divided by the extent as a position's is). The
    midpoint of a segment at an end of the range is that end, exact where the keys beyond reflect through it
    (`key_offsets`); the spread starts at the segment next to it instead, where a cubic reads one reflected key
    (its weakest place: an error of h^2/64 |f''|)."""
    picks = midpoint_segments(spec, samples)
    key_t = spec.key_times()
    err = {o: torch.zeros(xyz.shape[0], device=xyz.device) for o in ORDERS}
    halfway = [float(key_t[PAD - 1 + p]) + 0.5 * spec.spacing for p in picks]
    per_unit = channel_units(spec, scale_offset, xyz.device)
    for j, truth in iter_field_offsets(field, xyz, halfway):
        i = PAD - 1 + picks[j]
        truth = truth - base
        for o in ORDERS:
            err[o] = torch.maximum(err[o], ((interp(o, i, 0.5) - truth).abs() * per_unit).amax(-1))
    return err


def channel_units(spec: TableSpec, scale_offset: ScaleOffset, device: torch.device) -> Tensor:
    """[10] what one unit of each stored channel counts for against the tolerance: positions in scene extents,
    rotations as they are, scales in scene extents under `linear` (offsets of the scale) and as they are under
    `log` (offsets of the log-scale)."""
    check_scale_offset(scale_offset)
    units = torch.ones(CHANNELS, device=device)
    units[:3] = 1.0 / spec.extent
    if scale_offset == "linear":
        units[7:] = 1.0 / spec.extent
    return units


def scratch_limit(device: torch.device) -> int:
    """Bytes a table build may hold beside the table for every key's fp32 fine residuals: a quarter of what the GPU
    has free (the driver's free memory and torch's cached blocks), or 1 GiB on a CPU. A quarter, not more: the
    build runs at the end of a training run, where other runs may share the GPU and still need to allocate."""
    device = torch.device(device)
    if device.type != "cuda":
        return 1 << 30
    free, _ = torch.cuda.mem_get_info(device)
    cached = torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    return int(0.25 * (free + cached))


def anchor_lines(anchors: Tensor, anchor_keys: Sequence[int]) -> Callable[[int], Tensor]:
    """Key index -> the line between the two anchors [A, M, C] around it, at that key (fp32 [M, C])."""
    keys = [int(k) for k in anchor_keys]

    def line(k: int) -> Tensor:
        j = min(max(bisect.bisect_right(keys, k) - 1, 0), len(keys) - 2)
        u = (k - keys[j]) / (keys[j + 1] - keys[j])
        return anchors[j] * (1.0 - u) + anchors[j + 1] * u

    return line


class TimeTable:
    """The offsets of one model's Gaussians at the keyframes of `spec` (see the module docstring)."""

    def __init__(
        self,
        spec: TableSpec,
        base: Tensor,
        anchors: Tensor,
        residual: Tensor,
        moving: Tensor,
        network: Tensor,
        info: Dict[str, Any],
        codec: Codec,
        anchor_keys: Optional[Sequence[int]] = None,
    ) -> None:
        self.spec = spec
        self.codec = codec
        self.base = base  # [N, 10] fp32: mean offsets (what a Gaussian that does not move keeps)
        self.anchors = anchors  # [A, M, 10] fp32: the anchor keys less the base, moving Gaussians only
        self.residual = residual  # [K, M, 10]: each key less the base and less its anchor line
        self.moving = moving  # [M] indices into the Gaussians
        self.network = network  # [R] indices of the Gaussians rendered through the MLP
        self.info = info
        # Which keys the anchors are: the spec's, or for a window cut from a whole table the whole table's, counted
        # from the window's first key (`window_of`: the first may lie before it, the last after it).
        self._anchor_keys = list(anchor_keys) if anchor_keys is not None else spec.anchor_keys()
        self.scale_offset: ScaleOffset = "log"  # how the stored scale offsets compose (`build`)
        # Built with TF32 products (garo_ns.render.frame sets it): the probe that judges the table samples the field
        # the same way, so the measured change includes TF32's rounding of the keys.
        self.tf32 = False
        self._key_anchor: Optional[Tensor] = None  # made on the first `rows_at`
        self._anchor_at: Optional[Tensor] = None
        self._line = anchor_lines(anchors, self._anchor_keys)

    @classmethod
    @torch.no_grad()
    def build(
        cls,
        spec: TableSpec,
        field: Any,
        xyz: Tensor,
        midpoint_samples: int = 64,
        scale_offset: ScaleOffset = "log",
        scratch_bytes: Optional[int] = None,
    ) -> "TimeTable":
        """Sample `field` at the spec's keyframes for canonical positions `xyz`; choose the order by the
        midpoint check (the spec's order is the preference on a tie) and which Gaussians stay on the network.
        The table holds the field's offsets as they come, its scale offsets composed as `scale_offset` says
        (the model's). `scratch_bytes`: the most memory the build may hold every key's fine residuals in fp32
        with (default `scratch_limit`)."""
        times = spec.key_times().tolist()
        n = xyz.shape[0]
        # Offsets from those at the middle of the range, anchors first; then one key at a time. fp32 and fp16 keys
        # are stored as they come. Integer keys need each Gaussian's largest fine residual before any key is
        # encoded: where every key's fp32 residuals fit in `scratch_bytes` they are kept from that pass and encoded
        # after it (one pass of the field over the keys, the same numbers); else the field runs over the keys twice,
        # holding one key's residuals at a time. The field's passes are most of a build's time.
        per_unit = channel_units(spec, scale_offset, xyz.device)  # refuses an unknown composition before any pass
        base = field_offsets(field, xyz, [0.5 * (spec.t_lo + spec.t_hi)])[0]
        anchor_keys = spec.anchor_keys()
        anchors = reflected_offsets(field, xyz, spec, [key_time(spec, k) for k in anchor_keys]) - base
        line = anchor_lines(anchors, anchor_keys)

        plain = Codec(spec.precision)  # fp32 and fp16 keys need no scale: they are encoded as they come
        residual = torch.empty(len(times), n, CHANNELS, dtype=plain.dtype, device=xyz.device)
        limit = scratch_limit(xyz.device) if scratch_bytes is None else scratch_bytes
        fine: Optional[Tensor] = None
        if plain.levels is not None and len(times) * n * CHANNELS * 4 <= limit:
            try:
                fine = torch.empty(len(times), n, CHANNELS, device=xyz.device)
            except torch.OutOfMemoryError:  # another process took the room since: two passes, the same table
                fine = None
        spread = torch.zeros(n, CHANNELS, device=xyz.device)  # largest fine residual
        motion = torch.zeros_like(spread)  # largest offset from the base
        for k, d in key_offsets(field, xyz, spec):
            r = d - base
            f = r - line(k)
            spread = torch.maximum(spread, f.abs())
            motion = torch.maximum(motion, r.abs())
            if plain.levels is None:
                residual[k] = plain.encode(f)
            elif fine is not None:
                fine[k] = f
        codec = Codec(spec.precision, spread)
        if fine is not None:
            for k in range(len(times)):
                residual[k] = codec.encode(fine[k])
            del fine
        elif plain.levels is not None:
            for k, d in key_offsets(field, xyz, spec):
                residual[k] = codec.encode(d - base - line(k))
        whole = cls(spec, base, anchors, residual, torch.arange(xyz.shape[0], device=xyz.device), None, {}, codec)
        err = midpoint_errors(spec, field, xyz, base, whole.interpolate_moving, midpoint_samples, scale_offset)
        spec, network, off = choose_order(spec, err)
        order = spec.order
        # A Gaussian whose offsets stay within a thousandth of the tolerance of the base keeps the base.
        moving = torch.nonzero((motion * per_unit).amax(-1) > spec.tolerance * 1e-3)
        moving = moving.squeeze(-1)
        if moving.numel() != xyz.shape[0]:
            residual, anchors = residual[:, moving].contiguous(), anchors[:, moving].contiguous()
            codec.select(moving)
        del whole
        info = {
            "spec": spec.to_dict(),
            "keys": len(times),
            "anchors": len(anchor_keys),
            "gaussians": int(xyz.shape[0]),
            "moving": int(moving.numel()),
            "network": int(network.numel()),
            "scale_offset": scale_offset,
            "network_by_order": off,
            "midpoint_error_max": {o: float(err[o].max()) if err[o].numel() else 0.0 for o in ORDERS},
            # How the chosen order's errors spread over the Gaussians: what a tolerance would leave to the network.
            "midpoint_error_quantiles": {
                str(q): float(err[order].quantile(q)) if err[order].numel() else 0.0 for q in (0.5, 0.9, 0.99, 0.999)
            },
        }
        table = cls(spec, base, anchors, residual, moving, network, info, codec)
        table.scale_offset = scale_offset
        table.info["mb"] = table.nbytes() / 2**20
        return table

    @classmethod
    @torch.no_grad()
    def preview(
        cls,
        spec: TableSpec,
        field: Any,
        xyz: Tensor,
        midpoint_samples: int = 64,
        scale_offset: ScaleOffset = "log",
    ) -> "TimeTable":
        """What a table of `spec` renders halfway between two keys (`offsets_halfway`), without its keys: the order
        and the Gaussians left to the network chosen as `build` chooses them, from the keys around the sampled
        midpoints alone, and the residuals unrounded (fp32 whatever `spec.precision`: storage rounding only adds to
        what the keys' spacing leaves). A few hundred of the field's passes where `build` makes one per key (a
        dense table takes thousands): the render switches preview a ladder of tables with it and build only a
        table whose preview comes within their margin (garo_ns.render.switches). It serves halfway frames only."""
        check_scale_offset(scale_offset)
        base = field_offsets(field, xyz, [0.5 * (spec.t_lo + spec.t_hi)])[0]
        around: Dict[str, Any] = {"segment": None, "keys": None}

        def interp(order: Order, i: int, f: float) -> Tensor:
            # The four keys around segment i (what either order reads), sampled once for both orders.
            if around["segment"] != i:
                around["keys"] = (
                    reflected_offsets(field, xyz, spec, [key_time(spec, k) for k in range(i - 1, i + 3)]) - base
                )
                around["segment"] = i
            return interpolate(around["keys"], order, 1, f)

        err = midpoint_errors(spec, field, xyz, base, interp, midpoint_samples, scale_offset)
        spec, network, off = choose_order(spec, err)
        n = xyz.shape[0]
        empty = torch.empty(0, n, CHANNELS, device=xyz.device)
        keys = spec.intervals + 2 * PAD
        info = {"spec": spec.to_dict(), "keys": keys, "gaussians": int(n), "network": int(network.numel())}
        info.update(preview=True, network_by_order=off, scale_offset=scale_offset)
        table = cls(spec, base, empty, empty, torch.arange(n, device=xyz.device), network, info, Codec("fp32"))
        table.scale_offset = scale_offset
        return table

    @staticmethod
    def field_passes(spec: TableSpec, midpoint_samples: int = 64, preview: bool = False) -> int:
        """How many times the field is sampled at (each over every Gaussian) to `build` a table of `spec` (with room
        for its residuals: one pass over the keys), or at most to `preview` it."""
        midpoints = len(midpoint_segments(spec, midpoint_samples))
        if preview:
            return 1 + 5 * midpoints  # the middle; per midpoint its truth and the four keys around it
        # Keys beyond the range are made from the ends' values and the keys they reflect to (`key_offsets`): the
        # anchors' pass samples two more times than its keys, the keys' pass two fewer.
        return 1 + len(spec.anchor_keys()) + spec.intervals + 2 * PAD + midpoints

    TENSORS = ("base", "anchors", "residual", "moving", "network")

    def state(self) -> Dict[str, Any]:
        """The table as plain data (its tensors on the CPU), for `from_state` (garo_ns.render.table_cache)."""
        tensors = {k: getattr(self, k).cpu() for k in self.TENSORS}
        scale = None if self.codec.scale is None else self.codec.scale.cpu()
        meta = {"scale_offset": self.scale_offset, "tf32": self.tf32, "precision": self.codec.precision}
        meta["anchor_keys"] = list(self._anchor_keys)
        return {"spec": self.spec.to_dict(), "info": self.info, "scale": scale, **meta, **tensors}

    @classmethod
    def from_state(cls, state: Dict[str, Any], device: Any) -> "TimeTable":
        """The table `state` holds, on `device`: the same keys, scales and choices as the table it was taken from (its
        whole range as one window)."""
        return cls.window_of(state, TableSpec(**state["spec"]), device)

    @classmethod
    def window_of(cls, state: Dict[str, Any], window: TableSpec, device: Any) -> "TimeTable":
        """The stretch `window` (`window_spec` of the whole table's spec) of the whole table `state` holds, on
        `device`: its keys, their scales and the anchors around them, so every frame inside is the whole table's
        frame. Only the window's keys are read from `state`'s tensors (a file mapped into memory reads no more)."""
        whole = TableSpec(**state["spec"])
        start = round((window.t_lo - whole.t_lo) / whole.spacing)
        n = window.intervals + 2 * PAD
        if not (0 <= start and start + window.intervals <= whole.intervals):
            raise ValueError(f"a window from {window.t_lo} over {window.intervals} intervals lies outside {whole}")
        keys = state["anchor_keys"]
        lo = bisect.bisect_right(keys, start) - 1  # the anchors at or around the window's keys
        hi = bisect.bisect_left(keys, start + n - 1)
        codec = Codec(state["precision"])
        codec.scale = None if state["scale"] is None else state["scale"].to(device)
        spec = replace(window, order=whole.order)
        info = {**state["info"], "spec": spec.to_dict(), "keys": n, "anchors": hi - lo + 1}
        table = cls(
            spec,
            state["base"].to(device),
            state["anchors"][lo : hi + 1].to(device),
            state["residual"][start : start + n].to(device),
            state["moving"].to(device),
            state["network"].to(device),
            info,
            codec,
            [k - start for k in keys[lo : hi + 1]],
        )
        table.scale_offset, table.tf32 = state["scale_offset"], bool(state["tf32"])
        table.info["mb"] = table.nbytes() / 2**20
        return table

    @property
    def is_preview(self) -> bool:
        """Whether this is a `preview` (no keys: it renders halfway frames only)."""
        return bool(self.info.get("preview"))

    def nbytes(self) -> int:
        parts = (self.base, self.anchors, self.residual, self.moving, self.network) + (
            (self.codec.scale,) if self.codec.scale is not None else ()
        )
        return sum(t.numel() * t.element_size() for t in parts if t is not None)

    def interpolate_moving(self, order: Order, i: int, f: float) -> Tensor:
        """The moving Gaussians' residuals from the base [M, 10] at fraction f of segment i: the stored fine
        residuals interpolated, plus the same interpolation of their anchor lines."""
        if order == "linear":
            return self._linear_moving(i, f)
        fast = self._cubic_moving(i, f)
        if fast is not None:
            return fast
        out = self.codec.interpolate(self.residual, order, i, f)
        offsets, w = weights(order, f)
        for o, wk in zip(offsets, w):
            out.add_(self._line(i + o), alpha=wk)
        return out

    def _linear_moving(self, i: int, f: float) -> Tensor:
        """`interpolate_moving` of the linear order in four kernels, as a frame needs it (a frame's cost is kernel
        launches, not bytes): keys i and i + 1 lie on one anchor line, so the lines' share is one lerp of two
        anchors, and the fine residuals' one lerp of the two keys, scaled back by int16's scales."""
        keys = self._anchor_keys
        j = min(max(bisect.bisect_right(keys, i) - 1, 0), len(keys) - 2)
        u = (i + f - keys[j]) / (keys[j + 1] - keys[j])
        line = torch.lerp(self.anchors[j], self.anchors[j + 1], u)
        pair = self.residual[i : i + 2].float()
        fine = torch.lerp(pair[0], pair[1], f)
        if self.codec.scale is None:
            return line.add_(fine)
        return torch.addcmul(line, fine, self.codec.scale)

    def _cubic_moving(self, i: int, f: float) -> Optional[Tensor]:
        """`interpolate_moving` of the cubic order where its four keys i - 1 .. i + 2 lie on one anchor line (None
        elsewhere): Catmull-Rom's weights sum to one, so the lines' share is the line at the weighted key."""
        keys = self._anchor_keys
        j = min(max(bisect.bisect_right(keys, i - 1) - 1, 0), len(keys) - 2)
        if i - 1 < keys[j] or i + 2 > keys[j + 1]:
            return None
        offsets, w = weights("cubic", f)
        u = (sum(wk * (i + o) for o, wk in zip(offsets, w)) - keys[j]) / (keys[j + 1] - keys[j])
        out = torch.lerp(self.anchors[j], self.anchors[j + 1], u)
        quad = self.residual[i - 1 : i + 3].float()
        fine = quad[0] * w[0]
        for k in range(1, 4):
            fine.add_(quad[k], alpha=w[k])
        if self.codec.scale is None:
            return out.add_(fine)
        return out.addcmul_(fine, self.codec.scale)

    @property
    def graphable(self) -> bool:
        """Whether `rows_at` serves this table: linear keys and no Gaussian on the network (the frame's
        CUDA graph; other tables take `frame_rows`)."""
        return self.spec.order == "linear" and self.network.numel() == 0

    def rows_at(self, rows: Tensor, time: Tensor) -> Tensor:
        """`frame_rows` of a `graphable` table with the time a device scalar: the segment, its keys and anchors
        found on the device (gathers, no host reads), so that a CUDA graph can replay the whole frame."""
        spec = self.spec
        key_anchor, anchor_at = self.anchor_index(rows.device)
        u = (time.clamp(spec.t_lo, spec.t_hi) - spec.t_lo) / spec.spacing + (PAD - 0.5)
        i = u.floor().clamp(PAD - 1, spec.intervals + PAD - 1)
        f = u - i
        pair = torch.stack([i, i + 1]).long()
        j = key_anchor.index_select(0, pair[:1])
        ends = torch.cat([j, j + 1])
        at = anchor_at.index_select(0, ends)
        line = self.anchors.index_select(0, ends)
        out = torch.lerp(line[0], line[1], (i + f - at[0]) / (at[1] - at[0]))
        keys2 = self.residual.index_select(0, pair).float()
        fine = torch.lerp(keys2[0], keys2[1], f)
        out = out.add_(fine) if self.codec.scale is None else out.addcmul_(fine, self.codec.scale)
        if self.moving.numel() == rows.shape[0]:
            return out.add_(rows)
        return rows.clone().index_add_(0, self.moving, out)

    def anchor_index(self, device: torch.device) -> Tuple[Tensor, Tensor]:
        """Per key, the anchor line it lies on [K] (int64), and each anchor's key index [A] (fp32): what a frame
        on the device reads to find its segment's anchors (made once)."""
        if self._key_anchor is None:
            keys = torch.tensor(self._anchor_keys, device=device)
            k = torch.arange(self.spec.intervals + 2 * PAD, device=device)
            self._key_anchor = (torch.searchsorted(keys, k, right=True) - 1).clamp(0, len(keys) - 2)
            self._anchor_at = keys.float()
        return self._key_anchor, self._anchor_at  # type: ignore[return-value]

    def frame_rows(self, rows: Tensor, network_rows: Optional[Tensor], field: Any, xyz: Tensor, time: float) -> Tensor:
        """Every Gaussian's means, quaternions and scale rows [N, 10] at `time` for a frame: `rows` are the
        canonical values plus the base ([N, 10]: means, normalised quaternions, `scale_rows`; made once per table),
        `network_rows` the canonical values of the network's Gaussians. The same numbers as `deformed`, in
        a handful of kernels."""
        i, f = self.spec.segment(time)
        if self.moving.numel() == rows.shape[0]:  # every Gaussian moves (the usual case): no scatter
            out = self.interpolate_moving(self.spec.order, i, f).add_(rows)
        else:
            out = rows.clone()
            if self.moving.numel():
                out.index_add_(0, self.moving, self.interpolate_moving(self.spec.order, i, f))
        if self.network.numel():
            out.index_copy_(0, self.network, self.network_offsets(field, xyz, time).add_(network_rows))
        return out

    def network_offsets(self, field: Any, xyz: Tensor, time: float) -> Tensor:
        """The MLP's own offsets [R, 10] of the Gaussians on the network."""
        return torch.cat(field(xyz[self.network], float(time)), dim=-1).float()

    def offsets_at(self, time: float) -> Tensor:
        """Every Gaussian's table offsets [N, 10] at `time` (the network's Gaussians included, as tabled)."""
        if self.is_preview:
            raise RuntimeError("a time table's preview holds no keys: it renders halfway frames only")
        i, f = self.spec.segment(time)
        out = self.base.clone()
        if self.moving.numel():
            out.index_add_(0, self.moving, self.interpolate_moving(self.spec.order, i, f))
        return out

    @torch.no_grad()
    def offsets_halfway(self, field: Any, xyz: Tensor, time: float) -> Tensor:
        """The offsets at `time` as a table of this spacing, order and precision would give them if `time`
        lay exactly halfway between two keyframes: the field sampled at time +- 0.5, 1.5 spacings, the outer
        two kept whole as anchors, the inner two stored as this table stores fine residuals (same precision and
        scales), interpolated at the midpoint. What the render switches are measured with: the worst place for
        every measured view inside the range; at its ends, where the table's keys beyond are reflected, the samples
        beyond are reflected as those keys are (`reflected_offsets`), so the probe gives what the table renders."""
        h = self.spec.spacing
        times = [time - 1.5 * h, time - 0.5 * h, time + 0.5 * h, time + 1.5 * h]
        out = self.base.clone()
        if self.moving.numel():
            with tf32_products(self.tf32):
                r = (reflected_offsets(field, xyz, self.spec, times) - self.base)[:, self.moving]
            probe = TimeTable(
                TableSpec(**{**self.spec.to_dict(), "intervals": 4 - 2 * PAD, "anchor_every": 3}),
                self.base,
                r[[0, 3]],
                torch.empty(0),
                self.moving,
                self.network,
                {},
                self.codec,
            )
            probe.residual = torch.stack([self.codec.encode(r[k] - probe._line(k)) for k in range(4)])
            out.index_add_(0, self.moving, probe.interpolate_moving(self.spec.order, 1, 0.5))
        return out

    def deformed(self, field: Any, canonical: Any, time: float, halfway: bool = False) -> Tuple[Tensor, Tensor, Tensor]:
        """Means, quaternions (unnormalised) and log-scales at `time`, composed as the field composes them;
        the network's Gaussians get the MLP's own offsets."""
        xyz = canonical.means.detach()
        d = self.offsets_halfway(field, xyz, time) if halfway else self.offsets_at(time)
        if self.network.numel():
            d.index_copy_(0, self.network, self.network_offsets(field, xyz, time))
        d = d.to(canonical.means.dtype)
        quats = F.normalize(canonical.quats, dim=-1)
        log_scales = canonical.log_scales + log_scale_offset(canonical.log_scales, d[:, 7:], self.scale_offset)
        return canonical.means + d[:, :3], quats + d[:, 3:7], log_scales


def scale_rows(log_scales: Tensor, scale_offset: ScaleOffset) -> Tensor:
    """What a tabled frame's rows hold of each Gaussian's scales [N, 3], so that adding the table's offsets composes
    them as the model does: the log-scales under `log`, the scales themselves under `linear`."""
    return log_scales if scale_offset == "log" else torch.exp(log_scales)


def row_scales(rows: Tensor, scale_offset: ScaleOffset) -> Tensor:
    """The rasterizer's scales from a frame's scale rows [N, 3] (`scale_rows` plus offsets): exp of log-scales, or
    the scales as garo_ns.deformation.linear_scales takes them."""
    return torch.exp(rows) if scale_offset == "log" else linear_scales(rows)


def table_bytes(intervals: int, gaussians: int, precision: str, anchor_every: int = 16) -> int:
    """The most bytes a table of `intervals` over `gaussians` Gaussians takes (`TimeTable.nbytes`): every
    Gaussian moving and every one on the network, which no table exceeds."""
    spec = TableSpec(0.0, 1.0, intervals, precision=precision, anchor_every=anchor_every)  # type: ignore[arg-type]
    keys, anchors = intervals + 2 * PAD, len(spec.anchor_keys())
    row = gaussians * CHANNELS
    fine = torch.empty(0, dtype=Codec(precision).dtype).element_size()  # a stored residual, as `Codec` keeps it
    scale = row * 4 if precision in LEVELS else 0  # the codec's fp32 scale per Gaussian and channel
    return row * 4 * (1 + anchors) + row * fine * keys + scale + gaussians * 8 * 2  # + moving and network indices


def build_bytes(intervals: int, gaussians: int, precision: str, anchor_every: int = 16) -> int:
    """The most bytes a `TimeTable.build` of such a table holds at once, its fp32 scratch aside (`scratch_bytes`,
    which the budget's remainder caps): the table with every Gaussian's keys, and the copy of the moving Gaussians'
    keys and anchors made while the whole keys are still held."""
    spec = TableSpec(0.0, 1.0, intervals, precision=precision, anchor_every=anchor_every)  # type: ignore[arg-type]
    row = gaussians * CHANNELS
    fine = torch.empty(0, dtype=Codec(precision).dtype).element_size()
    copy = row * fine * (intervals + 2 * PAD) + row * 4 * len(spec.anchor_keys())
    return table_bytes(intervals, gaussians, precision, anchor_every) + copy


def plan_intervals(
    frames: int, keys_per_frame: int, gaussians: int, budget_mb: float, precision: str, anchor_every: int = 16
) -> int:
    """Intervals of a table over `frames` training times with `keys_per_frame` keys per gap, reduced to the
    most whose build (`build_bytes`: the table and what its build holds besides) fits `budget_mb` (0: not even two
    intervals fit)."""
    want = max(1, keys_per_frame * max(frames - 1, 1))
    return fitting_intervals(want, gaussians, budget_mb, precision, anchor_every)


def fitting_intervals(want: int, gaussians: int, budget_mb: float, precision: str, anchor_every: int = 16) -> int:
    """The most intervals, up to `want`, whose build (`build_bytes`) fits `budget_mb` (0: not even two fit)."""
    budget = budget_mb * 2**20
    lo, hi = 1, want  # the most intervals that fit lies in [lo, hi] once lo fits
    if build_bytes(lo, gaussians, precision, anchor_every) > budget:
        return 0
    while lo < hi:  # bytes grow with the intervals
        mid = (lo + hi + 1) // 2
        if build_bytes(mid, gaussians, precision, anchor_every) <= budget:
            lo = mid
        else:
            hi = mid - 1
    return lo if lo >= 2 else 0


def window_spec(spec: TableSpec, time: float, intervals: int) -> TableSpec:
    """The stretch of `spec`'s table around `time` that `intervals` of its intervals cover: keys at the same times as
    the whole table's there (its spacing, on its grid), so a frame inside interpolates the same keys. Windows start
    on a grid of half a window: nearby times share one, and a time lies at least a quarter of a window inside its own
    (but at the ends of the range). `spec` itself where `intervals` cover the whole range."""
    if intervals >= spec.intervals:
        return spec
    step = max(intervals // 2, 1)
    u = (min(max(float(time), spec.t_lo), spec.t_hi) - spec.t_lo) / spec.spacing
    start = min(max(round((u - 0.5 * intervals) / step) * step, 0), spec.intervals - intervals)
    end, h = start + intervals, spec.spacing
    t_lo, t_hi = spec.t_lo + start * h, spec.t_hi if end == spec.intervals else spec.t_lo + end * h
    lo, hi = spec.ends()  # the keys beyond the whole range reflect through its ends, not the window's
    return TableSpec(
        **{**spec.to_dict(), "t_lo": t_lo, "t_hi": t_hi, "intervals": intervals, "range_lo": lo, "range_hi": hi}
    )


def spec_for(
    times: Optional[Tensor],
    keys_per_frame: int,
    gaussians: int,
    budget_mb: float,
    precision: str,
    tolerance: float,
    extent: float,
) -> Tuple[Optional[TableSpec], str]:
    """The table spec for a model trained on `times`, or None and why not."""
    if times is None or times.numel() == 0:
        return None, "no training times"
    lo, hi = float(times.min()), float(times.max())
    n = plan_intervals(int(times.numel()), keys_per_frame, gaussians, budget_mb, precision)
    if n == 0:
        return None, f"over the memory budget ({budget_mb:g} MB) even with two intervals"
    return TableSpec(lo, hi, n, "linear", precision, tolerance, float(extent)), ""  # type: ignore[arg-type]
