"""One scene's variants against the baseline of each one's own run (garo_ns.bench.ablation)."""

from __future__ import annotations

import json

import pytest

from garo_ns.bench.ablation import AblationArgs, build, main, ordering, ordering_sentence, paired_text, variant_rows


def _row(fps, psnr, n, **settings):
    return {
        "psnr": psnr,
        "ssim": 0.9,
        "lpips": 0.01,
        "fps": fps,
        "num_gaussians": n,
        "model_size_mb": 1.0,
        "iterations": 40_000,
        "shortened": False,
        "garo_mode": "full",
        "rho_max": 0.02,
        **settings,
    }


def _file(base_fps, variants, scene="jj", gpu="H100"):
    return {
        "scene": scene,
        "split": "test",
        "gpu": gpu,
        "git_commit": "abc",
        "variants": {"deform-splatfacto": _row(base_fps, 37.0, 100_000, garo_mode="off"), **variants},
    }


def test_each_ratio_is_taken_within_its_own_file_and_a_repeat_is_averaged():
    a = _file(100.0, {"garo-oaa": _row(300.0, 36.9, 30_000, garo_mode="oaa"), "garo-deform": _row(200.0, 36.8, 40_000)})
    b = _file(400.0, {"garo-deform": _row(1200.0, 37.0, 20_000)})  # a faster run: only ratios compare
    rows = variant_rows([("a.json", a), ("b.json", b)], ["garo-oaa", "garo-deform"])
    assert rows["garo-oaa"]["garo-oaa"]["fps_ratio"] == pytest.approx(3.0)
    assert rows["garo-oaa"]["source"] == "a.json"
    joint = rows["garo-deform"]["garo-deform"]
    assert joint["fps_ratio"] == pytest.approx((2.0 + 3.0) / 2)  # not 1400 / 500
    assert joint["psnr_drop_db"] == pytest.approx((0.2 + 0.0) / 2)
    assert joint["fps_ratio_range"] == pytest.approx([2.0, 3.0])
    assert rows["garo-deform"]["settings"] == {"garo_mode": "full", "rho_max": 0.02}


def test_refuses_what_is_not_one_scenes_runs_of_one_variant():
    a = _file(100.0, {"garo-deform": _row(200.0, 36.8, 40_000)})
    with pytest.raises(ValueError, match="differ in scene"):
        variant_rows([("a", a), ("b", _file(100.0, {}, scene="mutant"))], ["garo-deform"])
    with pytest.raises(ValueError, match="differ in gpu"):
        variant_rows([("a", a), ("b", _file(100.0, {}, gpu="H200"))], ["garo-deform"])
    no_base = {**a, "variants": {"garo-deform": a["variants"]["garo-deform"]}}
    with pytest.raises(ValueError, match="no deform-splatfacto row"):
        variant_rows([("a", no_base)], ["garo-deform"])
    with pytest.raises(ValueError, match=r"no file holds \['garo-gca'\]"):
        variant_rows([("a", a)], ["garo-deform", "garo-gca"])
    other = _file(100.0, {"garo-deform": _row(200.0, 36.8, 40_000, rho_max=0.05)})
    with pytest.raises(ValueError, match="rho_max"):
        variant_rows([("a", a), ("b", other)], ["garo-deform"])
    with pytest.raises(ValueError, match="Table 3 needs"):
        build(AblationArgs(results=[], variants=["garo-deform"]), [("a", a)])
    short = _file(100.0, {"garo-deform": _row(200.0, 36.8, 40_000)})
    short["variants"]["deform-splatfacto"]["iterations"] = 18_000
    with pytest.raises(ValueError, match="different numbers of steps"):
        build(AblationArgs(results=[], figure="rho"), [("a", a), ("short", short)])


def _table3(joint, oaa, gca):
    """Rows of the three criteria from (fps, psnr, gaussians) each, baseline 100 FPS, 37 dB."""
    f = _file(
        100.0,
        {"garo-deform": _row(*joint), "garo-oaa": _row(*oaa, garo_mode="oaa"), "garo-gca": _row(*gca, garo_mode="gca")},
    )
    return variant_rows([("f", f)], ["garo-oaa", "garo-gca", "garo-deform"])


