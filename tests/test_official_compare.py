"""The comparison with the official D-3DGS code reports only pairs run under the same conditions."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "official_compare", Path(__file__).parents[1] / "benchmarks" / "official_compare.py"
)
official_compare = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(official_compare)  # type: ignore[union-attr]


def ours(
    scene="/tmp/jumpingjacks", iterations=40_000, split="test", background="black", psnr=37.5, lpips=0.012, gpu="H200"
):
    arm = {"psnr": psnr, "ssim": 0.99, "lpips": lpips, "num_gaussians": 80_000, "fps": 200.0, "iterations": iterations}
    result = {"scene": scene, "split": split, "background": background, "gpu": gpu}
    return {**result, "variants": {"deform-splatfacto": arm}}


def official(iterations=40_000, split="test", background="black", psnr=37.6, lpips=0.011):
    arm = {"psnr": psnr, "ssim": 0.99, "lpips": lpips, "num_gaussians": 88_000, "fps": 150.0}
    arm.update(iterations=iterations, split=split, background=background)
    return {"gpu": "H200", "rows": [{"scene": "jumpingjacks", "official": arm}]}


def test_a_matching_pair_is_reported_with_its_gaps_and_verdict():
    out = official_compare.compare([ours()], official())
    assert out["refused"] == [] and len(out["rows"]) == 1
    row = out["rows"][0]
    assert row["scene"] == "jumpingjacks"
    assert row["psnr_gap_db"] == pytest.approx(-0.1) and row["lpips_gap"] == pytest.approx(0.001)
    assert row["target_met"] is True
    assert official_compare.compare([ours(psnr=37.3)], official())["rows"][0]["target_met"] is False  # -0.3 dB
    assert official_compare.compare([ours(lpips=0.015)], official())["rows"][0]["target_met"] is False
    assert "| jumpingjacks (test) | 40,000 | 37.50 / 37.60 |" in official_compare.markdown(out)


@pytest.mark.parametrize(
    "ours_kwargs, official_kwargs, word",
    [
        ({"iterations": 39_000}, {}, "iterations"),
        ({}, {"split": "val"}, "split"),
        ({"background": "white"}, {}, "background"),
        ({}, {"iterations": None}, "iterations"),
        ({"gpu": "H100"}, {}, "gpu"),
    ],
)
def test_arms_that_differ_in_steps_split_or_background_are_refused(ours_kwargs, official_kwargs, word):
    out = official_compare.compare([ours(**ours_kwargs)], official(**official_kwargs))
    assert out["rows"] == []
    assert len(out["refused"]) == 1 and word in out["refused"][0] and "jumpingjacks" in out["refused"][0]


def test_a_scene_without_an_official_run_is_refused_not_dropped():
    out = official_compare.compare([ours(scene="/tmp/mutant")], official())
    assert out["rows"] == [] and out["refused"] == ["mutant: no official run", "jumpingjacks: no run of ours"]


def test_runs_of_a_scene_are_compared_as_means_on_the_same_gpu_model():
    runs = [dict(ours(psnr=p, lpips=lp), source=f"run{i}") for i, (p, lp) in enumerate([(37.4, 0.012), (37.0, 0.014)])]
    second_official = official(psnr=37.0, lpips=0.013)
    out = official_compare.compare(runs, [official(), second_official])
    row = out["rows"][0]
    assert row["ours"]["psnr"] == pytest.approx(37.2) and row["official"]["psnr"] == pytest.approx(37.3)
    assert row["psnr_gap_db"] == pytest.approx(-0.1) and row["lpips_gap"] == pytest.approx(0.001)
    assert row["target_met"] is True  # one run alone (37.0 against 37.6) would have missed it
    assert [r["psnr"] for r in row["ours"]["runs"]] == [37.4, 37.0] and len(row["official"]["runs"]) == 2
    # An official run on another GPU model is not averaged in: the H100 run of ours has no partner.
    out = official_compare.compare([*runs, ours(gpu="H100", psnr=30.0)], official())
    assert len(out["rows"]) == 1 and out["rows"][0]["ours"]["psnr"] == pytest.approx(37.2)
    assert out["refused"] == ["jumpingjacks: arms differ in gpu ('H100' ours, 'H200' official)"]
    # An official 20k run beside the 40k one: the 40k arms pair, the 20k run is not mixed in.
    out = official_compare.compare(runs, [official(iterations=20_000, psnr=30.0), official()])
    assert out["rows"][0]["official"]["psnr"] == pytest.approx(37.6) and out["refused"] == []
    assert "| jumpingjacks (test) | 40,000 | 37.20 / 37.60 |" in official_compare.markdown(out)


def profile(method="deform-splatfacto", split=None, psnr=37.45, gpu="H200", **score):
    """A train_profile result (`--score`); `split=None`: a file from before train_profile recorded it."""
    score = {"psnr": psnr, "ssim": 0.99, "lpips": 0.011, "num_gaussians": 90_000, **score}
    if split is not None:
        score.update(split=split, background="black")
    env = {"gpu": gpu, "git_commit": "abc"}
    return {"scene": "jumpingjacks", "method": method, "steps": 40_000, "environment": env, "score": score}


def test_a_train_profile_run_pairs_as_ours_and_says_what_it_assumed():
    out = official_compare.compare([profile(split="test"), ours()], official())
    (row,) = out["rows"]
    assert [r["psnr"] for r in row["ours"]["runs"]] == [37.45, 37.5]  # the profile and the benchmark run, averaged
    assert row["ours"]["psnr"] == pytest.approx(37.475) and "assumed" not in row["ours"]
    old = official_compare.compare([profile()], official())["rows"][0]["ours"]
    assert old["split"] == "test" and old["background"] == "black" and sorted(old["assumed"]) == ["background", "split"]
    assert "background and split are train_profile's defaults" in official_compare.markdown(
        official_compare.compare([profile()], official())
    )
    assert official_compare.compare([profile(split="val")], official())["rows"] == []  # a recorded split is held to
    refused = official_compare.compare([profile(method="garo-deform"), profile(psnr=None)], official())["refused"]
    assert any("garo-deform" in r for r in refused) and any("not scored" in r for r in refused)
