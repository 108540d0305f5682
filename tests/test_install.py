"""The plugin installs beside an existing nerfstudio without replacing its torch, torchvision, gsplat or nerfstudio.

pip resolves the plugin's requirements in dry-run mode with no index (nothing can be downloaded, so any
requirement the environment does not already satisfy makes the resolution fail) and reports what it would
install. Two environments: the project's own `.venv`, and a simulated user's nerfstudio 1.1.5 environment
with an older CUDA torch, made by putting metadata-only distributions in front of the real ones on
PYTHONPATH (pip reads installed versions from the first distribution of each name on `sys.path`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUARDED = {"torch", "torchvision", "gsplat", "nerfstudio", "numpy"}

# What a user who followed nerfstudio's install guide has: torch 2.1.2 and torchvision 0.16.2 built for
# CUDA 11.8 (local version labels). nerfstudio, gsplat, numpy and the rest stay the real ones in .venv.
USER_ENV = {
    "torch": ("2.1.2+cu118", []),
    "torchvision": ("0.16.2+cu118", ["torch==2.1.2", "numpy", "pillow!=8.3.*,>=5.3.0"]),
}


def _fake_site(root: Path, dists: Dict[str, Tuple[str, List[str]]]) -> Path:
    """A directory of metadata-only `.dist-info` folders: installed versions as pip sees them."""
    site = root / "site"
    for name, (version, requires) in dists.items():
        info = site / f"{name}-{version}.dist-info"
        info.mkdir(parents=True)
        lines = ["Metadata-Version: 2.1", f"Name: {name}", f"Version: {version}"]
        lines += [f"Requires-Dist: {r}" for r in requires]
        (info / "METADATA").write_text("\n".join(lines) + "\n")
        (info / "INSTALLER").write_text("pip\n")
        (info / "RECORD").write_text("")
    return site


def dry_run(tmp: Path, requirements: List[str], pythonpath: Optional[Path] = None) -> Tuple[int, dict, str]:
    """`pip install --dry-run --no-index --report` of `requirements`; returns (exit code, report, output)."""
    report = tmp / "report.json"
    env = dict(os.environ, PIP_CONFIG_FILE=os.devnull, PIP_NO_INPUT="1", PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PIP_FIND_LINKS", None)
    env.pop("PIP_INDEX_URL", None)
    env.pop("PIP_EXTRA_INDEX_URL", None)
    if pythonpath is not None:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(pythonpath), env.get("PYTHONPATH")]))
    cmd = [sys.executable, "-m", "pip", "install", "--dry-run", "--no-index", "--no-build-isolation"]
    cmd += ["--report", str(report), *requirements]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    data = json.loads(report.read_text()) if report.exists() else {}
    return proc.returncode, data, proc.stdout + proc.stderr


def would_install(report: dict) -> Dict[str, str]:
    """Name -> version of everything the report says pip would install (the plugin itself included)."""
    items = report.get("install", [])
    return {i["metadata"]["name"].lower().replace("_", "-"): i["metadata"]["version"] for i in items}


def installed_version(name: str, pythonpath: Optional[Path] = None) -> str:
    """The version pip would consider installed for `name`, in a fresh interpreter with `pythonpath` first."""
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    code = f"import importlib.metadata as m; print(m.version({name!r}))"
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return proc.stdout.strip()


@pytest.fixture(scope="module")
def user_site(tmp_path_factory) -> Path:
    site = _fake_site(tmp_path_factory.mktemp("userenv"), USER_ENV)
    assert installed_version("torch", site) == "2.1.2+cu118"  # the simulation is what pip will see
    return site


def test_plugin_changes_nothing_in_the_project_environment(tmp_path):
    code, report, out = dry_run(tmp_path, ["-e", ".[test]"])
    assert code == 0, out[-3000:]
    assert set(would_install(report)) == {"garo-ns"}, would_install(report)


def test_plugin_installs_into_a_users_nerfstudio_without_touching_torch(tmp_path, user_site):
    code, report, out = dry_run(tmp_path, ["-e", "."], pythonpath=user_site)
    assert code == 0, f"the plugin's requirements do not fit the user's nerfstudio environment:\n{out[-3000:]}"
    changed = set(would_install(report)) & GUARDED
    assert not changed, f"would replace {changed}: {would_install(report)}"
    assert set(would_install(report)) == {"garo-ns"}, would_install(report)


def test_the_check_catches_a_pinned_torch(tmp_path, user_site):
    """The control: the same dry run with the old exact pin of torch is refused in the user's environment."""
    code, report, _ = dry_run(tmp_path, ["-e", ".", "torch==2.14.1"], pythonpath=user_site)
    assert code != 0 or "torch" in would_install(report)


def test_lock_file_pins_what_the_project_environment_has():
    """setup.sh installs with requirements-lock.txt as constraints: its pins of the guarded packages are the
    versions in .venv, and they satisfy the ranges in pyproject.toml (checked by the first test)."""
    pins = {}
    for line in (ROOT / "requirements-lock.txt").read_text().splitlines():
        if "==" in line and not line.startswith("#"):
            name, version = line.split("==", 1)
            pins[name.strip().lower()] = version.strip()
    assert GUARDED <= set(pins), GUARDED - set(pins)
    for name in GUARDED:
        assert installed_version(name) == pins[name], name
