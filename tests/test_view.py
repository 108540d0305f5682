"""A camera as the rasterizer takes it: the same numbers nerfstudio's own rescaling gives, in one host copy."""

from __future__ import annotations

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras

from garo_ns.render.view import camera_numbers, camera_view


def _camera(times=True):
    return Cameras(
        camera_to_worlds=torch.eye(4)[None, :3, :],
        fx=torch.tensor([[1111.1]]),
        fy=torch.tensor([[1109.7]]),
        cx=torch.tensor([[400.3]]),
        cy=torch.tensor([[399.9]]),
        width=torch.tensor([[801]]),
        height=torch.tensor([[799]]),
        times=torch.tensor([[0.37]]) if times else None,
    )


@pytest.mark.parametrize("downscale", [1.0, 2.0, 3.0])
def test_camera_view_matches_nerfstudios_rescaled_intrinsics(downscale):
    camera = _camera()
    view = camera_view(camera, camera.camera_to_worlds, downscale, "cpu", 0.37)
    reference = _camera()
    reference.rescale_output_resolution(1 / downscale)
    assert torch.equal(view.K, reference.get_intrinsics_matrices())
    assert (view.width, view.height) == (int(reference.width), int(reference.height))
    assert float(camera.fx) == pytest.approx(1111.1)  # the caller's camera is left as it was


def test_camera_numbers_carry_the_time_or_none():
    assert camera_numbers(_camera())[3] == pytest.approx(0.37)
    assert camera_numbers(_camera(times=False))[3] is None
