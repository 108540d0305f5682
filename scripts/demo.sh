#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the main job: train garo-deform and the deform-splatfacto baseline on
# the built-in dynamic scene, print them side by side and write a picture and a plot of them.
# Extra arguments go to garo-demo (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1
.venv/bin/garo-demo "$@"
