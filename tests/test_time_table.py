"""The time table: exact at its keyframes, within the predicted interpolation error between them, its budget."""

from __future__ import annotations

import math

import pytest
import torch

from garo_ns.render.frame import Canonical, activate, compose, table_rows
from garo_ns.render.time_table import (
    PAD,
    TableSpec,
    TimeTable,
    build_bytes,
    fitting_intervals,
    plan_intervals,
    spec_for,
    table_bytes,
    weights,
    window_spec,
)

W = 2 * math.pi  # one period over the time range


class SineField:
    """Offsets of known smooth motion: d = amp_i sin(W t + phase_i) on every channel, for the Gaussian whose
    canonical x is i."""

    def __init__(self, amp, phase):
        self.amp, self.phase = amp, phase
        self.calls = 0

    def __call__(self, xyz, t):
        self.calls += 1
        i = xyz[:, 0].long()
        d = self.amp[i, None] * torch.sin(W * float(t) + self.phase[i, None]).expand(-1, 10)
        return d[:, :3], d[:, 3:7], d[:, 7:]


def _field(n=64, seed=0, amp=0.05):
    g = torch.Generator().manual_seed(seed)
    return SineField(amp * torch.rand(n, generator=g, dtype=torch.float64).float(), 6 * torch.rand(n, generator=g))


def _xyz(n=64):
    return torch.stack([torch.arange(n).float(), torch.zeros(n), torch.zeros(n)], dim=-1)


def _spec(intervals, **kw):
    return TableSpec(**{"t_lo": 0.0, "t_hi": 1.0, "intervals": intervals, "precision": "fp32", "tolerance": 1e-4, **kw})


def test_keys_sit_halfway_between_evenly_spaced_training_times():
    spec = _spec(2 * 9)  # 10 training times, two intervals each
    for j in range(10):
        i, f = spec.segment(j / 9)
        assert f == pytest.approx(0.5) and PAD - 1 <= i <= spec.intervals + PAD - 1
    keys = spec.key_times()
    assert keys[PAD - 1] < 0 < keys[PAD] and keys[-PAD] > 1  # the range is inside, with padding
    assert torch.allclose(keys[1:] - keys[:-1], torch.full((len(keys) - 1,), spec.spacing))


def test_the_table_reproduces_the_field_at_its_keyframes():
    field = _field()
    xyz = _xyz()
    table = TimeTable.build(_spec(12), field, xyz)
    for t in table.spec.key_times()[PAD - 1 : -PAD + 1].tolist():
        if 0 <= t <= 1:
            exact = torch.cat(field(xyz, t), dim=-1)
            assert torch.allclose(table.offsets_at(t), exact, atol=1e-6), t


@pytest.mark.parametrize("order", ["linear", "cubic"])
def test_halfway_error_is_what_the_order_predicts(order):
    field = _field()
    xyz = _xyz()
    for intervals in (16, 32):
        table = TimeTable.build(_spec(intervals, order=order), field, xyz)
        table.spec = TableSpec(**{**table.spec.to_dict(), "order": order})  # this order, whatever the build picks
        h = table.spec.spacing
        # Midpoint error: linear h^2/8 max|f''|; cubic (there 4-point Lagrange) 3/128 h^4 max|f''''|. The cubic's
        # midpoints next to an end read a key beyond it, the end's value reflected (2 f(end) - f(end + h/2) where
        # the field has f(end - h/2)): h^2/4 |f''| off, weighed 1/16 there.
        power = 2 if order == "linear" else 4
        bound = field.amp * (W * h) ** power * (1 / 8 if order == "linear" else 3 / 128)
        near_end = bound + (0.0 if order == "linear" else field.amp * (W * h) ** 2 / 64)
        worst = torch.zeros(64)
        for t in (table.spec.key_times()[PAD:-PAD] - h / 2).tolist():
            if 0 <= t <= 1:
                err = (table.offsets_at(t) - torch.cat(field(xyz, t), dim=-1)).abs().amax(-1)
                inside = 1.5 * h < t < 1 - 1.5 * h
                assert bool((err <= (bound if inside else near_end) * 1.001 + 1e-6).all()), t
                worst = torch.maximum(worst, err)
        assert bool((worst >= 0.5 * bound).any())  # the prediction is the error's size, not a loose bound


@pytest.mark.parametrize("order", ["linear", "cubic"])
@pytest.mark.parametrize("precision", ["fp32", "int16"])
def test_the_ranges_first_and_last_times_are_the_fields_own(order, precision):
    """Each end of the range lies halfway between the last key inside and the first beyond: keys beyond that
    sample the field there bring in motion the field shows at times it never trained on (here a sine that goes on),
    and both orders would miss the end by about what they miss a midpoint by. Reflected through the end, they
    give the field's own value there; the next midpoint in stays within its bound (test above)."""
    field, xyz = _field(amp=0.5), _xyz()
    for t_lo, t_hi in ((0.0, 1.0), (0.15, 0.8)):
        spec = _spec(12, order=order, precision=precision, t_lo=t_lo, t_hi=t_hi)
        table = TimeTable.build(spec, field, xyz)
        table.spec = TableSpec(**{**table.spec.to_dict(), "order": order})  # this order, whatever the build picks
        for t in (t_lo, t_hi):
            exact = torch.cat(field(xyz, t), dim=-1)
            err = float((table.offsets_at(t) - exact).abs().max())
            # fp32 keys: exact up to rounding; int16: up to the fine residuals' step (a 32767th of their range).
            assert err <= (1e-6 if precision == "fp32" else 2e-5), (t, err)
        # A window at an end reflects through the whole range's end, as the whole table does: the same frames.
        for t in (t_lo, t_hi):
            window = TimeTable.build(window_spec(spec, t, 4), field, xyz)
            window.spec = TableSpec(**{**window.spec.to_dict(), "order": order})
            assert torch.allclose(window.offsets_at(t), table.offsets_at(t), atol=2e-5)
        inner = window_spec(spec, 0.5 * (t_lo + t_hi), 4)
        assert inner.range_lo == t_lo and inner.range_hi == t_hi and t_lo < inner.t_lo