def test_the_ordering_sentence_says_where_the_joint_criterion_stands():
    best = ordering(_table3((300.0, 36.9, 20_000), (250.0, 36.5, 30_000), (200.0, 36.7, 40_000)))
    assert best["ranks"]["PSNR"] == ["garo-deform", "garo-gca", "garo-oaa"]
    assert best["ranks"]["FPS"] == ["garo-deform", "garo-oaa", "garo-gca"]
    assert "ordering holds here" in ordering_sentence(best)
    part = ordering(_table3((300.0, 36.5, 20_000), (250.0, 36.9, 30_000), (200.0, 36.7, 40_000)))
    assert part["joint_first"] == {"PSNR": False, "FPS": True, "Gaussians": True}
    assert "leads on FPS and Gaussians only" in ordering_sentence(part)
    worst = ordering(_table3((150.0, 36.5, 50_000), (250.0, 36.9, 30_000), (200.0, 36.7, 40_000)))
    assert "leads on no measure, so the ablation's ordering does not hold" in ordering_sentence(worst)


def test_the_rho_figure_sorts_by_rho_reads_a_renamed_joint_row_and_says_where_the_claim_holds(tmp_path):
    old = _file(100.0, {"garo-window": _row(150.0, 36.9, 50_000)})  # garo-deform under its older name
    sweep = _file(
        200.0,
        {
            "garo-rho0.1": _row(500.0, 36.6, 10_000, rho_max=0.1),
            "garo-rho0.005": _row(220.0, 37.0, 90_000, rho_max=0.005),
            "garo-rho0.1+static+graph": _row(900.0, 36.6, 10_000, rho_max=0.1),  # a render row, not an arm
        },
    )
    paths = []
    for name, data in (("old.json", old), ("sweep.json", sweep)):
        paths.append(tmp_path / name)
        paths[-1].write_text(json.dumps(data))
    out = tmp_path / "fig5.json"
    result = main(AblationArgs(results=paths, output=out, figure="rho", aliases=["garo-window=garo-deform"]))
    assert [s["rho_max"] for s in result["sweep"]] == [0.005, 0.02, 0.1]
    assert [s["variant"] for s in result["sweep"]] == ["garo-rho0.005", "garo-deform", "garo-rho0.1"]
    assert result["sweep"][2]["fps_ratio"] == pytest.approx(2.5)
    assert result["claim_met_at_rho"] == [0.1]  # 2.5x at 0.4 dB; 0.02 is 1.5x
    assert json.loads(out.read_text())["claim_met_at_rho"] == [0.1]
    assert "on this scene: met at rho_max 0.1;" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 0
    with pytest.raises(SystemExit, match="cannot read benchmark result"):
        main(AblationArgs(results=[tmp_path / "missing.json"], output=out))


