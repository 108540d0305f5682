"""The README and docs/ stay true to the code and the result files: the generated settings page and the
README's results block are current, every relative link points to a file, and the README stays short."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _script(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / name), *args], cwd=ROOT, capture_output=True, text=True
    )


def test_settings_page_regenerates_without_a_diff():
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import settings_page
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    assert settings_page.render_page() == (ROOT / "docs" / "settings.md").read_text(), (
        "docs/settings.md is out of date: run python scripts/settings_page.py"
    )


def test_settings_page_lists_every_model_option():
    import dataclasses

    from garo_ns.garo_model import GaroModelConfig

    page = (ROOT / "docs" / "settings.md").read_text()
    for f in dataclasses.fields(GaroModelConfig):
        if not f.name.startswith("_"):
            assert f"| `{f.name.replace('_', '-')}` |" in page, f.name


def test_readme_results_block_is_up_to_date():
    result = _script("readme_results.py", "--check")
    assert result.returncode == 0, result.stdout + result.stderr


def test_readme_results_check_fails_on_a_stale_block(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text((ROOT / "README.md").read_text().replace("| standup (test) |", "| standup (test) | stale"))
    stale = _script("readme_results.py", "--check", "--readme", str(readme))
    assert stale.returncode == 1 and "out of date" in stale.stdout, stale.stdout + stale.stderr
    assert _script("readme_results.py", "--readme", str(readme)).returncode == 0  # rewrites the block
    assert "| standup (test) | 4" in readme.read_text()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_to_files(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # not links inside code blocks
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    missing = []
    for target in targets:
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # an absolute URL or an anchor on the same page
        path = (page.parent / target.split("#")[0]).resolve()
        if not path.exists():
            missing.append(target)
    assert not missing, f"{page.name}: links to missing files {missing}"


def test_readme_is_at_most_15_kb():
    assert (ROOT / "README.md").stat().st_size <= 15_000


def test_benchmarks_holds_only_scripts_the_docs_name_and_none_that_history_retired():
    """Each script in benchmarks/ is named in the README or docs/ (what it makes is cited there); a script that
    HISTORY's "Retired scripts" table lists is not in the folder."""
    named = "\n".join(page.read_text() for page in PAGES)
    scripts = sorted(p.name for p in (ROOT / "benchmarks").iterdir() if p.suffix in (".py", ".sh"))
    assert scripts and not [name for name in scripts if name not in named], "scripts the docs do not name"
    history = (ROOT / "benchmarks" / "HISTORY.md").read_text()
    table = history.split("## Retired scripts", 1)[1].split("\n## ", 1)[0]
    retired = re.findall(r"^\| `([\w.]+\.(?:py|sh))` \|", table, flags=re.M)
    assert retired and not set(retired) & set(scripts), "a retired script is back in benchmarks/"


@pytest.mark.parametrize("block", ["compaction", "demo", "tests", "training"])
def test_readme_demo_and_test_figures_come_from_their_result_files(tmp_path, block):
    """The demo's and the tests' figures are rewritten from their files; a typed change is caught."""
    readme = tmp_path / "README.md"
    text = (ROOT / "README.md").read_text()
    begin, end = f"<!-- {block}:begin -->", f"<!-- {block}:end -->"
    assert begin in text and end in text
    readme.write_text(text.replace(end, "typed by hand\n" + end))
    assert _script("readme_results.py", "--check", "--readme", str(readme)).returncode == 1
    assert _script("readme_results.py", "--readme", str(readme)).returncode == 0
    rewritten = readme.read_text()
    assert "typed by hand" not in rewritten and begin in rewritten and end in rewritten


def test_results_block_names_an_imported_arm_and_the_paired_retiming(tmp_path):
    """A Table 1 row whose baseline trained in an earlier hold says so, and the benchmark's alternating re-timing
    is reported beside the row."""
    import json

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))

    def arm(fps, **extra):
        return {"psnr": 30.0, "lpips": 0.01, "fps": fps, "num_gaussians": 1000, "iterations": 40_000, **extra}

    table = {
        "scene": "s",
        "split": "test",
        "gpu": "G",
        "git_commit": "0123456789",
        "variants": {
            "deform-splatfacto": arm(100.0, trained_in={"gpu": "G", "git_commit": "abcdef0123"}),
            "garo-deform": arm(200.0, trained_in="this run"),
        },
    }
    (tmp_path / "table1_s_G.json").write_text(json.dumps(table))
    block = readme_results.render_block(tmp_path, tmp_path)
    assert "s: the baseline arm did not fit" in block and "commit abcdef0" in block and "GARO arm" not in block
    assert "alternating passes" not in block
    table["variants"]["deform-splatfacto"]["fps_paired"] = {"fps": 100.0, "passes": 6}
    table["variants"]["garo-deform"]["fps_paired"] = {"fps": 210.0, "passes": 6}
    (tmp_path / "table1_s_G.json").write_text(json.dumps(table))
    block = readme_results.render_block(tmp_path, tmp_path)
    assert "s: timed again in 6 alternating passes in the same run (median pass): 2.10x." in block


