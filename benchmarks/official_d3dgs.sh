#!/usr/bin/env bash
# The OFFICIAL D-3DGS code (ingra14m/Deformable-3D-Gaussians, branch `paper`) on D-NeRF scenes, scored
# as we score our models (benchmarks/official_score.py). None of the official code is in this repo: it is
# assembled into the git-ignored .d3dgs/ (add /.d3dgs/ and /.whl/ to .git/info/exclude).
#
# HERE (the CPU machine), once:
#   1. fetch the snapshots (the `fetch` tool): ingra14m/Deformable-3D-Gaussians,
#      ingra14m/depth-diff-gaussian-rasterization, g-truc/glm, camenduru/simple-knn (under /work/.mirror)
#   2. bash benchmarks/official_d3dgs.sh assemble
#        .d3dgs/code          `git archive paper`, submodules/depth-diff-gaussian-rasterization at the commit
#                             the paper branch records (glm at the commit the rasterizer records, without its
#                             docs and tests), submodules/simple-knn = camenduru/simple-knn (a GitHub copy of
#                             the INRIA repo, with torch 2.x fixes), assets/ dropped (images only); two build
#                             fixes: #include <cstdint> in cuda_rasterizer/rasterizer_impl.h and np.byte ->
#                             np.uint8 in scene/dataset_readers.py (numpy 2)
#        .d3dgs/SOURCES.json  the commits used
#        .d3dgs/garo_head     `git archive HEAD garo_ns`: the committed evaluation code the scorer imports
#        .d3dgs/scenes/S      train + test of each scene (from .scenes/S, see ../shared/device/make-device-kit.sh;
#                             val is not needed and left out to stay under 64 MiB a call)
#        .whl/                the plyfile wheel (Python 3.12), the only package the GPU image lacks
#   3. SCENES="jumpingjacks mutant standup" bash ../shared/device/make-device-kit.sh  (.device: wheels for
#      nerfstudio (SSIM), LPIPS weights, prelude.sh)
#
# THERE (the GPU machine, `run` calls back to back, one hold; work in /tmp/w, which survives while calls follow
# within 30 s). Each call carries at most 64 MiB, so one scene per call:
#   call 1  carry .d3dgs/code .d3dgs/garo_head .whl .d3dgs/scenes/A:  bash benchmarks/official_d3dgs.sh start A 6011
#           (builds both extensions in the background, then starts A once the build is done)
#   call 2  carry .d3dgs/scenes/B:                bash benchmarks/official_d3dgs.sh start B 6012
#   call 3  carry .device .d3dgs/scenes/C:        bash ... start C 6013; source .device/prelude.sh
#           (the kit, for scoring: nerfstudio's SSIM, the LPIPS weights; the runs do not see it)
#   call 4+ (nothing carried):                     bash benchmarks/official_d3dgs.sh wait 450
#           waits until every run ended or the deadline passed, then scores (results under $OUT)
# GPU=i (default 0) puts a run on GPU i: on the 2-GPU kind, the official run on GPU 1 and ours
# (device_run.sh launch ... --gpus 0) on GPU 0 make a same-round pair of one scene in one hold (about 22 minutes;
# on one GPU the pair needs about 29 minutes shared or 30 in turn, more than a session's device time).
# All runs train at once on the one GPU. Each is killed at the deadline, DEADLINE_S (default 1290) seconds
# after call 1 started, so that scoring ends inside the hold; a run that did not reach 40000 is scored at its
# last saved iteration (saves at 20k, 30k, 35k, 40k) and marked shortened.
# Measured there (H200): three runs at once went at 15-20 it/s each once densification had grown the models, one
# alone at about 42 it/s (57 in the 3000-step warm-up), so 40k takes about 16 minutes a scene alone: for the
# full 40k figures, train ONE scene per hold (start A; wait ...), or one per GPU where several are lent.
# OFFICIAL_PATCH=P[,P...] (at the first `start`): the official code with some of its terms made ours, to find what
# separates the two on a scene (`apply_patch` below says what each does): normalized_rotation, alpha_0999, log_scale
# and valid_ssim; all four at once make the official code's terms ours. The patches are named in SOURCES.json's
# "patches" and in the result's file name (official_d3dgs_<P+P>_<GPU>.json).
#
# REAL CAPTURES (issue #68 item 3: an `ns-process-data video` folder or a Nerfies-layout one, on our frames, pixels,
# times and held-out split).
# HERE, after assemble (SCENES=" " assembles without D-NeRF scenes), once per capture (about 20 s; needs a video's
# colmap/sparse/0 and images_2/, or a Nerfies capture's rgb/2x/):
#   bash benchmarks/official_d3dgs.sh prepare-real /work/real/pillow pillow   (benchmarks/official_real.py)
#        .d3dgs/scenes/NAME   the official COLMAP layout (13-14 MB for pillow, teddy) of our frames, pixels and
#                             held-out split: official_real.py's docstring says what it holds, how and why
# THERE, one capture per hold (20000 iterations of 183x239 frames), e.g. pillow:
#   call 1  carry .d3dgs/code .d3dgs/garo_head .whl .d3dgs/scenes/pillow:
#           bash benchmarks/official_d3dgs.sh start pillow 6011
#   call 2  carry .device:  source .device/prelude.sh; bash benchmarks/official_d3dgs.sh wait 480
#   call 3+ (nothing carried):  bash benchmarks/official_d3dgs.sh wait 480   (until it scores)
#           (all in one call would carry about 55 MB of the 64 MiB; two leave room)
# `start` sees test_frames.txt and then trains as the official README trains NeRF-DS / HyperNeRF:
#   python train.py -s W/data/NAME -m W/out/NAME --eval --iterations 20000 (no --is_blender, no --is_6dof; saves and
#   tests at 10k, 15k, 20k), on the official code patched (named in SOURCES.json): split_file (test_frames.txt's
#   test frames), frame_times (our times; the official place over the frames puts a Nerfies held-out frame a place
#   from its twin) and principal_point (the official camera is centred; these lie 1.4 and 3.6 px (pillow), 8.1 px
#   (teddy), 43 px (nerfies-cake) off). On a fresh W, OFFICIAL_CENTRED=1 / OFFICIAL_INDEX_TIMES=1 leave the last two
#   out (result tags `centred`, `index_times`). `score` scores the held-out frames as `garo-eval --split val`
#   scores ours (official_score.py) into official_real_[TAG_]GPU.json and official_NAME.json;
#   `python -m garo_ns.bench.summary ... --official FILE` puts each row under `official` in the capture's row of
#   real_<GPU>.json, with the baseline's PSNR minus the official one (`psnr_gap_db`).
# Phases: assemble | prepare-real CAPTURE NAME | start SCENE PORT | status | wait SECONDS | score |
#         patch P... (apply patches to W/code; OFFICIAL_WORK=DIR sets W, default /tmp/w)
set -u
phase=$1
shift
W=${OFFICIAL_WORK:-/tmp/w}
ITERS="20000 30000 35000 40000"
ITERS_REAL="10000 15000 20000"
MIRROR=${MIRROR:-/work/.mirror}