def test_a_strayed_baseline_is_read_against_the_mean_of_all_baselines_and_the_retimed_speed_up_is_shown(tmp_path):
    def paired(row, fps):
        return {**row, "fps_paired": {"fps": fps}}

    # Run a: its baseline scored high (37.6), so the variant's own-run drop (0.6 dB) overstates it; run b's
    # baseline scored 37.0, so the mean of both baselines is 37.3. The benchmark's alternating re-timing
    # gives 1.8x where the first timing gave 2.1x.
    a = _file(100.0, {"garo-rho0.05": paired(_row(210.0, 37.0, 20_000, rho_max=0.05), 180.0)})
    a["variants"]["deform-splatfacto"] = paired({**a["variants"]["deform-splatfacto"], "psnr": 37.6}, 100.0)
    b = _file(100.0, {"garo-deform": _row(150.0, 36.9, 30_000)})  # no re-timing in this run
    paths = []
    for name, data in (("a.json", a), ("b.json", b)):
        paths.append(tmp_path / name)
        paths[-1].write_text(json.dumps(data))
    out = tmp_path / "fig5.json"
    result = main(AblationArgs(results=paths, output=out, figure="rho"))
    pooled = result["baseline_pooled"]
    assert pooled["runs"] == 2 and pooled["psnr_mean"] == pytest.approx(37.3)
    assert pooled["psnr_range"] == pytest.approx([37.0, 37.6])
    rho05 = result["rows"]["garo-rho0.05"]["garo-rho0.05"]
    assert rho05["psnr_drop_db"] == pytest.approx(0.6)
    assert rho05["psnr_drop_vs_pooled_db"] == pytest.approx(0.3)
    assert rho05["fps_ratio"] == pytest.approx(2.1) and rho05["fps_ratio_paired"] == pytest.approx(1.8)
    assert result["rows"]["garo-deform"]["garo-deform"]["fps_ratio_paired"] is None
    # Within its run 0.05 misses the claim on PSNR; against the mean it meets PSNR but not the re-timed FPS.
    assert result["claim_met_at_rho"] == [] and result["claim_met_at_rho_pooled_paired"] == []
    md = out.with_suffix(".md").read_text()
    assert "| garo-rho0.05 | 0.05 | 1 | 37.00 | 37.60 | +0.60 | +0.30 | 0.0100 | 2.10x | 1.80x | 20,000 | 20% |" in md
    assert "The baseline over these 2 runs: 37.00 to 37.60 dB (mean 37.30)" in md
    # With a re-timing that holds up, the mean-baseline reading meets the claim where the own-run one does not.
    a["variants"]["garo-rho0.05"]["fps_paired"] = {"fps": 205.0}
    paths[0].write_text(json.dumps(a))
    result = main(AblationArgs(results=paths, output=out, figure="rho"))
    assert result["claim_met_at_rho"] == [] and result["claim_met_at_rho_pooled_paired"] == [0.05]


