"""Step times read from benchmark worker logs (benchmarks/step_rate.py)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("step_rate", ROOT / "benchmarks" / "step_rate.py")
step_rate = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(step_rate)

# As nerfstudio's local writer prints them: colour codes, a first line in seconds, then milliseconds.
LOG = (
    "0 (0.00%)           1 s, 217.760 ms      13 h, 31 m, 50 s      \x1b[0m\n"
    "2000 (5.00%)        10.000 ms            5 m, 1 s             26.44 M\n"
    "2500 (6.25%)        14.000 ms            5 m, 1 s             26.44 M\n"
    "4100 (10.25%)       21.500 ms            5 m, 1 s             26.44 M\n"
)


def test_progress_lines_give_the_mean_step_time_per_window(tmp_path):
    steps = step_rate.step_ms(LOG)
    assert steps == {2000: 10.0, 2500: 14.0, 4100: 21.5}  # the line in seconds is not read as 217.76 ms
    assert step_rate.window_means(steps) == {"2000-3000": 12.0, "4000-6000": 21.5}
    log = tmp_path / "garo-oaa.log"
    log.write_text(LOG)
    out = tmp_path / "rate.json"
    script = str(ROOT / "benchmarks" / "step_rate.py")
    subprocess.run([sys.executable, script, "--group", "3-arms", str(log), "--output", str(out)], check=True)
    assert json.loads(out.read_text())["groups"] == {"3-arms": {"garo-oaa": {"2000-3000": 12.0, "4000-6000": 21.5}}}