if [ "$phase" = prepare-real ]; then
  set -e
  cd "$(git rev-parse --show-toplevel)"
  mkdir -p .d3dgs/scenes
  ${PYTHON:-.venv/bin/python} benchmarks/official_real.py "$1" .d3dgs/scenes/"$2"
  du -sh .d3dgs/scenes/"$2"
  exit 0
fi

if [ "$phase" = assemble ]; then
  set -e
  root=$(git rev-parse --show-toplevel)
  cd "$root"
  mkdir -p .git/info
  for d in /.d3dgs/ /.whl/; do grep -qx "$d" .git/info/exclude 2>/dev/null || echo "$d" >>.git/info/exclude; done
  off=$MIRROR/ingra14m+Deformable-3D-Gaussians/repo
  ras=$MIRROR/ingra14m+depth-diff-gaussian-rasterization/repo
  glm=$MIRROR/g-truc+glm/repo
  knn=$MIRROR/camenduru+simple-knn/repo
  rm -rf .d3dgs/code .d3dgs/garo_head
  C=.d3dgs/code
  mkdir -p $C
  git -C "$off" archive paper | tar -x -C $C
  ras_commit=$(git -C "$off" ls-tree paper submodules/depth-diff-gaussian-rasterization | awk '{print $3}')
  R=$C/submodules/depth-diff-gaussian-rasterization
  rm -rf $R && mkdir -p $R && git -C "$ras" archive "$ras_commit" | tar -x -C $R
  glm_commit=$(git -C "$ras" ls-tree "$ras_commit" third_party/glm | awk '{print $3}')
  rm -rf $R/third_party/glm && mkdir -p $R/third_party/glm
  git -C "$glm" archive "$glm_commit" | tar -x -C $R/third_party/glm
  rm -rf $R/third_party/glm/{doc,test,util} $C/assets
  K=$C/submodules/simple-knn
  rm -rf $K && mkdir -p $K && git -C "$knn" archive HEAD | tar -x -C $K
  grep -q '<cstdint>' $R/cuda_rasterizer/rasterizer_impl.h ||
    sed -i 's/#include <iostream>/#include <cstdint>\n#include <iostream>/' $R/cuda_rasterizer/rasterizer_impl.h
  sed -i 's/dtype=np\.byte)/dtype=np.uint8)/' $C/scene/dataset_readers.py
  grep -q '<cstdint>' $R/cuda_rasterizer/rasterizer_impl.h && ! grep -q 'np\.byte' $C/scene/dataset_readers.py
  cat >.d3dgs/SOURCES.json <<EOF
{"official_commit": "$(git -C "$off" rev-parse paper)",
 "depth_diff_gaussian_rasterization_commit": "$ras_commit", "glm_commit": "$glm_commit",
 "simple_knn": "camenduru/simple-knn $(git -C "$knn" rev-parse HEAD) (paper branch records INRIA $(git -C "$off" ls-tree paper submodules/simple-knn | awk '{print $3}'))",
 "patches": ["#include <cstdint> in cuda_rasterizer/rasterizer_impl.h", "np.byte -> np.uint8 in scene/dataset_readers.py"],
 "garo_ns_commit": "$(git rev-parse HEAD)"}