def test_the_tolerance_holds_at_every_midpoint_of_a_dense_table_those_next_to_the_ends_too():
    """A dense table's build checks a spread of 64 midpoints. A cubic's weakest are the two next to the ends, where
    it reads a reflected key: (W h)^2 / 64 at amplitude 1 (4.6e-5 for the fast Gaussian here, 60 times its error
    inside). The spread starts there, so that Gaussian goes to the network rather than miss the tolerance."""
    field = _field(amp=0.05)
    field.amp[0] = 3.0
    xyz = _xyz()
    table = TimeTable.build(_spec(200, tolerance=1e-5), field, xyz)
    tabled = torch.ones(64, dtype=torch.bool)
    tabled[table.network] = False
    h = table.spec.spacing
    for t in (table.spec.key_times()[PAD:-PAD] - h / 2).tolist():
        if 0 <= t <= 1:
            err = (table.offsets_at(t) - torch.cat(field(xyz, t), dim=-1)).abs().amax(-1)
            assert float(err[tabled].max()) <= table.spec.tolerance * 1.01, t
    assert TimeTable.field_passes(table.spec) == 1 + len(table.spec.anchor_keys()) + 200 + 2 * PAD + 64


def test_a_range_of_one_time_gives_every_key_the_fields_value_there():
    field, xyz = _field(), _xyz()
    table = TimeTable.build(_spec(2, t_lo=0.3, t_hi=0.3), field, xyz)
    exact = torch.cat(field(xyz, 0.3), dim=-1)
    for t in (0.0, 0.3, 0.9):  # clamped to the range
        assert torch.allclose(table.offsets_at(t), exact, atol=1e-6)


def test_the_build_picks_the_order_that_keeps_more_gaussians_tabled_and_the_rest_on_the_network():
    field = _field(amp=0.05)
    fast = torch.arange(64) < 4
    field.amp[fast] = 3.0  # a few Gaussians move much more: linear cannot follow them at this spacing
    xyz = _xyz()
    # 32 intervals: the cubic's midpoints next to the range's ends, which read a reflected key, stay within the
    # tolerance too (3 (W h)^2 / 64 < 2e-3), where linear's everywhere miss it (3 (W h)^2 / 8).
    table = TimeTable.build(_spec(32, tolerance=2e-3), field, xyz)
    assert table.info["network_by_order"]["cubic"] < table.info["network_by_order"]["linear"]
    assert table.spec.order == "cubic"
    linear_only = TimeTable.build(_spec(64, tolerance=1e-2), field, xyz)
    assert linear_only.spec.order == "linear"  # a tie at this spacing: the cheaper order
    # Those left to the network get the field's own offsets at any time.
    strict = TimeTable.build(_spec(8, tolerance=1e-3), field, xyz)
    assert 0 < strict.network.numel() < 64
    assert set(strict.network.tolist()) >= set(torch.nonzero(fast).flatten().tolist())
    canonical = Canonical(
        xyz, torch.tensor([[1.0, 0, 0, 0]]).repeat(64, 1), torch.zeros(64, 3), *[torch.zeros(64, 1)] * 3
    )
    t = 0.37
    means = strict.deformed(field, canonical, t)[0]
    exact = compose(field, canonical, t)[0]
    assert torch.allclose(means[strict.network], exact[strict.network], atol=1e-6)


@pytest.mark.parametrize("precision", ["fp32", "int16"])
@pytest.mark.parametrize("intervals, tolerance", [(16, 2e-3), (8, 1e-3)])  # cubic, none on the network; some on it
def test_a_preview_renders_halfway_as_its_table_does_less_the_keys_rounding(precision, intervals, tolerance):
    field = _field(amp=0.05)
    field.amp[:4] = 3.0  # a few Gaussians the linear order cannot follow at this spacing: the network or cubic
    xyz = _xyz()
    spec = _spec(intervals, tolerance=tolerance, precision=precision)
    built, preview = TimeTable.build(spec, field, xyz), TimeTable.preview(spec, field, xyz)
    assert preview.is_preview and not built.is_preview
    assert preview.spec == built.spec and preview.info["network_by_order"] == built.info["network_by_order"]
    assert torch.equal(preview.network, built.network)
    # A halfway frame reads four keys, each stored to within half of its step (int16: the Gaussian's largest fine
    # residual / 32767; fp32: exact), with Catmull-Rom's weights' magnitudes summing to at most 1.25.
    step = built.codec.scale if built.codec.scale is not None else torch.zeros(64, 10)
    for t in (0.1, 0.37, 0.8):
        gap = (built.offsets_halfway(field, xyz, t) - preview.offsets_halfway(field, xyz, t)).abs()
        assert bool((gap <= 1.25 * 0.5 * step + 1e-6).all()), t
    if precision == "int16":
        assert float(gap.max()) > 0  # the rounding is there, and the preview leaves it out


