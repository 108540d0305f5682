#!/usr/bin/env bash
# Sets up (scripts/setup.sh) and runs the main job: train garo-deform and the deform-splatfacto baseline on
# the built-in dynamic scene, print them side by side and write a picture and a plot of them.
# Extra arguments go to garo-demo (see --help).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export TORCHDYNAMO_DISABLE=1
# One CPU thread per process unless told otherwise: the demo's tensors are small, and on a 2-core machine
# shared with other work torch's default two threads spin at each barrier; measured under such load, a
# 300-step demo took 2.9 min with one thread, and the same run with two was still in its first arm after 10.
# The cores go to the arms instead: on a CPU with one per arm they train at once, a process each.
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} MKL_NUM_THREADS=${MKL_NUM_THREADS:-1}
.venv/bin/garo-demo "$@"
