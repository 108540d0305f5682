"""The probe of the official code's deformation terms (benchmarks/official_terms.py) runs and changes what it says."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest
import torch

from garo_ns.render.frame import Canonical, activate, compose
from garo_ns.tools.scene import SceneSpec, generate_scene

_spec = importlib.util.spec_from_file_location(
    "official_terms", Path(__file__).parents[1] / "benchmarks" / "official_terms.py"
)
official_terms = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(official_terms)  # type: ignore[union-attr]


def _canonical(n=5):
    torch.manual_seed(0)
    return Canonical(
        torch.randn(n, 3),
        torch.randn(n, 4),
        torch.randn(n, 3) - 3,
        torch.zeros(n, 1),
        torch.rand(n, 3),
        torch.zeros(n, 15, 3),
    )


def test_the_scale_term_adds_the_offset_after_activation_and_only_it():
    canonical = _canonical()
    d_scale = torch.full((5, 3), 0.01)
    field = lambda xyz, t: (torch.zeros_like(xyz), torch.zeros(len(xyz), 4), d_scale)  # noqa: E731
    ours = activate(canonical, compose(field, canonical, 0.5))
    none = official_terms.official_functions("none")
    same = none["activate"](canonical, none["compose"](field, canonical, 0.5))
    assert torch.allclose(same.scales, ours.scales) and torch.equal(same.quats, ours.quats)
    theirs = official_terms.official_functions("scale")
    official = theirs["activate"](canonical, theirs["compose"](field, canonical, 0.5))
    assert torch.allclose(official.scales, torch.exp(canonical.log_scales) + 0.01)
    assert torch.allclose(ours.scales, torch.exp(canonical.log_scales) * math.exp(0.01))
    assert "render_splats" not in theirs and "render_splats" in official_terms.official_functions("rotation")


def test_rotation_matrices_of_an_unnormalised_quaternion_are_scaled_rotations_plus_identity():
    q = torch.nn.functional.normalize(torch.randn(4, 4), dim=-1)
    unit = official_terms.rotation_matrices(q)
    assert torch.allclose(unit @ unit.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-5)
    s = 1.2  # |q| = s: the formula gives s^2 R + (1 - s^2) I
    assert torch.allclose(official_terms.rotation_matrices(s * q), s * s * unit + (1 - s * s) * torch.eye(3), atol=1e-5)


@pytest.mark.slow
def test_a_short_run_records_the_gaussian_count(tmp_path, capsys):
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=32, n_train=8, n_val=3, n_test=3))
    out = tmp_path / "scale.json"
    result = official_terms.main(
        [
            "--scene",
            str(scene),
            "--term",
            "scale",
            "--steps",
            "40",
            "--every",
            "10",
            "--device",
            "cpu",
            "--quick",
            "--work-dir",
            str(tmp_path / "runs"),
            "--score",
            "test",
            "--output",
            str(out),
        ]
    )
    assert [s for s, _ in result["gaussians_every"]] == [0, 10, 20, 30, 39]
    assert result["score"]["split"] == "test" and result["score"]["n_images"] == 3
    assert math.isfinite(result["score"]["psnr"]) and result["score"]["psnr"] > 5
    assert result["gaussians_end"] == result["gaussians_every"][-1][1] > 0 and out.exists()
    assert result["replaced_calls"]["compose"] > 0  # the official term was in the training frames
    # The score rendered every view with the term too: outside training the plugin's frame path would not.
    assert result["replaced_calls_scoring"]["compose"] >= 3
    # The run's checkpoint scored again (another process, another day): the same model, the same score.
    again = official_terms.main(
        [
            "--rescore",
            str(tmp_path / "runs" / "scale" / "deform-splatfacto" / "nerfstudio_models"),
            "--scene",
            str(scene),
            "--term",
            "scale",
            "--device",
            "cpu",
            "--output",
            str(out),
        ]
    )
    assert again["score"]["psnr"] == pytest.approx(result["score"]["psnr"], abs=1e-4)
    assert again["replaced_calls_scoring"]["compose"] >= 3 and again["gaussians_end"] == result["gaussians_end"]
    assert json.loads(out.read_text())["scored"]["how"].startswith("the run's checkpoint")
    with pytest.raises(ValueError, match="is the scale term on scene, not none on"):
        official_terms.rescore(
            tmp_path / "runs" / "scale" / "deform-splatfacto" / "nerfstudio_models", scene, "none", "test", "cpu", out
        )
    # The printed lines carry the same curve, so a run cut before it writes its file still leaves it.
    assert official_terms.curves_from_log(capsys.readouterr().out) == {"scale": result["gaussians_every"]}
    import garo_ns.garo_model as garo_model

    assert garo_model.compose is compose and garo_model.activate is activate  # restored after the run
    with pytest.raises(ValueError, match="CUDA only"):
        official_terms.train(scene, "rotation", 10, 5, tmp_path / "r", "cpu")
    with pytest.raises(ValueError, match="would not render the rotation term"):
        official_terms.train(scene, "scale+rotation", 10, 5, tmp_path / "r", "cuda", score="test")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the rotation term renders through gsplat's CUDA kernels")
def test_the_rotation_term_renders_a_unit_quaternion_as_the_plugin_does():
    """Through covariances, normalised quaternions give the plugin's pixels and means2d gradients; only an
    unnormalised one renders differently (what the term is about)."""
    from garo_ns.render.frame import Splats, render_splats
    from garo_ns.render.view import RenderView

    g = torch.Generator().manual_seed(0)
    n = 2000
    means = ((torch.rand(n, 3, generator=g) - 0.5) * 2).cuda()
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1).cuda()
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 - 4).cuda()
    splats = Splats(means, quats, scales, torch.rand(n, generator=g).cuda(), torch.rand(n, 1, 3, generator=g).cuda())
    viewmat = torch.eye(4)[None]
    viewmat[0, 2, 3] = 4.0
    K = torch.tensor([[[200.0, 0.0, 64.0], [0.0, 200.0, 48.0], [0.0, 0.0, 1.0]]])
    view = RenderView(viewmat.cuda(), K.cuda(), 128, 96, 0.5)
    official = official_terms.official_functions("rotation")["render_splats"]
    ours, _, _ = render_splats(splats, view, 0, None, "RGB", "cuda")
    theirs, _, info = official(splats, view, 0, None, "RGB", "cuda")
    assert float(ours.mean()) > 0.01 and "means2d" in info and "radii" in info
    torch.testing.assert_close(theirs, ours, rtol=0, atol=1e-4)
    stretched, _, _ = official(splats._replace(quats=quats * 1.3), view, 0, None, "RGB", "cuda")
    assert (stretched - ours).abs().max() > 1e-3


def test_curves_of_runs_cut_short_come_from_their_log(tmp_path):
    log = tmp_path / "terms.log"
    log.write_text(
        "official_terms none step 0 gaussians 100\n"
        "Step (% Done)  Train Iter (time)\n"  # the trainer's own output in between
        "official_terms scale step 0 gaussians 100\n"
        "official_terms none step 500 gaussians 180\n"
        "official_terms scale step 500 gaussians 150\n"
        "official_terms none step 1000 gaussians 260\n"
        "official_terms bogus step 500 gaussians 1\n"
    )
    out = tmp_path / "partial.json"
    result = official_terms.main(
        ["--from-log", str(log), "--scene", "/tmp/mutant", "--steps", "15000", "--output", str(out)]
    )
    assert result["terms"]["none"]["gaussians_every"] == [(0, 100), (500, 180), (1000, 260)]
    assert result["terms"]["scale"]["last_step"] == 500 and "bogus" not in result["terms"]
    # Compared where every term got to, not at each one's last record.
    assert result["common_step"] == 500 and result["gaussians_at_common_step"] == {"none": 180, "scale": 150}
    assert result["cut_short"] and result["scene"] == "mutant" and out.exists()
    empty = tmp_path / "empty.log"
    empty.write_text("nothing here\n")
    with pytest.raises(ValueError, match="no `official_terms"):
        official_terms.main(["--from-log", str(empty), "--scene", "x", "--output", str(tmp_path / "e.json")])
    with pytest.raises(SystemExit):  # training names its term: no silent default
        official_terms.main(["--scene", "x", "--output", str(tmp_path / "t.json")])