@pytest.mark.parametrize("order", ["linear", "cubic"])
@pytest.mark.parametrize("precision", ["fp32", "int16"])
def test_the_probe_that_decides_measures_the_table_that_renders(order, precision):
    """The render switches record the change `offsets_halfway` makes; what a user sees is the built table's
    `offsets_at`. At evenly spaced training times (each halfway between two keys) the two must be the same
    offsets, up to the keys' rounding, so that the recorded change is the rendered one: a probe that sampled a
    denser table (a quarter of the spacing) would record a change many times smaller."""
    field = _field(amp=0.05)
    xyz = _xyz()
    table = TimeTable.build(_spec(2 * 9, order=order, precision=precision), field, xyz)
    table.spec = TableSpec(**{**table.spec.to_dict(), "order": order})
    step = table.codec.scale if table.codec.scale is not None else torch.zeros(64, 10)
    for j in range(10):
        t = j / 9  # the training times the table's keys straddle
        assert table.spec.segment(t)[1] == pytest.approx(0.5)
        rendered, probed = table.offsets_at(t), table.offsets_halfway(field, xyz, t)
        exact = torch.cat(field(xyz, t), dim=-1)
        rendered_err, probed_err = (rendered - exact).abs().amax(), (probed - exact).abs().amax()
        assert bool(((rendered - probed).abs() <= 1.25 * step + 1e-6).all()), t
        assert float(probed_err) == pytest.approx(float(rendered_err), rel=0.05, abs=2e-6), t
        if 0 < j < 9:
            assert float(rendered_err) > 1e-5  # an interpolation error there is to measure
        else:  # the range's ends: the keys beyond are reflected through them, and the probe's samples as well
            assert float(rendered_err) <= float(step.max()) + 1e-6  # up to the keys' rounding


def test_a_preview_costs_the_same_few_field_passes_however_many_keys_its_table_has():
    xyz = _xyz()
    calls = {}
    for intervals in (200, 2000):
        field = _field()
        preview = TimeTable.preview(_spec(intervals), field, xyz)
        calls[intervals] = field.calls
        built_field = _field()
        TimeTable.build(_spec(intervals), built_field, xyz)
        assert built_field.calls > intervals  # a build samples every key
    # The middle of the range, 64 midpoints and the four keys around each.
    assert calls[200] == calls[2000] <= 1 + 64 * 5
    with pytest.raises(RuntimeError, match="halfway frames only"):
        preview.offsets_at(0.5)


def test_fp16_residuals_cost_what_their_resolution_predicts():
    field = _field(amp=0.5)
    xyz = _xyz()
    full = TimeTable.build(_spec(40), field, xyz)
    half = TimeTable.build(_spec(40, precision="fp16"), field, xyz)
    assert half.nbytes() < 0.6 * full.nbytes()
    t = float(half.spec.key_times()[PAD + 3])
    # A residual of size <= 1 (twice the amplitude) in fp16: at most half a unit in the last place, 2^-11.
    assert (half.offsets_at(t) - full.offsets_at(t)).abs().max() <= 2**-11


def test_gaussians_that_do_not_move_are_stored_once():
    field = _field()
    field.amp[32:] = 0.0
    table = TimeTable.build(_spec(10), field, _xyz())
    assert table.moving.tolist() == list(range(32)) and table.residual.shape[1] == 32


def test_the_memory_budget_gives_fewer_keys_or_no_table():
    n = 100_000
    want = plan_intervals(150, 2, n, budget_mb=10_000, precision="fp16")
    assert want == 2 * 149
    fewer = plan_intervals(150, 2, n, budget_mb=200, precision="fp16")
    assert 2 <= fewer < want
    # The most whose build fits (the table and the copies its build makes): one interval more would not.
    assert build_bytes(fewer, n, "fp16") <= 200 * 2**20 < build_bytes(fewer + 1, n, "fp16")
    assert build_bytes(fewer, n, "fp16") > table_bytes(fewer, n, "fp16")
    spec, why = spec_for(torch.linspace(0, 1, 150), 2, n, 5, "fp16", 1e-4, 1.0)
    assert spec is None and "memory budget" in why
    spec, why = spec_for(None, 2, n, 5, "fp16", 1e-4, 1.0)
    assert spec is None and why == "no training times"


@pytest.mark.parametrize("precision", ["int16", "int8", "fp16", "fp32"])
@pytest.mark.parametrize("anchor_every", [1, 4, 16])
def test_a_table_planned_for_a_budget_stays_within_it(precision, anchor_every):
    # A table refused on load for exceeding its budget by half a megabyte (the plan counted a fraction of an anchor
    # per key where the keys round up to whole anchors) is the case this guards: the plan's bytes are the table's.
    n = 64
    field = _field(n, amp=0.5)  # every Gaussian moves
    for budget_mb in (0.1, 0.274, 0.6):  # a build holds about twice its table
        intervals = plan_intervals(400, 4, n, budget_mb, precision, anchor_every)
        assert intervals >= 2
        spec = _spec(intervals, precision=precision, anchor_every=anchor_every, tolerance=0.0)  # all on the network
        table = TimeTable.build(spec, field, _xyz(n))
        assert table.moving.numel() == n and table.network.numel() == n
        assert table.nbytes() == table_bytes(intervals, n, precision, anchor_every)
        assert build_bytes(intervals, n, precision, anchor_every) <= budget_mb * 2**20
        if intervals < 4 * 399:
            assert build_bytes(intervals + 1, n, precision, anchor_every) > budget_mb * 2**20