def test_results_block_counts_a_scene_run_twice_once(tmp_path):
    """`table1_<scene>_run<k>_<GPU>.json` is another run of a scene: a row of its own in the table, and the
    scene's runs are averaged before the average over scenes."""
    import json

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))

    def table(scene, base_fps, garo_fps, garo_psnr):
        arm = {"lpips": 0.01, "num_gaussians": 1000, "iterations": 40_000}
        return {
            "scene": scene,
            "split": "test",
            "gpu": "G",
            "git_commit": "0123456789",
            "variants": {
                "deform-splatfacto": {**arm, "psnr": 30.0, "fps": base_fps},
                "garo-deform": {**arm, "psnr": garo_psnr, "fps": garo_fps},
            },
        }

    (tmp_path / "table1_a_G.json").write_text(json.dumps(table("a", 100.0, 300.0, 29.0)))
    (tmp_path / "table1_a_run2_G.json").write_text(json.dumps(table("a", 100.0, 100.0, 30.0)))
    (tmp_path / "table1_b_G.json").write_text(json.dumps(table("b", 100.0, 100.0, 30.0)))
    (tmp_path / "table1_a_H.json").write_text(json.dumps(table("a", 1.0, 900.0, 0.0)))  # another GPU: not read
    assert readme_results.find_files(tmp_path) == {
        "a": [tmp_path / "table1_a_G.json", tmp_path / "table1_a_run2_G.json"],
        "b": [tmp_path / "table1_b_G.json"],
    }
    block = readme_results.render_block(tmp_path, tmp_path)
    assert "| a run 1 (test) |" in block and "| a run 2 (test) |" in block and "| b (test) |" in block
    # a: (3x + 1x) / 2 = 2x and -0.5 dB; b: 1x and 0 dB; over scenes 1.5x at -0.25 dB (not 5/3x over files)
    assert "| average of 2 scenes |" in block and "| 1.50x | -0.25 dB |" in block
    assert "A scene run more than once (a) counts once in the average" in block


def test_compaction_block_comes_from_the_target_summary(tmp_path):
    """Until `compact_<GPU>.json` exists the block says so; then each scene's row, the average and the target's
    verdict come from it, and a summary made without --target is refused."""
    import json

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    from garo_ns.bench.summary import SummaryArgs, main

    assert "has not been run at 40k yet" in readme_results.compaction_block(tmp_path, tmp_path)

    def result(scene, base_fps, fps, drop):
        base = {"psnr": 40.0, "lpips": 0.01, "fps": base_fps, "num_gaussians": 100_000, "model_size_mb": 24.0}
        arm = {"psnr": 40.0 - drop, "lpips": 0.011, "fps": fps, "num_gaussians": 30_000, "model_size_mb": 7.0}
        rows = {
            "deform-splatfacto": {**base, "iterations": 40_000},
            "garo-compact": {**arm, "fps": fps / 2, "iterations": 40_000},
            "garo-compact+auto": {**arm, "iterations": 40_000},
            "garo-compact+auto+fp16": {**arm, "model_size_mb": 3.5, "iterations": 40_000},
        }
        return {"scene": scene, "split": "test", "gpu": "NVIDIA H200", "git_commit": "abc1234", "variants": rows}

    paths = []
    for scene, drop in (("jumpingjacks", 0.1), ("standup", 0.3)):
        paths.append(tmp_path / f"compact40k_{scene}_H200.json")
        paths[-1].write_text(json.dumps(result(scene, 200.0, 1400.0, drop)))
    variants = ["garo-compact", "garo-compact+auto", "garo-compact+auto+fp16"]
    out = tmp_path / "compact_H200.json"
    main(SummaryArgs(results=paths, output=out, variants=variants))
    with pytest.raises(ValueError, match="no target_check"):
        readme_results.compaction_block(tmp_path, tmp_path)
    main(
        SummaryArgs(
            results=paths,
            output=out,
            variants=variants,
            target="compaction",
            target_variant="garo-compact+auto",
            size_variant="garo-compact+auto+fp16",
        )
    )
    block = readme_results.compaction_block(tmp_path, tmp_path)
    assert "| jumpingjacks | 40.00 / 39.90 | 0.0100 / 0.0110 | 200 / 1400 | 7.00x | 100,000 / 30,000 | 3.5 |" in block
    assert "Not run at 40k yet: mutant. The average and the verdict cover 2 of the 3 scenes." in block
    assert (
        "The paper's claim (2.0x at <= 0.5 dB, on average): `garo-compact` meets it (3.50x at +0.20 dB; 2 of 2 "
        "scenes), `garo-compact+auto` meets it (7.00x at +0.20 dB; 2 of 2 scenes)." in block
    )
    assert "| average | 40.00 / 39.80 |" in block and "40,000 steps, NVIDIA H200" in block
    assert "Target `compaction`: Every criterion is met on 2 scene(s)." in block
    assert "[`compact_H200.md`](compact_H200.md)" in block


