"""The A/B over scenes (garo_ns.bench.ab): both result formats, each scene weighing once, the verdicts."""

import json
from pathlib import Path

import pytest

from garo_ns.bench.ab import compare, main, run_of

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def _profile(path, scene, psnr, lpips=0.01, gaussians=100):
    env = {"gpu": "GPU X", "git_commit": "abc"}
    score = {"psnr": psnr, "lpips": lpips}
    run = {"steps": 40_000, "train_seconds": 300.0, "steps_per_second": 40_000 / 300.0}
    path.write_text(
        json.dumps({"scene": scene, "environment": env, "score": score, "gaussians_final": gaussians, **run})
    )
    return str(path)


def _benchmark(path, scene, rows):
    variants = {name: {"psnr": p, "lpips": 0.02, "num_gaussians": 200} for name, p in rows.items()}
    path.write_text(json.dumps({"scene": scene, "gpu": "GPU Y", "git_commit": "def", "variants": variants}))
    return str(path)


def test_each_scene_weighs_once_and_the_verdicts_follow_the_mean(tmp_path):
    base = [
        _benchmark(tmp_path / "ta.json", "a", {"m": 40.0, "other": 1.0}) + ":m",
        _profile(tmp_path / "a2.json", "a", 40.4),
        _profile(tmp_path / "b.json", "b", 30.0, gaussians=50),
    ]
    arm = [_profile(tmp_path / "xa.json", "a", 40.5), _profile(tmp_path / "xb.json", "b", 29.9, gaussians=40)]
    result, table = main(["--base", *base, "--arm", *arm, "--output", str(tmp_path / "ab.json"), "--date", "d"])
    a, b = result["scenes"]["a"], result["scenes"]["b"]
    assert abs(a["base"]["psnr"] - 40.2) < 1e-9 and abs(a["psnr_change_db"] - 0.3) < 1e-9
    assert abs(a["base"]["psnr_spread"] - 0.4) < 1e-9 and a["arm"]["psnr_spread"] is None
    assert abs(result["psnr_change_db"] - 0.1) < 1e-9  # (+0.3 - 0.1) / 2: scene a's two base runs count once
    assert result["within"] and result["gains"] and abs(b["gaussian_ratio"] - 0.8) < 1e-9
    assert "| a | 40.20 (40.00, 40.40) | 40.50 | +0.30 |" in table and "+0.10 dB (within 0.15 dB; gains" in table
    assert json.loads((tmp_path / "ab.json").read_text())["date"] == "d"


def test_a_loss_beyond_the_tolerance_is_neither_within_nor_a_gain(tmp_path):
    result = compare(
        [run_of(_profile(tmp_path / "b.json", "a", 40.0))], [run_of(_profile(tmp_path / "x.json", "a", 39.8))]
    )
    assert not result["within"] and not result["gains"]
    tiny = compare([run_of(str(tmp_path / "b.json"))], [run_of(_profile(tmp_path / "y.json", "a", 40.004))])
    assert tiny["within"] and not tiny["gains"]  # +0.004 dB shows as +0.00: no gain
    only_base = run_of(_profile(tmp_path / "c.json", "c", 1.0))
    assert compare([run_of(str(tmp_path / "b.json")), only_base], [run_of(str(tmp_path / "x.json"))])[
        "skipped_scenes"
    ] == ["c"]


def test_bad_inputs_are_refused_with_a_message(tmp_path):
    bench = _benchmark(tmp_path / "t.json", "a", {"m": 40.0})
    with pytest.raises(SystemExit, match="no variant 'n'"):
        run_of(bench + ":n")
    unscored = {"scene": "a", "environment": {}, "steps": 10, "train_seconds": 1.0, "steps_per_second": 10.0}
    (tmp_path / "u.json").write_text(json.dumps(unscored))
    with pytest.raises(SystemExit, match="no scored run"):
        run_of(str(tmp_path / "u.json"))
    (tmp_path / "v.json").write_text(json.dumps({"scene": "a"}))
    with pytest.raises(SystemExit, match="not a train_profile result"):
        run_of(str(tmp_path / "v.json"))
    with pytest.raises(SystemExit, match="cannot read"):
        run_of(str(tmp_path / "missing.json"))
    with pytest.raises(SystemExit, match="no scene has runs on both sides"):
        compare([run_of(bench + ":m")], [run_of(_profile(tmp_path / "p.json", "b", 1.0))])


def test_the_committed_ab_files_are_their_runs_summary():
    files = sorted(RESULTS.glob("ab_*.json"))
    checked = 0
    for path in files:
        data = json.loads(path.read_text())
        if "base" not in data or not isinstance(data["base"], list):
            continue  # an A/B written by train_speed (before and after sides)
        root = RESULTS.parents[1]
        base = [run_of(str(root / s)) for s in data["base"]]
        arm = [run_of(str(root / s)) for s in data["arm"]]
        fresh = compare(base, arm, data["within_db"])
        assert {k: data[k] for k in fresh} == json.loads(json.dumps(fresh))
        checked += 1
    assert checked >= 1