def test_int16_keys_resolve_each_gaussians_motion_evenly():
    field = _field(amp=0.5)
    field.amp[0] = 40.0  # one Gaussian far from the base: fp16's steps there are coarse
    xyz = _xyz()
    full = TimeTable.build(_spec(40), field, xyz)
    q16 = TimeTable.build(_spec(40, precision="int16"), field, xyz)
    half = TimeTable.build(_spec(40, precision="fp16"), field, xyz)
    assert q16.residual.dtype == torch.int16 and q16.nbytes() < 0.6 * full.nbytes()
    worst16, worst_half = torch.zeros(64, 10), torch.zeros(64, 10)
    for t in torch.linspace(0, 1, 51).tolist():
        worst16 = torch.maximum(worst16, (q16.offsets_at(t) - full.offsets_at(t)).abs())
        worst_half = torch.maximum(worst_half, (half.offsets_at(t) - full.offsets_at(t)).abs())
    # At most half a step of each Gaussian's own scale (its largest residual / 32767), plus float rounding.
    step = (2 * field.amp)[:, None] / 32767
    assert bool((worst16 <= 0.5 * step * 1.01 + 1e-5).all())
    # fp16's step grows with the residual: on the far Gaussian it errs many times more.
    assert worst16[0].max() < 0.25 * worst_half[0].max()


@pytest.mark.parametrize("precision, levels", [("int16", 32767), ("int8", 127)])
def test_integer_keys_error_follows_the_bends_not_the_size_of_the_motion(precision, levels):
    """Fine residuals from the anchor lines are what an integer key stores: on dense keys its error is at most half
    a step of each Gaussian's fine-residual range, and on a Gaussian that moves 80x more than the others that step
    is hundreds of times finer than a step over its whole motion (what whole residuals from the base gave)."""
    field = _field(amp=0.5)
    field.amp[0] = 40.0
    xyz = _xyz()
    spec = dict(intervals=320, anchor_every=4, tolerance=1.0)  # both linear: int8's step alone would tip the order
    full = TimeTable.build(_spec(**spec), field, xyz)
    quantised = TimeTable.build(_spec(precision=precision, **spec), field, xyz)
    assert quantised.residual.dtype == getattr(torch, precision) and quantised.anchors.dtype == torch.float32
    anchor_keys = _spec(**spec).anchor_keys()
    assert full.spec.order == quantised.spec.order == "linear"
    assert len(quantised.anchors) == len(anchor_keys) and anchor_keys[-1] == 323
    worst = torch.zeros(64, 10)
    for t in torch.linspace(0, 1, 97).tolist():
        worst = torch.maximum(worst, (quantised.offsets_at(t) - full.offsets_at(t)).abs())
    fine_step = quantised.codec.scale  # [M, 10]: each Gaussian's largest fine residual / levels
    rounding = 4 * torch.finfo(torch.float32).eps * field.amp[:, None]  # fp32 sums at the offsets' own size
    assert bool((worst <= 0.5 * fine_step * 1.01 + rounding + 2e-6).all())
    whole_step = 2 * 40.0 / levels
    assert float(fine_step[0].max()) < whole_step / 300


class KinkField:
    """Offsets that bend sharply once, as a ReLU MLP's do: d = amp_i * max(t - t0_i, 0) on every channel."""

    def __init__(self, n=64, seed=0):
        g = torch.Generator().manual_seed(seed)
        self.amp = 0.5 + torch.rand(n, generator=g)
        self.t0 = 0.1 + 0.8 * torch.rand(n, generator=g)

    def __call__(self, xyz, t):
        i = xyz[:, 0].long()
        d = (self.amp[i] * (float(t) - self.t0[i]).clamp_min(0.0))[:, None].expand(-1, 10)
        return d[:, :3], d[:, 3:7], d[:, 7:]


def test_at_one_budget_int8_keys_follow_a_kinked_motion_closer_than_int16_keys():
    """Where the field bends sharply the error between keys falls only as 1/K, so the keys int8 fits in a budget
    (about 1.8x) outweigh its coarser step: what the render switches' int8 rungs rely on."""
    field, xyz, n = KinkField(), _xyz(), 64
    budget_mb = 0.25
    worst = {}
    for precision in ("int16", "int8"):
        intervals = plan_intervals(200, 64, n, budget_mb, precision)
        table = TimeTable.build(_spec(intervals, precision=precision, tolerance=1.0), field, xyz)
        assert table.nbytes() <= budget_mb * 2**20 and table.network.numel() == 0
        times = torch.rand(4000, generator=torch.Generator().manual_seed(3)).tolist()
        worst[precision] = max(float((table.offsets_at(t) - torch.cat(field(xyz, t), -1)).abs().max()) for t in times)
        worst[precision, "intervals"] = intervals
    assert worst["int8", "intervals"] > 1.7 * worst["int16", "intervals"]
    assert worst["int8"] < 0.8 * worst["int16"]


def test_anchors_are_exact_and_the_table_stays_exact_at_every_key():
    field = _field()
    xyz = _xyz()
    table = TimeTable.build(_spec(30, precision="int16", anchor_every=7), field, xyz)
    keys = table.spec.key_times()

    def key(k):  # the field's inside the range; beyond it, the end's value reflected
        t = float(keys[k])
        if 0 <= t <= 1:
            return torch.cat(field(xyz, t), dim=-1)
        end = 0.0 if t < 0 else 1.0
        return 2 * torch.cat(field(xyz, end), dim=-1) - torch.cat(field(xyz, 2 * end - t), dim=-1)

    for k in table.spec.anchor_keys():
        assert torch.allclose(table.anchors[table.spec.anchor_keys().index(k)] + table.base, key(k), atol=1e-6)
    for k in range(PAD, len(keys) - PAD):
        exact = torch.cat(field(xyz, float(keys[k])), dim=-1)
        # int16: a key is exact to half its fine step
        assert ((table.offsets_at(float(keys[k])) - exact).abs() <= 0.5 * table.codec.scale * 1.01 + 1e-6).all()