EOF
  cp .d3dgs/SOURCES.json $C/SOURCES.json
  mkdir -p .d3dgs/garo_head && git archive HEAD garo_ns | tar -x -C .d3dgs/garo_head
  for s in ${SCENES:-jumpingjacks mutant standup}; do
    rm -rf .d3dgs/scenes/$s && mkdir -p .d3dgs/scenes/$s
    cp -al .scenes/$s/train .scenes/$s/test .scenes/$s/transforms_train.json .scenes/$s/transforms_test.json \
      .d3dgs/scenes/$s/
  done
  ls .whl/plyfile-*.whl >/dev/null 2>&1 || python3 -m pip download -q --no-deps --only-binary=:all: \
    --python-version 3.12 --implementation cp --platform manylinux_2_17_x86_64 -d .whl plyfile==1.1.5
  du -sh .d3dgs/code .d3dgs/garo_head .d3dgs/scenes/* .whl .device 2>/dev/null
  exit 0
fi

export PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0
mkdir -p $W/data $W/out $W/results
now() { date +%s; }
deadline() { echo $(($(cat $W/t0) + ${DEADLINE_S:-1290})); }
progress() { # last iteration of a run's progress bar
  [ -e $W/$1.log ] && tr '\r' '\n' <$W/$1.log | grep -o '[0-9]*/[0-9]* \[' | tail -1 | cut -d/ -f1
}
status() {
  local s
  echo "[$(date +%T)] t=$(($(now) - $(cat $W/t0)))s of ${DEADLINE_S:-1290}; build: $(cat $W/build.state 2>/dev/null)"
  for s in $(cat $W/scenes 2>/dev/null); do
    echo "  $s: it $(progress $s) $([ -e $W/$s.end ] && echo "ended rc=$(cat $W/$s.rc)")" \
      "saved: $(ls $W/out/$s/point_cloud 2>/dev/null | tr '\n' ' ')"
  done
  nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
}
all_ended() {
  local s
  for s in $(cat $W/scenes); do [ -e $W/$s.end ] || return 1; done
  return 0
}

