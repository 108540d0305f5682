"""What the model returns for one rendered camera (garo_ns.render.outputs)."""

from __future__ import annotations

import torch

from garo_ns.render.outputs import camera_outputs


def _frame():
    """One row of two pixels: a bright one drawn at depth 2 (alpha 1), an empty one (alpha 0, depth 0)."""
    render = torch.tensor([[[[1.5, 0.2, 0.1, 2.0], [0.0, 0.0, 0.0, 0.0]]]])
    alpha = torch.tensor([[[[1.0], [0.0]]]])
    return render, alpha, torch.tensor([0.25, 0.5, 0.75])


def test_outside_training_the_colour_is_clamped_and_empty_pixels_take_the_farthest_depth():
    render, alpha, background = _frame()
    out = camera_outputs(render, alpha, background, with_depth=True, training=False)
    assert torch.equal(out["rgb"], torch.tensor([[[1.0, 0.2, 0.1], [0.25, 0.5, 0.75]]]))
    assert torch.equal(out["depth"], torch.tensor([[[2.0], [2.0]]]))
    assert out["background"].shape == (1, 2, 3) and torch.equal(out["background"][0, 1], background)
    assert torch.equal(out["accumulation"], alpha[0])


def test_in_training_the_colour_is_unclamped_and_the_background_stays_one_colour():
    render, alpha, background = _frame()
    out = camera_outputs(render[..., :3], alpha, background, with_depth=False, training=True)
    assert float(out["rgb"][0, 0, 0]) == 1.5  # the loss sees an over-bright pixel as it is
    assert out["depth"] is None and torch.equal(out["background"], background)
