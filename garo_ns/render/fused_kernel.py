"""The fused deformation kernel (Triton): see garo_ns.render.fused_field, which loads this module on first
use, once for compiled kernels and once more, under another name, for Triton's interpreter (the tests on a
CPU), since `triton.jit` reads TRITON_INTERPRET when a function is defined. Import nothing from here directly.
"""

import triton
import triton.language as tl


@triton.jit
def produce(
    h,
    j,
    first_ptr,
    skip_ptr,
    tvec_ptr,
    w_ptr,
    b_ptr,
    rows,
    rmask,
    LAYER: tl.constexpr,
    SKIP_LAYER: tl.constexpr,
    WIDTH: tl.constexpr,
    BLOCK_N: tl.constexpr,
):
    """Columns [j * BLOCK_N, (j + 1) * BLOCK_N) of layer LAYER's ReLU output, half [BLOCK_M, BLOCK_N]."""
    cols = j * BLOCK_N + tl.arange(0, BLOCK_N)
    if LAYER == 0:  # no product: the cached position part plus the frame's time row
        pre = tl.load(first_ptr + rows[:, None] * WIDTH + cols[None, :], mask=rmask[:, None], other=0.0)
        pre = pre.to(tl.float32) + tl.load(tvec_ptr + cols)[None, :]
    else:
        w = tl.load(w_ptr + (LAYER - 1) * WIDTH * WIDTH + cols[:, None] * WIDTH + tl.arange(0, WIDTH)[None, :])
        pre = tl.dot(h, tl.trans(w))
        if LAYER == SKIP_LAYER:  # bias replaced by the re-injected input's part: cached + time row
            base = tl.load(skip_ptr + rows[:, None] * WIDTH + cols[None, :], mask=rmask[:, None], other=0.0)
            pre += base.to(tl.float32) + tl.load(tvec_ptr + WIDTH + cols)[None, :]
        else:
            pre += tl.load(b_ptr + LAYER * WIDTH + cols)[None, :]
    return tl.maximum(pre, 0.0).to(tl.float16)


@triton.jit
def consume(
    p,
    acc,
    j,
    w_ptr,
    hw_ptr,
    LAYER: tl.constexpr,
    DEPTH: tl.constexpr,
    WIDTH: tl.constexpr,
    BLOCK_N: tl.constexpr,
    HEADS_P: tl.constexpr,
):
    """`acc` plus chunk j's share of layer LAYER's (or the heads', LAYER == DEPTH) pre-activation."""
    ks = j * BLOCK_N + tl.arange(0, BLOCK_N)
    if LAYER < DEPTH:
        w = tl.load(w_ptr + (LAYER - 1) * WIDTH * WIDTH + ks[:, None] * WIDTH + tl.arange(0, WIDTH)[None, :])
    else:
        w = tl.load(hw_ptr + ks[:, None] * HEADS_P + tl.arange(0, HEADS_P)[None, :])
    return tl.dot(p, w, acc)


# `n` is not specialised (on n % 16 == 0, n == 1): one compiled kernel for every number of Gaussians.
@triton.jit(do_not_specialize=["n"])
def fused_field(
    first_ptr,
    skip_ptr,
    tvec_ptr,
    w_ptr,
    b_ptr,
    hw_ptr,
    hb_ptr,
    out_ptr,
    n,
    WIDTH: tl.constexpr,
    DEPTH: tl.constexpr,
    SKIP_LAYER: tl.constexpr,
    HEADS: tl.constexpr,
    HEADS_P: tl.constexpr,
    BLOCK_M: tl.constexpr,
    BLOCK_N: tl.constexpr,
    STAGES: tl.constexpr,
):
    """Offsets [n, HEADS] (fp32) of a block of BLOCK_M Gaussians through every layer and the heads."""
    rows = tl.program_id(0).to(tl.int64) * BLOCK_M + tl.arange(0, BLOCK_M)
    rmask = rows < n  # the last block is ragged: its missing rows read zeros and store nothing
    cols = tl.arange(0, WIDTH)
    if DEPTH % 2 == 0:  # layer 0 whole: the first pair's input
        pre = tl.load(first_ptr + rows[:, None] * WIDTH + cols[None, :], mask=rmask[:, None], other=0.0)
        h = tl.maximum(pre.to(tl.float32) + tl.load(tvec_ptr + cols)[None, :], 0.0).to(tl.float16)
    else:  # layer 0 is produced chunk by chunk by the first pair; h is not read
        h = tl.full([BLOCK_M, WIDTH], 0.0, tl.float16)
    START: tl.constexpr = 1 - DEPTH % 2  # the first pair's first layer
    for pair in tl.static_range((DEPTH + 1) // 2):  # unrolled: layer indices are compile-time constants
        if START + 2 * pair + 1 < DEPTH:
            acc = tl.full([BLOCK_M, WIDTH], 0.0, tl.float32)
        else:
            acc = tl.full([BLOCK_M, HEADS_P], 0.0, tl.float32)
        for j in tl.range(0, WIDTH // BLOCK_N, num_stages=STAGES):
            p = produce(
                h,
                j,
                first_ptr,
                skip_ptr,
                tvec_ptr,
                w_ptr,
                b_ptr,
                rows,
                rmask,
                START + 2 * pair,
                SKIP_LAYER,
                WIDTH,
                BLOCK_N,
            )
            acc = consume(p, acc, j, w_ptr, hw_ptr, START + 2 * pair + 1, DEPTH, WIDTH, BLOCK_N, HEADS_P)
        if START + 2 * pair + 1 < DEPTH:
            if START + 2 * pair + 1 == SKIP_LAYER:
                base = tl.load(skip_ptr + rows[:, None] * WIDTH + cols[None, :], mask=rmask[:, None], other=0.0)
                acc += base.to(tl.float32) + tl.load(tvec_ptr + WIDTH + cols)[None, :]
            else:
                acc += tl.load(b_ptr + (START + 2 * pair + 1) * WIDTH + cols)[None, :]
            h = tl.maximum(acc, 0.0).to(tl.float16)
    hc = tl.arange(0, HEADS_P)
    out = acc + tl.load(hb_ptr + hc)[None, :]
    tl.store(out_ptr + rows[:, None] * HEADS + hc[None, :], out, mask=rmask[:, None] & (hc[None, :] < HEADS))