# One of OFFICIAL_PATCH's terms applied to the machine's copy of the official code ($W/code), each replacing a text
# that must occur exactly as often as counted, and named in SOURCES.json's "patches".
replace() { # FILE COUNT OLD NEW (sed patterns, without "|")
  [ "$(grep -c "$3" "$1")" = "$2" ] || { echo "patch: '$3' not found $2 time(s) in $1"; return 1; }
  sed -i "s|$3|$4|g" "$1"
}
apply_patch() {
  local c=$W/code ras=$W/code/submodules/depth-diff-gaussian-rasterization/cuda_rasterizer what
  case $1 in
  normalized_rotation) # the rasterizer gets normalize(q + dq), as gsplat normalises ours (the official kernel reads
    # an unnormalised q as a rotation that also scales and shears)
    replace $c/gaussian_renderer/__init__.py 1 'rotations = pc.get_rotation + d_rotation$' \
      'rotations = torch.nn.functional.normalize(pc.get_rotation + d_rotation)' || return 1
    what="gaussian_renderer/__init__.py hands the rasterizer normalize(q + dq)" ;;
  alpha_0999) # one Gaussian's alpha capped at 0.999, as gsplat's kernels cap it (the official: 0.99)
    replace $ras/forward.cu 1 'min(0.99f,' 'min(0.999f,' && replace $ras/backward.cu 1 'min(0.99f,' 'min(0.999f,' || return 1
    what="cuda_rasterizer/{forward,backward}.cu cap alpha at 0.999" ;;
  log_scale) # the scale offset added to the log-scale, as ours (deform-scale-offset log): s * exp(ds)
    replace $c/gaussian_renderer/__init__.py 1 'scales = pc.get_scaling + d_scaling$' \
      'scales = pc.get_scaling * torch.exp(d_scaling)' || return 1
    what="gaussian_renderer/__init__.py composes the scale as s * exp(ds)" ;;
  valid_ssim) # the loss's SSIM over the valid region only, as ours (pytorch_msssim's): no zero padding
    replace $c/utils/loss_utils.py 5 'padding=window_size // 2' 'padding=0' || return 1
    what="utils/loss_utils.py: SSIM without padding, the mean over the valid region" ;;
  split_file) # a real capture: test = the frames test_frames.txt names (our held-out frames), not idx % llffhold == 0
    replace $c/scene/dataset_readers.py 1 'cam_infos) if idx % llffhold != 0\]' \
      'cam_infos) if not garo_held_out(path, c, idx % llffhold == 0)]' &&
      replace $c/scene/dataset_readers.py 1 'cam_infos) if idx % llffhold == 0\]' \
        'cam_infos) if garo_held_out(path, c, idx % llffhold == 0)]' || return 1
    cat >>$c/scene/dataset_readers.py <<'PY'


def garo_held_out(path, cam, default):  # split_file (garo_ns benchmarks/official_d3dgs.sh)
    names = os.path.join(path, "test_frames.txt")
    return cam.image_name in open(names).read().split() if os.path.exists(names) else default