def test_training_line_reads_the_newest_train_speed_file(tmp_path):
    import json

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from readme_results import training_block

    def side(minutes, psnr, steps=None, scenes=("lego",)):
        runs = [{"file": f"run{minutes}{s}.json", "scene": s, "minutes_per_40k": minutes, "psnr": psnr} for s in scenes]
        return {"runs": runs, "minutes_per_40k": minutes, "minutes_per_40k_steps": steps, "psnr": psnr}

    entry = {"before": side(9.31, 30.0), "after": side(4.5, 30.1, 4.0, ("lego", "ship"))}
    entry.update(speedup=2.07, scenes_compared=["lego"])
    (tmp_path / "train_speed_X.json").write_text(json.dumps({"gpus": ["GPU X"], "methods": {"garo-deform": entry}}))
    newer = {"date": "2026-01-02", "gpus": ["GPU Y"], "methods": {"garo-deform": {"after": side(3.25, 30.2)}}}
    (tmp_path / "train_speed_Y.json").write_text(json.dumps(newer))
    line = training_block(tmp_path, tmp_path)
    assert "alone on one GPU Y on lego (" in line and "`garo-deform` 3.2 min, 30.20 dB." in line and "GPU X" not in line
    (tmp_path / "train_speed_Y.json").unlink()
    line = training_block(tmp_path, tmp_path)
    assert "alone on one GPU X on lego, ship (" in line
    assert "`garo-deform` 4.5 min (4.0), 30.10 dB, 2.07x the speed before on lego." in line
    entry["after"]["slowest_minutes_per_40k"] = 4.75
    (tmp_path / "train_speed_X.json").write_text(json.dumps({"gpus": ["GPU X"], "methods": {"garo-deform": entry}}))
    assert "4.5 min (4.0), the slowest run 4.8, 30.10 dB" in training_block(tmp_path, tmp_path)


def test_the_readme_names_the_newest_gpu_test_run(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
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
    # pytest -v frames its counts in '='; a run the phase's limit stopped names the test it stopped in, after them.
    (tmp_path / "gputests_H200.log").write_text(
        "commit bbbbbbbbbb 2026-11-26 NVIDIA H200\n===== 70 passed, 4 warnings in 20.21s =====\n"
        "last test started: tests/test_a.py::test_x\n"
    )
    assert "70 passed on an H200, commit bbbbbbb" in readme_results.gpu_tests_sentence(tmp_path, tmp_path)
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


def test_real_block_says_why_each_capture_misses_the_target(tmp_path):
    """The real-capture block names each miss from the files: a refused time table with its measured change, a
    PSNR loss over 0.5 dB; and our baseline's signed gap to the official code, ahead or behind."""
    import json

    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import readme_results
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))

    def capture(scene, fast_fps, fast_drop, table_used, gap):
        arms = {a: {"peak_memory_mb": {"training": 4096.0}} for a in readme_results.REAL_ARMS}
        arms["garo-compact+auto"] = {
            "render_switches_used": {"time_table": table_used},
            "switch_record": {"tried": {"time_table": 0.0213}},
        }
        (tmp_path / f"real_{scene}_G.json").write_text(json.dumps({"git_commit": "0123456789", "variants": arms}))
        arm = {"psnr": 20.0, "lpips": 0.1, "fps": 100.0, "num_gaussians": 1000}
        fast = {**arm, "fps": 100.0 * fast_fps, "fps_ratio": fast_fps, "psnr_drop_db": fast_drop}
        official = {"psnr": 20.0 - gap, "lpips": 0.1, "iterations": 20000, "num_gaussians": 3000, "psnr_gap_db": gap}
        return {
            "scene": scene,
            "source": f"real_{scene}_G.json",
            "deform-splatfacto": arm,
            "garo-deform": arm,
            "garo-compact+auto": fast,
            "official": official,
        }

    rows = [
        capture("pillow", 4.8, 0.1, True, 0.06),
        capture("teddy", 1.6, -0.1, False, 1.57),
        capture("nerfies-cake", 8.9, 0.62, True, -0.89),
    ]
    (tmp_path / "real_G.json").write_text(json.dumps({"rows": rows}))
    block = readme_results.real_block(tmp_path, tmp_path)
    assert "4x within 0.5 dB on 1 of 3 captures (pillow)" in block
    assert "teddy: 1.60x, its time table refused (0.021 dB on training views)" in block
    assert "nerfies-cake: 0.62 dB lost" in block and "nerfies-cake: 8.90x" not in block
    assert "pillow +0.06 dB, teddy +1.57 dB, nerfies-cake -0.89 dB" in block
