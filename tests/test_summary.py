"""Cross-scene summary of benchmark results (garo_ns.bench.summary)."""

from __future__ import annotations

import json

import pytest

from garo_ns.bench.summary import SummaryArgs, main, parse_aliases, summarise


def _result(scene, base_fps, garo_fps, base_psnr, garo_psnr, iterations=40_000):
    def row(fps, psnr, n):
        return {
            "psnr": psnr,
            "ssim": 0.9,
            "lpips": None,
            "fps": fps,
            "num_gaussians": n,
            "model_size_mb": n / 4000,
            "iterations": iterations,
            "shortened": iterations < 40_000,
        }

    return {
        "scene": scene,
        "split": "test",
        "gpu": "GPU",
        "git_commit": "abc",
        "variants": {
            "deform-splatfacto": row(base_fps, base_psnr, 100_000),
            "garo-deform": row(garo_fps, garo_psnr, 50_000),
        },
    }


def test_average_of_per_scene_ratios():
    a = _result("a", 100.0, 300.0, 30.0, 29.8)
    b = _result("b", 200.0, 200.0, 40.0, 40.4, iterations=30_000)
    summary = summarise([("a.json", a), ("b.json", b)], ["garo-deform"])
    avg = summary["average"]["garo-deform"]
    assert avg["fps_ratio"] == pytest.approx(2.0)  # mean of 3x and 1x, not 500/300
    assert avg["psnr_drop_db"] == pytest.approx((0.2 - 0.4) / 2)
    assert avg["lpips"] is None  # not measured everywhere: no average
    assert summary["average"]["deform-splatfacto"]["fps"] == pytest.approx(150.0)
    assert summary["shortened_scenes"] == ["b"]
    claim = summary["paper_claim"]["garo-deform"]
    assert claim["scenes_meeting"] == ["a"]  # 3x at 0.2 dB; b is 1x
    assert claim["average_meets"]  # 2.0x at -0.1 dB on average


def test_refuses_incomplete_or_duplicate_input(tmp_path):
    a = _result("a", 100.0, 300.0, 30.0, 29.8)
    with pytest.raises(ValueError, match="a.json: no result for \\['garo-prune0.5'\\]"):
        summarise([("a.json", a)], ["garo-deform", "garo-prune0.5"])
    with pytest.raises(ValueError, match="given twice"):
        summarise([("a.json", a), ("a.json", a)], ["garo-deform"])
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(SystemExit, match="cannot read benchmark result .*broken.json"):
        main(SummaryArgs(results=[broken], output=tmp_path / "out.json"))
    assert not (tmp_path / "out.json").exists()


def test_writes_json_table_and_plot(tmp_path):
    paths = []
    for scene, fps in (("a", 100.0), ("b", 50.0)):
        path = tmp_path / f"{scene}.json"
        path.write_text(json.dumps(_result(scene, fps, 2 * fps, 30.0, 29.9)))
        paths.append(path)
    out = tmp_path / "sum" / "summary.json"
    main(SummaryArgs(results=paths, output=out))
    assert json.loads(out.read_text())["average"]["garo-deform"]["fps_ratio"] == pytest.approx(2.0)
    table = out.with_suffix(".md").read_text()
    assert "| average |  | garo-deform |" in table and "2.00x" in table
    assert "garo-deform: met on average (2.00x at +0.10 dB); met on 2 of 2 scenes (a, b)." in table
    assert out.with_suffix(".png").stat().st_size > 1000


def test_an_alias_reads_a_renamed_run_only_where_the_variant_is_missing():
    a = _result("a", 100.0, 300.0, 30.0, 29.8)
    b = _result("b", 100.0, 150.0, 30.0, 29.0)
    b["variants"]["garo-window"] = b["variants"].pop("garo-deform")
    b["variants"]["garo-window"]["fps"] = 250.0
    a["variants"]["garo-window"] = dict(a["variants"]["garo-deform"], fps=999.0)  # a has garo-deform itself
    summary = summarise([("a.json", a), ("b.json", b)], ["garo-deform"], {"garo-deform": "garo-window"})
    rows = {r["scene"]: r for r in summary["rows"]}
    assert rows["a"]["garo-deform"]["fps_ratio"] == pytest.approx(3.0) and "read_from" not in rows["a"]
    assert rows["b"]["garo-deform"]["fps_ratio"] == pytest.approx(2.5)
    assert rows["b"]["read_from"] == {"garo-deform": "garo-window"}
    with pytest.raises(ValueError, match="no result for"):
        summarise([("b.json", b)], ["garo-deform"])  # without the alias the renamed run is not used
    with pytest.raises(ValueError, match="ROW=VARIANT"):
        parse_aliases(["garo-window"])
    assert parse_aliases(["garo-window=garo-deform"]) == {"garo-deform": "garo-window"}