PY
    what="scene/dataset_readers.py: readColmapSceneInfo holds out the frames test_frames.txt names" ;;
  frame_times) # a real capture: each frame's time is ours (frame_times.json), not its place over the frames
    replace $c/scene/dataset_readers.py 1 '        fid = int(image_name) / (num_frames - 1)$' \
      '        times = os.path.join(images_folder, "..", "frame_times.json")  # frame_times (garo_ns)\n        fid = json.load(open(times))[image_name] if os.path.exists(times) else int(image_name) / (num_frames - 1)' ||
      return 1
    what="scene/dataset_readers.py: readColmapCameras gives each frame the time frame_times.json names" ;;
  principal_point) # the PINHOLE principal point the COLMAP reader reads, in the projection (the official: centred)
    replace $c/scene/dataset_readers.py 1 '    depth: Optional\[np.array\] = None$' \
      '    depth: Optional[np.array] = None\n    cxcy: Optional[tuple] = None' &&
      replace $c/scene/dataset_readers.py 1 'width=width, height=height, fid=fid)$' \
        'width=width, height=height, fid=fid, cxcy=tuple(intr.params[-2:]))' &&
      replace $c/utils/camera_utils.py 1 'depth=cam_info.depth)$' 'depth=cam_info.depth, cxcy=cam_info.cxcy)' &&
      replace $c/scene/cameras.py 1 'fid=None, depth=None):$' 'fid=None, depth=None, cxcy=None):' &&
      replace $c/scene/cameras.py 1 'fovY=self.FoVy).transpose(0, 1).to(self.data_device)$' \
        'fovY=self.FoVy).transpose(0, 1).to(self.data_device)\n        if cxcy is not None:  # P[0, 2], P[1, 2] (transposed): pixel centres at +0.5, as COLMAP\n            self.projection_matrix[2, 0] = 2 * cxcy[0] / self.image_width - 1\n            self.projection_matrix[2, 1] = 2 * cxcy[1] / self.image_height - 1' ||
      return 1
    what="scene/cameras.py projects with the PINHOLE camera's cx, cy (read in scene/dataset_readers.py, passed by utils/camera_utils.py)" ;;
  *) echo "unknown patch $1 (see apply_patch)"; return 1 ;;
  esac
  python3 - $c/SOURCES.json "$1: $what" <<'PY'
import json, sys
sources = json.load(open(sys.argv[1]))
sources["patches"].append(sys.argv[2])
json.dump(sources, open(sys.argv[1], "w"))
PY
}

# A patch applied once to the machine's copy of the official code (copied from .d3dgs/code on first use).
copy_code() { [ -e $W/code ] || { cp -r .d3dgs/code $W/code && cp -r .d3dgs/garo_head $W/garo_head; }; }
ensure_patch() {
  copy_code
  grep -q "\"$1: " $W/code/SOURCES.json || apply_patch $1
}

case $phase in
patch) # patch P...: apply patches to W/code (to check them on the CPU machine: OFFICIAL_WORK=/tmp/somewhere)
  for p in "$@"; do ensure_patch $p || exit 1; done
  ;;
