"""What the demo prints and plots for a new user: commands that run as printed, a PSNR axis that reads."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from garo_ns.tools.demo import psnr_axis, shell_command, write_speed_error_plot

BIN = Path(sys.executable).parent


@pytest.mark.skipif(not (BIN / "ns-viewer").exists(), reason="runs in the plugin's environment")
def test_printed_commands_run_without_an_activated_environment(monkeypatch):
    monkeypatch.setenv("PATH", "/usr/bin:/bin")  # not activated: the venv's scripts are not on PATH
    command = shell_command("ns-viewer")
    assert command != "ns-viewer" and Path(command).resolve() == (BIN / "ns-viewer").resolve()
    monkeypatch.setenv("PATH", f"{BIN}:/usr/bin:/bin")  # activated
    assert shell_command("ns-viewer") == "ns-viewer"


def test_psnr_axis_spans_at_least_two_db():
    low, high = psnr_axis([31.52, 31.63])
    assert high - low == pytest.approx(2.0) and low < 31.52 and high > 31.63
    low, high = psnr_axis([25.0, 31.0])  # a real gap keeps its margins
    assert low < 25.0 - 1 and high > 31.0 + 1


def test_the_plot_says_which_corner_is_better(tmp_path, monkeypatch):
    import matplotlib.axes

    seen = {}
    original = matplotlib.axes.Axes.annotate

    def spy(self, text, *args, **kwargs):
        seen.setdefault("texts", []).append(text)
        seen["ylim"] = self.get_ylim()
        return original(self, text, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "annotate", spy)
    arms = [
        {"method": m, "render_ms": ms, "psnr": p, "num_gaussians": 100, "rasterizer": "reference"}
        for m, ms, p in (("garo-deform", 20.0, 31.52), ("deform-splatfacto", 22.0, 31.63))
    ]
    write_speed_error_plot(arms, tmp_path / "plot.png")
    assert any("better" in t for t in seen["texts"])
    assert seen["ylim"][1] - seen["ylim"][0] >= 2.0 - 1e-9