@pytest.mark.parametrize(
    "order, intervals, tolerance, anchor_every, precision",
    [
        ("linear", 61, 1e-2, 4, "int16"),  # anchors every 4 keys: many segments end on an anchor
        ("linear", 61, 1e-2, 16, "fp16"),
        ("linear", 61, 1e-2, 16, "int8"),
        ("cubic", 32, 2e-3, 5, "int16"),
        ("cubic", 8, 1e-3, 3, "fp32"),  # a strict tolerance: some Gaussians on the network
    ],
)
def test_a_frame_reads_the_table_as_the_reference_does(order, intervals, tolerance, anchor_every, precision):
    """The frame's path (cached canonical rows, linear keys in four kernels) against `deformed` + `activate`."""
    field = _field(amp=0.05)
    field.amp[:4] = 3.0  # fast: cubic wins at coarse spacings, and the strictest build sends some to the network
    field.amp[48:] = 0.0  # still: not in the moving set
    xyz = _xyz()
    spec = _spec(intervals, tolerance=tolerance, anchor_every=anchor_every, precision=precision)
    table = TimeTable.build(spec, field, xyz)
    assert table.spec.order == order and table.moving.numel() == 48
    g = torch.Generator().manual_seed(1)
    canonical = Canonical(
        xyz,
        torch.randn(64, 4, generator=g),
        0.3 * torch.randn(64, 3, generator=g),
        torch.randn(64, 1, generator=g),
        torch.randn(64, 3, generator=g),
        torch.randn(64, 15, 3, generator=g),
    )
    rows, network_rows, opacities, colors = table_rows(canonical, table)
    keys = table.spec.key_times()
    times = torch.cat([torch.linspace(-0.05, 1.05, 89), keys[[table._anchor_keys[1], table._anchor_keys[-2]]]])
    for t in times.tolist():
        ref = activate(canonical, table.deformed(field, canonical, t))
        d = table.frame_rows(rows, network_rows, field, xyz, t)
        for got, want in zip((d[:, :3], d[:, 3:7], torch.exp(d[:, 7:]), opacities, colors), ref[:5]):
            assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), t
    if tolerance == 1e-3:
        assert table.network.numel() > 0
    # Every Gaussian moving: the frame adds to the rows without a scatter.
    field.amp[48:] = 0.01
    whole = TimeTable.build(spec, field, xyz)
    rows, network_rows, _, _ = table_rows(canonical, whole)
    for t in (0.013, 0.5, 0.871):
        ref = whole.deformed(field, canonical, t)
        d = whole.frame_rows(rows, network_rows, field, xyz, t)
        assert torch.allclose(d[:, :3], ref[0], atol=1e-6) and torch.allclose(d[:, 7:], ref[2], atol=1e-6)


@pytest.mark.parametrize("anchor_every", [3, 4, 16])
@pytest.mark.parametrize("precision", ["int16", "int8", "fp32"])
def test_the_fast_orders_are_the_stored_keys_interpolated(anchor_every, precision):
    """Linear and cubic frames take shortcuts through the anchor lines; both equal the definition: the stored fine
    residuals interpolated plus the same interpolation of the lines, in every segment (across anchors too)."""
    field = _field(amp=0.3)
    table = TimeTable.build(_spec(29, anchor_every=anchor_every, precision=precision), field, _xyz())
    line = table._line
    for order in ("linear", "cubic"):
        first = PAD - 1 if order == "linear" else PAD  # a cubic segment needs the key before it
        for i in range(first, table.spec.intervals + PAD):
            for f in (0.0, 0.3, 0.5, 0.9):
                offsets, w = weights(order, f)
                want = table.codec.interpolate(table.residual, order, i, f)
                for o, wk in zip(offsets, w):
                    want = want + wk * line(i + o)
                got = table.interpolate_moving(order, i, f)
                assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), (order, i, f)


@pytest.mark.parametrize("precision", ["int16", "int8"])
@pytest.mark.parametrize("still", [0, 16])
def test_the_device_time_frame_is_the_host_time_frame(still, precision):
    """`rows_at` (segment and keys found on the device, what the frame's CUDA graph replays) against `frame_rows`."""
    field = _field(amp=0.05)
    field.amp[64 - still :] = 0.0
    xyz = _xyz()
    table = TimeTable.build(_spec(61, tolerance=1e-2, anchor_every=4, precision=precision), field, xyz)
    assert table.graphable and table.moving.numel() == 64 - still
    rows = torch.randn(64, 10, generator=torch.Generator().manual_seed(2))
    keys = table.spec.key_times()
    for t in torch.cat([torch.linspace(-0.05, 1.05, 67), keys[table._anchor_keys[1:-1]]]).tolist():
        want = table.frame_rows(rows, None, field, xyz, t)
        got = table.rows_at(rows, torch.tensor(t))
        assert torch.allclose(got, want, rtol=1e-5, atol=1e-6), t


