#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the whole CPU test suite.
# System packages for the viewer, render and video tests: Debian's chromium (the viewer is tested in a real
# headless browser), ffmpeg (ns-render and ns-process-data need it) and colmap (ns-process-data poses a
# video with it). Installed when missing and apt-get can run; without them those tests are skipped with
# the reason.
set -euo pipefail
cd "$(dirname "$0")/.."
missing=()
command -v chromium > /dev/null || missing+=(chromium)
command -v ffmpeg > /dev/null || missing+=(ffmpeg)
command -v colmap > /dev/null || missing+=(colmap)
if [ ${#missing[@]} -gt 0 ] && command -v apt-get > /dev/null && [ "$(id -u)" = 0 ]; then
  (apt-get update -q > /dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${missing[@]}" > /dev/null) \
    || echo "warning: could not install ${missing[*]}; the tests that need them will be skipped"
fi
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1  # nerfstudio compiles a helper with torch.compile; not needed on CPU
.venv/bin/ruff check garo_ns tests benchmarks scripts
.venv/bin/python -m pytest -q -rs "$@"
