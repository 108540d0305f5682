#!/usr/bin/env bash
# Creates .venv with the exact versions of requirements-lock.txt and the plugin installed (editable).
# Idempotent. Needs Python >= 3.10 with venv; no GPU. pyproject.toml only states ranges (so that the
# plugin can join an existing nerfstudio environment); the lock makes this set the same everywhere:
# nerfstudio 1.1.5, gsplat 1.4.0, torch 2.14.1 + torchvision 0.29.1 (CUDA builds that also run on CPU).
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then "$py" -m venv .venv; fi
stamp=.venv/.garo-installed
if [ ! -e "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ requirements-lock.txt -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  # The lock pins every transitive version (no resolver backtracking, same set everywhere).
  .venv/bin/python -m pip install -q -c requirements-lock.txt -e ".[test]"
  touch "$stamp"
fi