start)
  scene=$1 port=$2
  [ -e $W/t0 ] || now >$W/t0
  if [ ! -e $W/build.state ]; then
    copy_code
    for patch in $(echo "${OFFICIAL_PATCH:-}" | tr ',' ' '); do
      ensure_patch $patch || exit 1
    done
    [ -n "${OFFICIAL_PATCH:-}" ] && echo "$OFFICIAL_PATCH" | tr ',' '\n' >>$W/patch
    python3 -m pip install -q --no-index --no-deps .whl/*.whl
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    python3 -c "import torch; print('torch', torch.__version__, torch.version.cuda)"
    echo building >$W/build.state
    # Both extensions at once, in the background (about 2 minutes); runs wait for $W/built.
    setsid nohup bash -c "
      export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
      (cd $W/code/submodules/depth-diff-gaussian-rasterization && python3 -m pip install --no-build-isolation --no-deps . ) > $W/build_ras.log 2>&1 &
      (cd $W/code/submodules/simple-knn && python3 -m pip install --no-build-isolation --no-deps . ) > $W/build_knn.log 2>&1 &
      wait
      cd /tmp && if python3 -c 'import torch, diff_gaussian_rasterization, simple_knn._C'; then touch $W/built; echo built > $W/build.state; else echo FAILED > $W/build.state; fi
    " >$W/build.log 2>&1 </dev/null &
  fi
  rm -rf $W/data/$scene && cp -r .d3dgs/scenes/$scene $W/data/$scene
  grep -qx $scene $W/scenes 2>/dev/null || echo $scene >>$W/scenes
  # A real capture (prepare-real): our held-out frames, the principal point unless OFFICIAL_CENTRED=1, and the
  # official README's real-scene command (no --is_blender, 20000 iterations: our -real recipes' length).
  train_args="--eval --is_blender" its=$ITERS
  if [ -e $W/data/$scene/test_frames.txt ]; then
    ensure_patch split_file || exit 1
    if [ "${OFFICIAL_CENTRED:-0}" = 1 ]; then echo centred >>$W/patch; else ensure_patch principal_point || exit 1; fi
    if [ "${OFFICIAL_INDEX_TIMES:-0}" = 1 ] || [ ! -e $W/data/$scene/frame_times.json ]; then
      grep -qx index_times $W/patch 2>/dev/null || echo index_times >>$W/patch
    else ensure_patch frame_times || exit 1; fi
    train_args="--eval --iterations 20000" its=$ITERS_REAL
  fi
  # The run: waits for the build, trains with the official defaults (D-NeRF: 40000 iterations), killed at the deadline.
  setsid nohup bash -c "
    echo \$\$ > $W/$scene.pid
    while [ ! -e $W/built ]; do grep -q FAILED $W/build.state && { echo 1 > $W/$scene.rc; date +%s.%N > $W/$scene.end; exit 1; }; sleep 2; done
    cd $W/code
    date +%s.%N > $W/$scene.start
    left=\$(( $(deadline) - \$(date +%s) )); [ \$left -gt 1 ] || left=1
    CUDA_VISIBLE_DEVICES=${GPU:-0} timeout --foreground -s KILL \$left python3 train.py -s $W/data/$scene -m $W/out/$scene \
      $train_args --port $port --test_iterations $its --save_iterations $its
    echo \$? > $W/$scene.rc
    date +%s.%N > $W/$scene.end
  " >$W/$scene.log 2>&1 </dev/null &
  sleep 5
  status
  ;;
status)
  status
  tail -c 400 $W/build_ras.log 2>/dev/null
  ;;
wait)
  limit=$(($(now) + $1))
  [ "$limit" -lt "$(deadline)" ] || limit=$(deadline)
  while ! all_ended && [ "$(now)" -lt "$limit" ]; do
    status
    nap=$((limit - $(now)))
    [ $nap -le 30 ] || nap=30
    [ $nap -ge 1 ] && sleep $nap
  done
  status
  if all_ended || [ "$(now)" -ge "$(deadline)" ]; then exec bash "$0" score; fi
  echo "not done yet: call wait again"
  ;;
score)
  # Stop whatever still trains (each run is its own process session), so timing has the GPU alone.
  for s in $(cat $W/scenes); do
    [ -e $W/$s.end ] || { echo "stopping $s at it $(progress $s)"; kill -KILL -- -"$(cat $W/$s.pid)" 2>/dev/null; }
  done
  sleep 3
  for s in $(cat $W/scenes); do [ -e $W/$s.end ] || { echo 137 >$W/$s.rc; date +%s.%N >$W/$s.end; }; done
  status
  if [ -e /tmp/kit/prelude.sh ]; then source /tmp/kit/prelude.sh; else source .device/prelude.sh; fi
  export PYTHONPATH=$W/garo_head:${PYTHONPATH:-} # the committed evaluation code (SOURCES.json names the commit)
  gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | grep -o 'H[0-9]\{3\}' || echo GPU)
  tag=; [ -e $W/patch ] && tag="$(sort -u $W/patch | paste -sd+)_"
  kind=d3dgs_; [ -e "$W/data/$(head -1 $W/scenes)/test_frames.txt" ] && kind=real_
  # Scored and timed on the GPU the runs trained on: on a 2-GPU machine the other may be timing our arms.
  CUDA_VISIBLE_DEVICES=${GPU:-0} python3 benchmarks/official_score.py --work $W --code $W/code --scenes $(cat $W/scenes) \
    --sources $W/code/SOURCES.json --note "${SHARING_NOTE:-}" --output $W/results/official_$kind$tag$gpu.json 2>&1 | tee $W/score.log
  if [ -n "${OUT:-}" ]; then
    cp $W/results/*.json $OUT/
    for s in $(cat $W/scenes); do
      echo "== $s (rc $(cat $W/$s.rc), $(cat $W/$s.start 2>/dev/null) -> $(cat $W/$s.end))"
      tr '\r' '\n' <$W/$s.log | grep -v '^Training progress' | grep -v '^\s*$' | tail -12
      tr '\r' '\n' <$W/$s.log | grep '^Training progress' | tail -1
    done >$OUT/official_$kind$tag$gpu.log
    cp $W/score.log $OUT/score.log
  fi
  ;;
*)
  echo "unknown phase $phase" >&2
  exit 2
  ;;
esac