def test_tables_with_cubic_keys_or_network_gaussians_take_the_host_time_frame():
    field = _field(amp=0.05)
    field.amp[:4] = 3.0
    assert not TimeTable.build(_spec(16, tolerance=2e-3), field, _xyz()).graphable  # cubic
    linear = TimeTable.build(_spec(61, tolerance=1e-2), field, _xyz())
    assert linear.spec.order == "linear" and linear.graphable
    linear.network = torch.tensor([0])  # a Gaussian on the network: its MLP rows are not in the graph
    assert not linear.graphable


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_a_tabled_frame_replayed_as_a_cuda_graph_is_the_eager_frame():
    from garo_ns.deformation import DeformationField
    from garo_ns.render.frame import FramePath, FrameSettings

    device = torch.device("cuda")
    g = torch.Generator().manual_seed(3)
    n = 4096
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=3, width=64, skip=1).to(device).eval()
    canonical = Canonical(
        *(
            x.to(device)
            for x in (
                torch.rand(n, 3, generator=g),
                torch.randn(n, 4, generator=g),
                0.1 * torch.randn(n, 3, generator=g) - 3,
                torch.randn(n, 1, generator=g),
                torch.randn(n, 3, generator=g),
                torch.randn(n, 15, 3, generator=g),
            )
        )
    )
    spec = _spec(40, tolerance=1.0)  # every Gaussian tabled, linear
    eager, graphed = FramePath(), FramePath()
    with torch.no_grad():
        for t in (0.05, 0.5, 0.5, 0.93):
            a = eager.splats(field, canonical, None, None, t, FrameSettings(time_table=True), spec)
            b = graphed.splats(field, canonical, None, None, t, FrameSettings(time_table=True, cuda_graph=True), spec)
            assert b.graph is not None and a.graph is None
            for x, y in zip(a[:5], b[:5]):
                assert torch.allclose(x, y, rtol=1e-5, atol=1e-6), t
    assert graphed._graph.captures == 1  # one capture, replayed at every time


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need CUDA")
def test_a_windowed_table_replayed_as_a_cuda_graph_is_the_whole_tables_frame():
    """Under `time_table_window_mb` the graphed frame (the one-kernel lookup where Triton runs) takes each window's
    table: a capture per window, the whole table's frames."""
    from garo_ns.deformation import DeformationField
    from garo_ns.render.frame import FramePath, FrameSettings

    device = torch.device("cuda")
    g = torch.Generator().manual_seed(4)
    n = 4096
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=3, width=64, skip=1).to(device).eval()
    parts = (torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g), 0.1 * torch.randn(n, 3, generator=g) - 3)
    rest = (torch.randn(n, 1, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, 15, 3, generator=g))
    canonical = Canonical(*(x.to(device) for x in (*parts, *rest)))
    spec = _spec(120, tolerance=1.0)
    whole, windowed = FramePath(), FramePath()
    windowed.table_window_mb = table_bytes(120, n, "fp32") / 2**20 / 3
    settings = FrameSettings(time_table=True, cuda_graph=True)
    with torch.no_grad():
        for t in torch.linspace(0, 1, 13).tolist():
            a = whole.splats(field, canonical, None, None, t, settings, spec)
            a = [x.clone() for x in a[:5]]
            b = windowed.splats(field, canonical, None, None, t, settings, spec)
            assert b.graph is not None and windowed.table.spec.intervals < 120
            for x, y in zip(a, b[:5]):
                assert torch.allclose(x, y, rtol=1e-5, atol=1e-6), t
    assert whole._graph.captures == 1 and 3 <= windowed._graph.captures <= 13


def test_a_field_that_takes_a_time_per_row_is_sampled_several_times_per_call():
    """A table's keys on a model of some 10^4 Gaussians are thousands of small field calls: the deformation field
    takes one time per row, so the keys are sampled several at a time (from SAMPLER_TIMES times on through its
    time sampler, the positions' share of the encoding's layers made once), with the offsets (and so the table)
    those calls one time at a time give, in the same order."""
    from garo_ns.deformation import DeformationField
    from garo_ns.render.time_table import SAMPLER_TIMES, field_offsets, iter_field_offsets

    torch.manual_seed(0)
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=3, width=32, skip=1).eval()
    calls, sampled = [], []
    field.register_forward_hook(lambda module, args, out: calls.append(args[0].shape[0]))
    make_sampler = field.time_sampler

    def counting_sampler(xyz):
        sample = make_sampler(xyz)
        return lambda t: (sampled.append(t.numel() * xyz.shape[0]), sample(t))[1]

    field.time_sampler = counting_sampler
    xyz = torch.rand(300, 3) * 2 - 1
    times = torch.rand(40, generator=torch.Generator().manual_seed(1)).tolist()
    batched = field_offsets(field, xyz, times, chunk=3000)
    assert sampled == [3000] * 4 and calls == []  # ten times per call, through the sampler
    assert [k for k, _ in iter_field_offsets(field, xyz, times, chunk=3000)] == list(range(40))
    few = times[: SAMPLER_TIMES - 1]
    repeated = field_offsets(field, xyz, few, chunk=3000)  # too few times for the sampler
    assert calls == [300 * len(few)]
    calls.clear()
    field.times_per_row = False  # as a stand-in field that takes one time per call
    single = field_offsets(field, xyz, times, chunk=3000)
    assert calls == [300] * 40
    assert torch.allclose(batched, single, rtol=1e-5, atol=1e-6)
    assert torch.allclose(repeated, single[: len(few)], rtol=1e-5, atol=1e-6)

    spec = _spec(60, precision="int16", tolerance=1.0)
    table = TimeTable.build(spec, field, xyz)
    field.times_per_row = True
    twin = TimeTable.build(spec, field, xyz)
    assert torch.allclose(table.anchors, twin.anchors, rtol=1e-5, atol=1e-6)
    for t in (0.03, 0.41, 0.77):
        assert torch.allclose(table.offsets_at(t), twin.offsets_at(t), atol=1e-5)