def test_the_readme_block_is_written_from_the_table3_file(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.pop(0)
    assert "has not been run yet" in readme_results.ablation_block(tmp_path, tmp_path)
    a = _file(100.0, {"garo-oaa": _row(260.0, 36.8, 30_000), "garo-gca": _row(200.0, 36.7, 40_000)})
    b = _file(200.0, {"garo-deform": _row(600.0, 36.95, 20_000)})
    c = _file(100.0, {"garo-deform": _row(200.0, 36.85, 25_000)})
    paths = []
    for name, data in (("a.json", a), ("b.json", b), ("c.json", c)):
        paths.append(tmp_path / name)
        paths[-1].write_text(json.dumps(data))
    main(AblationArgs(results=paths, output=tmp_path / "paper_table3_GPU.json"))
    block = readme_results.ablation_block(tmp_path, tmp_path)
    assert "| `garo-deform` | both (GARO) | 2 | -0.10 dB | 0.0100 / 0.0100 | 2.50x | 22% |" in block
    assert "jj (test), 40,000 steps, H100;" in block
    assert "| `garo-oaa` | activity alone | 1 | -0.20 dB | 0.0100 / 0.0100 | 2.60x | 30% |" in block
    assert "the joint criterion leads on PSNR and Gaussians only" in block
    assert "`garo-deform`'s runs range from 2.00x to 3.00x" in block


def test_the_readme_block_adds_the_rho_table_from_the_fig5_file(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.pop(0)
    a = _file(100.0, {"garo-rho0.05": _row(250.0, 36.7, 20_000, rho_max=0.05)})
    b = _file(100.0, {"garo-deform": _row(150.0, 36.9, 30_000)})
    b["variants"]["deform-splatfacto"]["psnr"] = 36.8  # the mean of the two baselines: 36.9
    paths = []
    for name, data in (("a.json", a), ("b.json", b)):
        paths.append(tmp_path / name)
        paths[-1].write_text(json.dumps(data))
    main(AblationArgs(results=paths, output=tmp_path / "paper_fig5_GPU.json", figure="rho"))
    block = readme_results.ablation_block(tmp_path, tmp_path)
    assert "mean of all 2 baselines (36.80 to 37.00 dB" in block
    assert "| 0.02 | 1 | +0.10 dB | -0.00 dB | 1.50x | - | 30% |" in block
    assert "| 0.05 | 1 | -0.30 dB | -0.20 dB | 2.50x | - | 20% |" in block
    assert "holds at rho_max 0.05 within each run, and at rho_max 0.05 against all baselines" in block


def test_a_re_timed_speed_up_from_some_of_a_variants_runs_says_how_many():
    with_retime = _file(100.0, {"garo-deform": {**_row(200.0, 36.8, 30_000), "fps_paired": {"fps": 180.0}}})
    with_retime["variants"]["deform-splatfacto"]["fps_paired"] = {"fps": 100.0}
    without = _file(100.0, {"garo-deform": _row(150.0, 36.9, 30_000)})
    result = build(AblationArgs(results=[], figure="rho"), [("a", with_retime), ("b", without)])
    v = result["rows"]["garo-deform"]["garo-deform"]
    assert v["fps_ratio_paired"] == pytest.approx(1.8) and v["fps_ratio_paired_runs"] == 1
    assert paired_text(v, 2) == "1.80x (1 of 2 runs)"
    assert paired_text(v, 1) == "1.80x"
    assert paired_text({"fps_ratio_paired": None}, 2) == "-"


def test_the_readme_names_the_newest_gpu_test_run(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.pop(0)
    assert readme_results.gpu_tests_sentence(tmp_path, tmp_path) == ""
    (tmp_path / "gputests_H100.log").write_text("commit aaaaaaaaaa 2026-11-20 NVIDIA H100\n\n57 passed in 3s\n")
    (tmp_path / "gputests_H200.log").write_text(
        "commit bbbbbbbbbb 2026-11-26 NVIDIA H200\n....\n\n69 passed, 1 skipped, 4 warnings in 20.21s\n"
    )
    (tmp_path / "gputests_X.log").write_text("a log of a run that broke off\n")
    got = readme_results.gpu_tests_sentence(tmp_path, tmp_path)
    assert "2026-11-26: 69 passed, 1 skipped on an H200, commit bbbbbbb" in got and "warning" not in got
    assert "H100" not in got  # an older day's run
    (tmp_path / "gputests_H100.log").write_text("commit cccccccccc 2026-11-26 NVIDIA H100\n\n57 passed in 3s\n")
    got = readme_results.gpu_tests_sentence(tmp_path, tmp_path)
    assert "57 passed on an H100, commit ccccccc" in got and "69 passed, 1 skipped on an H200" in got
    # A run with a failure, and reruns of the failed test's file after a fix: only a passing one of that file, that
    # run and that GPU model is named.
    (tmp_path / "gputests_H100.log").write_text(
        "commit dddddddddd 2026-11-26 NVIDIA H100\nFAILED tests/test_a.py::test_x - assert 0\n"
        "1 failed, 56 passed in 3s\n"
    )
    reruns = {
        "cuda_subset_1.log": "commit eeeeeeeeee 2026-11-26 NVIDIA H100\nrerun of ddddddd: tests/test_b.py\n9 passed\n",
        "cuda_subset_2.log": "commit ffffffffff 2026-11-26 NVIDIA H200\nrerun of ddddddd: tests/test_a.py\n9 passed\n",
        "cuda_subset_3.log": "commit 1111111111 2026-11-26 NVIDIA H100\nrerun of ccccccc: tests/test_a.py\n9 passed\n",
        "cuda_subset_4.log": "commit 2222222222 2026-11-26 NVIDIA H100\nrerun of ddddddd: tests/test_a.py\n1 failed\n",
    }
    for name, text in reruns.items():
        (tmp_path / name).write_text(text)
    got = readme_results.gpu_tests_sentence(tmp_path, tmp_path)
    assert "1 failed, 56 passed on an H100, commit ddddddd" in got and "pass at" not in got
    (tmp_path / "cuda_subset_5.log").write_text(
        "commit 3333333333 2026-11-26 NVIDIA H100\nrerun of ddddddd: tests/test_c.py tests/test_a.py\n12 passed in 4s\n"
    )
    got = readme_results.gpu_tests_sentence(tmp_path, tmp_path)
    assert "fixed at 3333333 (its files: 12 passed, [`cuda_subset_5.log`]" in got
