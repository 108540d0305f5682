#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the main job: train garo-deform on the built-in dynamic scene
# and print its test figures and where the run is. Extra arguments go to garo-demo (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1
.venv/bin/garo-demo "$@"