@pytest.mark.parametrize("precision", ["int16", "int8", "fp16", "fp32"])
def test_a_build_with_room_for_its_residuals_runs_the_field_over_the_keys_once_to_the_same_table(precision):
    """Integer keys need every key's residual before the first is encoded: held in fp32 scratch where it fits, the
    field runs over the keys once instead of twice and the table is the same, bit for bit; fp32 and fp16 keys are
    stored as they come, with or without room."""
    spec = _spec(40, precision=precision, tolerance=1e-3, anchor_every=6)
    keys = spec.intervals + 2 * PAD
    tables, calls = {}, {}
    for room in (0, 1 << 30):
        field = _field()
        tables[room] = TimeTable.build(spec, field, _xyz(), scratch_bytes=room)
        calls[room] = field.calls
    one_pass = precision in ("fp16", "fp32")
    assert calls[0] - calls[1 << 30] == (0 if one_pass else keys - 2)  # those inside and the two ends
    a, b = tables[0], tables[1 << 30]
    for name in ("base", "anchors", "residual", "moving", "network"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert (a.codec.scale is None) == (b.codec.scale is None) == one_pass
    if not one_pass:
        assert torch.equal(a.codec.scale, b.codec.scale)
    assert a.spec == b.spec and a.info == b.info
    # Scratch one byte short of every key's fp32 residuals: two passes.
    field = _field()
    TimeTable.build(spec, field, _xyz(), scratch_bytes=keys * 64 * 10 * 4 - 1)
    assert field.calls == calls[0]


def test_tf32_products_turn_tf32_on_inside_and_give_the_setting_back():
    from garo_ns.render.time_table import tf32_products

    flag = torch.backends.cuda.matmul
    was = flag.allow_tf32
    try:
        flag.allow_tf32 = False
        with tf32_products(True):
            assert flag.allow_tf32
        assert not flag.allow_tf32
        with tf32_products(False):
            assert not flag.allow_tf32
        with pytest.raises(RuntimeError), tf32_products(True):
            raise RuntimeError("a build that fails")
        assert not flag.allow_tf32
        flag.allow_tf32 = True
        with tf32_products(False):
            assert flag.allow_tf32  # a caller's own TF32 is left on
        assert flag.allow_tf32
    finally:
        flag.allow_tf32 = was


@pytest.mark.parametrize(
    "device",
    [
        "cpu",
        pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="TF32 products need CUDA")),
    ],
)
def test_a_frame_builds_its_table_anew_in_tf32_when_asked(device, monkeypatch):
    """`time_table_tf32` keys the frame's table: turned on, the table is built again, inside TF32 products; on a CPU
    the same numbers, on CUDA within TF32's rounding of the field's products."""
    from garo_ns.deformation import DeformationField
    from garo_ns.render.frame import FramePath

    flags = []
    build = TimeTable.build.__func__

    def watched(cls, *args, **kwargs):
        flags.append(torch.backends.cuda.matmul.allow_tf32)
        return build(cls, *args, **kwargs)

    monkeypatch.setattr(TimeTable, "build", classmethod(watched))
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        g = torch.Generator().manual_seed(5)
        n = 2048
        field = DeformationField(pos_freqs=4, time_freqs=3, depth=3, width=64, skip=1).to(device).eval()
        parts = (torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g), 0.1 * torch.randn(n, 3, generator=g))
        canonical = Canonical(
            *(x.to(device) for x in parts),
            *(torch.zeros(n, k).to(device) for k in (1, 3)),
            torch.zeros(n, 15, 3).to(device),
        )
        spec = _spec(40, tolerance=1.0)
        frame = FramePath()
        with torch.no_grad():
            plain = frame.time_table(field, canonical, spec)
            assert frame.time_table(field, canonical, spec) is plain  # cached
            frame.table_tf32 = True
            tf32 = frame.time_table(field, canonical, spec)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = was
    assert tf32 is not plain and flags == [False, True]
    scale = float(plain.base.abs().max())
    assert scale > 0
    difference = float((tf32.base - plain.base).abs().max())
    assert difference == 0.0 if device == "cpu" else difference <= 1e-2 * scale


