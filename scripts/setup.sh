#!/usr/bin/env bash
# Creates .venv with the pinned dependencies and the plugin installed (editable). Idempotent.
# Needs Python >= 3.10 with venv; no GPU. Torch 2.14.1 + torchvision 0.29.1 are CUDA builds that
# also run on CPU (the preinstalled CPU-only torch cannot import torchvision).
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