def test_an_arm_trained_in_an_earlier_hold_is_named_in_the_table(tmp_path):
    a, b = _result("a", 100.0, 200.0, 30.0, 29.9), _result("b", 100.0, 200.0, 30.0, 29.9)
    a["variants"]["deform-splatfacto"]["trained_in"] = {"gpu": "H100", "git_commit": "1234567abc"}
    b["variants"]["deform-splatfacto"]["trained_in"] = "this run"
    paths = []
    for r in (a, b):
        paths.append(tmp_path / f"{r['scene']}.json")
        paths[-1].write_text(json.dumps(r))
    out = tmp_path / "summary.json"
    main(SummaryArgs(results=paths, output=out))
    table = out.with_suffix(".md").read_text()
    assert "a: deform-splatfacto trained in an earlier machine hold (H100, commit 1234567)" in table
    assert "b: deform-splatfacto trained" not in table  # trained in its own run: nothing to say


def test_the_alternating_re_timing_is_carried_where_a_file_has_it(tmp_path):
    a, b = _result("a", 100.0, 200.0, 30.0, 29.9), _result("b", 100.0, 200.0, 30.0, 29.9)
    a["variants"]["deform-splatfacto"]["fps_paired"] = {"fps": 110.0}
    a["variants"]["garo-deform"]["fps_paired"] = {"fps": 242.0}
    summary = summarise([("a.json", a), ("b.json", b)], ["garo-deform"])
    rows = {r["scene"]: r for r in summary["rows"]}
    assert rows["a"]["garo-deform"]["fps_ratio_paired"] == pytest.approx(2.2)
    assert "fps_ratio_paired" not in rows["b"]["garo-deform"]
    paths = []
    for r in (a, b):
        paths.append(tmp_path / f"{r['scene']}.json")
        paths[-1].write_text(json.dumps(r))
    main(SummaryArgs(results=paths, output=tmp_path / "s.json"))
    assert (
        "a: garo-deform timed again in alternating passes beside the baseline: 2.20x" in (tmp_path / "s.md").read_text()
    )


def test_runs_of_one_scene_count_once_as_their_mean(tmp_path):
    a1, a2 = _result("a", 100.0, 300.0, 30.0, 29.8), _result("a", 100.0, 100.0, 30.4, 30.4)
    b = _result("b", 100.0, 200.0, 40.0, 40.0)
    summary = summarise([("a1.json", a1), ("b.json", b), ("a2.json", a2)], ["garo-deform"])
    assert summary["scenes"] == ["a", "b"]
    rows = {r["scene"]: r for r in summary["rows"]}
    a = rows["a"]["garo-deform"]
    assert a["fps_ratio"] == pytest.approx(2.0) and a["fps_ratio_range"] == pytest.approx([1.0, 3.0])
    assert a["psnr_drop_db"] == pytest.approx(0.1) and a["psnr_drop_db_range"] == pytest.approx([0.0, 0.2])
    assert rows["a"]["deform-splatfacto"]["psnr"] == pytest.approx(30.2)
    assert [r["source"] for r in rows["a"]["runs"]] == ["a1.json", "a2.json"]
    # a counts once: (2.0 + 2.0) / 2, not (3 + 1 + 2) / 3 weighted by files
    assert summary["average"]["garo-deform"]["fps_ratio"] == pytest.approx(2.0)
    assert summary["average"]["garo-deform"]["psnr_drop_db"] == pytest.approx(0.05)
    with pytest.raises(ValueError, match="given twice"):
        summarise([("a1.json", a1), ("a1.json", a1)], ["garo-deform"])
    elsewhere = dict(a2, gpu="Other GPU")
    with pytest.raises(ValueError, match="differ in gpu"):
        summarise([("a1.json", a1), ("a2.json", elsewhere)], ["garo-deform"])
    paths = []
    for name, r in (("a1", a1), ("a2", a2), ("b", b)):
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps(r))
    main(SummaryArgs(results=paths, output=tmp_path / "s.json"))
    table = (tmp_path / "s.md").read_text()
    assert "| a run 2 | test | garo-deform |" in table and "| a (mean of 2 runs) | test | garo-deform |" in table
    assert "a: 2 runs (a1.json, a2.json); garo-deform 1.00x to 3.00x at +0.00 to +0.20 dB" in table