def test_a_time_outside_the_tables_range_renders_through_the_network():
    """A table keys the training times' range only; past it the frame takes the field's own offsets instead of
    freezing the edge pose."""
    from garo_ns.deformation import DeformationField
    from garo_ns.render.frame import FramePath, FrameSettings

    g = torch.Generator().manual_seed(2)
    n = 256
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=2, width=32, skip=1).eval()
    for p in field.parameters():  # heads that move every Gaussian
        p.data.normal_(0, 0.3, generator=g)
    canonical = Canonical(
        torch.rand(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        0.1 * torch.randn(n, 3, generator=g),
        torch.zeros(n, 1),
        torch.zeros(n, 3),
        torch.zeros(n, 15, 3),
    )
    spec = TableSpec(t_lo=0.2, t_hi=0.8, intervals=12, precision="fp32", tolerance=1.0)
    tabled, plain = FrameSettings(time_table=True), FrameSettings()
    frame = FramePath()
    with torch.no_grad():
        exact = {t: frame.splats(field, canonical, None, None, t, plain) for t in (0.05, 0.8, 0.95)}
        for t in (0.05, 0.95):  # outside: the network's frame, not the edge key's
            got = frame.splats(field, canonical, None, None, t, tabled, spec)
            assert torch.equal(got.means, exact[t].means), t
        edge = frame.splats(field, canonical, None, None, 0.8, tabled, spec)
    assert frame.table is not None  # inside the range the table renders
    assert not torch.equal(exact[0.95].means, edge.means)  # the field moves past the range: freezing would show


@pytest.mark.parametrize("tf32", [False, True])
def test_the_probe_samples_the_field_with_the_products_the_table_was_built_with(tf32):
    """A table built in TF32 is judged with its own rounding: the halfway probe that records its change samples
    the field inside TF32 products too (the flag is what matters; a CPU ignores it)."""
    from garo_ns.render.frame import FramePath

    inner = _field()
    flags = []

    class Watched:
        def __call__(self, xyz, t):
            flags.append(torch.backends.cuda.matmul.allow_tf32)
            return inner(xyz, t)

        def parameters(self):
            return iter(())

    field = Watched()
    xyz = _xyz()
    zeros = (torch.zeros(64, 3), torch.zeros(64, 1), torch.zeros(64, 3), torch.zeros(64, 15, 3))
    canonical = Canonical(xyz, torch.randn(64, 4), *zeros)
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        frame = FramePath()
        frame.table_tf32 = tf32
        table = frame.time_table(field, canonical, _spec(12))
        flags.clear()
        table.offsets_halfway(field, xyz, 0.5)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = was
    assert flags and all(f == tf32 for f in flags)


def test_a_builds_scratch_is_what_the_budget_leaves_and_the_table_is_the_same_without_it():
    """A build holds the table, the copies it makes (`build_bytes`) and an fp32 scratch of every key's residuals:
    the scratch gets what `time_table_budget_mb` leaves, and none at all makes the build take two passes of the
    field to the same table."""
    from garo_ns.render.frame import FramePath

    n = 64
    field, xyz = _field(n, amp=0.5), _xyz(n)
    spec = _spec(40, precision="int16")
    frame = FramePath()
    need = build_bytes(spec.intervals, n, spec.precision, spec.anchor_every)
    frame.table_budget_mb = (need + 1000) / 2**20
    assert 0 < frame.scratch_bytes(spec, xyz) <= 1000
    frame.table_budget_mb = need / 2**20
    assert frame.scratch_bytes(spec, xyz) == 0
    one_pass = TimeTable.build(spec, field, xyz, scratch_bytes=1 << 30)
    calls = field.calls
    two_passes = TimeTable.build(spec, field, xyz, scratch_bytes=0)
    assert field.calls - calls > calls  # the keys sampled twice
    assert torch.equal(one_pass.residual, two_passes.residual)


@pytest.mark.parametrize("whole_intervals, intervals", [(40, 8), (41, 9), (40, 1), (97, 30)])
def test_a_window_holds_the_whole_tables_keys_around_the_time_on_a_half_window_grid(whole_intervals, intervals):
    spec = _spec(whole_intervals, t_lo=0.2, t_hi=0.9)
    keys = spec.key_times().double()
    starts = set()
    for t in torch.linspace(0.2, 0.9, 57).tolist():
        w = window_spec(spec, t, intervals)
        assert w.intervals == intervals and w.t_lo <= t <= w.t_hi
        assert w.spacing == pytest.approx(spec.spacing, rel=1e-12)
        start = round((w.t_lo - spec.t_lo) / spec.spacing)
        # Its keys are the whole table's keys start .. start + intervals + 2 PAD - 1, at the same times.
        assert torch.allclose(w.key_times().double(), keys[start : start + intervals + 2 * PAD], atol=1e-6)
        step = max(intervals // 2, 1)
        assert start % step == 0 or start == whole_intervals - intervals
        if intervals >= 2 and 0 < start < whole_intervals - intervals:  # away from the ends: a quarter inside
            assert w.t_lo + 0.25 * intervals * w.spacing - 1e-9 <= t <= w.t_hi - 0.25 * intervals * w.spacing + 1e-9
        starts.add(start)
    assert len(starts) > 2  # the window moves with the time
    assert window_spec(spec, 0.5, whole_intervals) == spec and window_spec(spec, 0.5, 10**6) == spec


@pytest.mark.parametrize("precision", ["fp32", "int16"])
def test_a_frame_in_a_window_is_the_whole_tables_frame(precision):
    """A frame path under `time_table_window_mb` holds a window of the table around the frame's time (within the
    budget), builds the next one only when the time leaves it, and renders the whole table's frames: the same keys,
    so fp32 keys give the same numbers up to the order of sums; int16 keys are scaled to the window's own
    residuals, a finer step than the whole table's."""
    from garo_ns.deformation import DeformationField
    from garo_ns.render.frame import FramePath, FrameSettings

    g = torch.Generator().manual_seed(3)
    n = 64
    field = DeformationField(pos_freqs=4, time_freqs=3, depth=2, width=32, skip=1).eval()
    for p in field.parameters():  # heads that move every Gaussian
        p.data.normal_(0, 0.3, generator=g)
    parts = (torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g), 0.1 * torch.randn(n, 3, generator=g))
    canonical = Canonical(*parts, torch.zeros(n, 1), torch.zeros(n, 3), torch.zeros(n, 15, 3))
    spec = _spec(120, precision=precision, tolerance=1.0)
    whole, windowed, tabled = FramePath(), FramePath(), FrameSettings(time_table=True)
    budget = table_bytes(120, n, precision) / 2**20 / 3
    windowed.table_window_mb = budget
    fit = fitting_intervals(120, n, budget, precision)
    assert 2 <= fit < 120
    builds, last = 0, None
    with torch.no_grad():
        for t in torch.linspace(0, 1, 41).tolist():
            want = whole.splats(field, canonical, None, None, t, tabled, spec)
            got = windowed.splats(field, canonical, None, None, t, tabled, spec)
            table = windowed.table
            assert table is not None and table.spec.intervals == fit and table.nbytes() <= budget * 2**20
            assert table.spec.t_lo <= t <= table.spec.t_hi
            builds += table is not last
            last = table
            scale = float(want.means.abs().max())
            assert float((got.means - want.means).abs().max()) <= (1e-6 if precision == "fp32" else 1e-4) * scale
            assert float((got.quats - want.quats).abs().max()) <= (1e-6 if precision == "fp32" else 1e-4) * scale
    assert whole.table.spec == spec and windowed.built_info(spec)["window"]["of_intervals"] == 120
    # Built again only as the time left each window: far fewer builds than frames.
    assert 3 <= builds <= 2 + 120 // (fit // 2)
    # A budget that holds fewer than two intervals: no table, and why.
    windowed.table_window_mb = 1e-6
    assert windowed.time_table(field, canonical, spec, 0.5) is None
    assert "holds fewer than two" in windowed.table_failures[spec]
