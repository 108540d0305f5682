#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the whole CPU test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1  # nerfstudio compiles a helper with torch.compile; not needed on CPU
.venv/bin/ruff check garo_ns tests benchmarks
.venv/bin/python -m pytest -q -rs "$@"
