#!/usr/bin/env bash
# GPU-machine driver for one hold of a multi-GPU machine (the `device` tool), in phases that fit
# into back-to-back calls (each call is at most 10 minutes; the machine is kept while calls follow):
#   setup SCENE                     copy .scenes/SCENE to /tmp, compile gsplat
#   gputests GPU                    the CUDA-only tests
#   launch NAME SCENE SPLIT GPUS [benchmark args...]
#                                   python -m garo_ns.bench.benchmark in the background on the GPUs GPUS (e.g. 2,3;
#                                   pass --gpus 0 1 to use both): result $W/results/NAME.json, log $W/NAME.log
#   scene SCENE                     copy .scenes/SCENE to /tmp (a call that carries only it)
#   profile NAME SCENE [train_profile args...]
#                                   python -m garo_ns.bench.train_profile --score on /tmp/SCENE in the background
#   pair NAME SCENE PREV [train_profile args...]
#                                   an A/B on one host (2-GPU kinds): `profile NAME_base_SCENE` (the default recipe)
#                                   on GPU 0 and `profile NAME_arm_SCENE` with the args on GPU 1, started together
#   extra NAME CMD...               any other command in the background (parity, ...)
#   wait SECONDS                    poll until every launched job ended or SECONDS passed, then collect
#   collect                         pack results and logs into $OUT, and name the finished exports
#   exports PATTERN                 the finished exports matching PATTERN into $OUT (a call of their own)
# AFTER="JOB ..." before launch or profile starts it once those jobs have ended (a queue launched in one call);
# each phase below says more.
# A pair that does not fit one hold: export one arm in the first hold; here, `mkdir -p .trained/SCENE && cat
# VARIANT.tar.part-* | tar -x -C .trained/SCENE` (git-ignored; it lasts this session only, as the next session gets
# a fresh work tree: both holds of a pair belong to one session); in the next hold carry .trained/SCENE/VARIANT in
# a call of its own (`mkdir -p /tmp/imports && cp -r .trained/SCENE/VARIANT /tmp/imports/`; an export and a scene
# together pass the 64 MiB a call carries), then launch the other arm with --pretrained /tmp/imports/VARIANT
# (garo_ns.bench.transfer).
# Scenes come from .scenes/<name> (../shared/device/make-device-kit.sh).
# Training processes that share a GPU run under CUDA MPS (started by `setup` and `launch`, once per machine):
# without it the GPU time-slices between processes and three 40k arms gave about 1.3x the throughput of one;
# under MPS their kernels run side by side (three jumpingjacks arms reached 40k in 1122 s together). GARO_MPS=0
# turns it off; a machine where an MPS client cannot start a CUDA context falls back to time-slicing.
set -u
phase=$1
shift
W=/tmp/garo-work
if [ -e .device/prelude.sh ]; then source .device/prelude.sh; else source /tmp/kit/prelude.sh; fi
export NERFSTUDIO_METHOD_CONFIGS="garo-deform=garo_ns.config:garo_deform,deform-splatfacto=garo_ns.config:deform_splatfacto"
export TORCHDYNAMO_DISABLE=1
# The commit the result files name: .git-commit (`git rev-parse HEAD > .git-commit` here, carried in the first call:
# it is excluded from git, so only `carry` brings it). Without it they would name the machine copy's git HEAD,
# which can lag behind the work tree.
commit_file=.git-commit; [ -e $commit_file ] || commit_file=$W/src/.git-commit
if [ -e $commit_file ]; then export GARO_GIT_COMMIT=$(cat $commit_file)
else echo "device_run.sh: no .git-commit carried; result files will name the machine's git HEAD" >&2; fi
mkdir -p $W/results $W/jobs

start_mps() {
  [ "${GARO_MPS:-1}" = 1 ] && command -v nvidia-cuda-mps-control > /dev/null || return 0
  [ -e $W/mps.on ] && return 0
  nvidia-cuda-mps-control -d || return 0
  if timeout 90 python3 -c "import torch; assert torch.ones(8, device='cuda').sum().item() == 8"; then
    touch $W/mps.on; echo "CUDA MPS on: processes sharing a GPU run their kernels side by side"
  else
    echo quit | nvidia-cuda-mps-control; echo "CUDA MPS failed to serve a client; training processes time-slice the GPU"
  fi
}
# AFTER="JOB ..." queues a launched run behind each job named (a shell loop for its command line).
after_jobs() {
  for j in ${AFTER:-}; do printf 'while [ ! -e %s/jobs/%s.done ]; do sleep 5; done; ' $W $j; done
}
# What the result files record of it (garo_ns.bench.benchmark.environment).
[ -e $W/mps.on ] && export GARO_MPS_ON=1
[ -d $W/src ] || cp -r . $W/src
# A later call's tree lacks .git-commit unless carried again: keep the carried one where later calls look.
[ -e .git-commit ] && cp .git-commit $W/src/.git-commit
export PYTHONPATH=$W/src:${PYTHONPATH:-}

case $phase in
setup)
  scene=$1
  cp -r .scenes/$scene /tmp/$scene && touch /tmp/$scene.ready
  start_mps
  cd $W/src
  nvidia-smi --query-gpu=index,name,memory.total --format=csv
  python3 -c "import torch; print('torch', torch.__version__, 'gpus', torch.cuda.device_count())"
  t0=$(date +%s)
  python3 -c "from gsplat.cuda._backend import _C; assert _C is not None; print('gsplat CUDA ready')" || exit 1
  echo "gsplat compile: $(( $(date +%s) - t0 )) s" ;;
gputests)
  export CUDA_VISIBLE_DEVICES=$1
  cd $W/src
  # The CUDA-only tests and those whose CUDA path differs (the time table, the switches, the camera); the log names
  # the commit, the date and the GPU: benchmarks/results/gputests_<GPU>.log.
  # Each test's line goes to $OUT/gputests_full.log as it ends, and the run stops at GPUTESTS_S seconds (default 400):
  # a run that hangs then names the test it hung in (one ran past a 10-minute call with MPS on and two GPUs busy).
  { echo "commit ${GARO_GIT_COMMIT:-$(git rev-parse HEAD 2>/dev/null)} $(date -u +%F) $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)"
    timeout ${GPUTESTS_S:-400} python3 -m pytest -v -p no:cacheprovider tests/test_graphs.py tests/test_rendering_cuda.py \
      tests/test_time_table.py tests/test_render_switches.py tests/test_view.py tests/test_training_graphs.py tests/test_adam.py \
      tests/test_train_raster.py tests/test_train_profile.py tests/test_fused_ssim.py tests/test_dense.py tests/test_fp32_heads.py tests/test_table_lookup.py tests/test_frame_graph.py --tb=line 2>&1 \
      | tee $OUT/gputests_full.log | grep -E "Error|FAILED|ERROR| passed| failed" | tail -n 40
    tail -1 $OUT/gputests_full.log | grep -qE "[0-9]+ (passed|failed)" \
      || echo "last test started: $(grep -E '::' $OUT/gputests_full.log | tail -1)"; } | tee $OUT/gputests.log ;;
launch)
  name=$1; scene=$2; split=$3; gpus=$4; shift 4
  [ -d /tmp/$scene ] || cp -r .scenes/$scene /tmp/$scene
  start_mps; [ -e $W/mps.on ] && export GARO_MPS_ON=1
  cd $W/src
  # AFTER=JOB queues this run behind job JOB (its deadline counts from its own start).
  after=$(after_jobs)
  CUDA_VISIBLE_DEVICES=$gpus setsid nohup bash -c "$after python3 -m garo_ns.bench.benchmark --scene /tmp/$scene --split $split $* \
      --output $W/results/$name.json --work-dir $W/$name > $W/$name.log 2>&1; echo \$? > $W/jobs/$name.done" \
      > /dev/null 2>&1 &
  touch $W/jobs/$name.job; sleep 2; echo "launched $name on GPUs $gpus${AFTER:+ (starts when $AFTER has ended)}" ;;
scene)
  cp -r .scenes/$1 /tmp/$1 && touch /tmp/$1.ready && echo "/tmp/$1 ready" ;;
profile)
  name=$1; scene=$2; shift 2
  cd $W/src
  # Waits for the scene's copy (a later call may carry it) and for AFTER's job, so that a queue of runs can be
  # launched in the first call.
  after=$(after_jobs)
  setsid nohup bash -c "$after while [ ! -e /tmp/$scene.ready ]; do sleep 2; done; \
      python3 -m garo_ns.bench.train_profile --scene /tmp/$scene --score $* --work-dir $W/$name \
      --output $W/results/$name.json > $W/$name.log 2>&1; echo \$? > $W/jobs/$name.done" > /dev/null 2>&1 &
  touch $W/jobs/$name.job; sleep 2; echo "launched $name${AFTER:+ (starts when $AFTER has ended)}" ;;
pair)
  name=$1; scene=$2; prev=$3; shift 3
  # Both of this pair's runs wait for both of the previous pair's (PREV: its scene, - for none), so that SWAP may
  # change between pairs.
  wait=; [ "$prev" != - ] && wait="${name}_base_$prev ${name}_arm_$prev"
  # SWAP=1 puts the default on GPU 1 and the arm on GPU 0: two GPUs of one host differed by 2 to 8% on identical
  # steps (the pair's steps 1k to 3k, before the field starts), as much as the arm being measured; alternate SWAP
  # over the scenes, or compare the arms' steps 1k to 3k.
  g0=0; g1=1; [ "${SWAP:-0}" = 1 ] && g0=1 && g1=0
  # BOTH="ARGS": train_profile arguments of both runs (e.g. --method deform-splatfacto).
  CUDA_VISIBLE_DEVICES=$g0 AFTER="$wait" bash "$0" profile ${name}_base_$scene $scene ${BOTH:-}
  CUDA_VISIBLE_DEVICES=$g1 AFTER="$wait" bash "$0" profile ${name}_arm_$scene $scene ${BOTH:-} "$@" ;;
extra)
  name=$1; shift
  cd $W/src
  # Braces: the log takes the output of every command in CMD (a loop, `&` and `wait` included), not the last one's.
  setsid nohup bash -c "{ $*; } > $W/$name.log 2>&1; echo \$? > $W/jobs/$name.done" > /dev/null 2>&1 &
  touch $W/jobs/$name.job; sleep 2; echo "launched $name" ;;
wait)
  limit=$1; t0=$(date +%s); pending=1
  while [ $(( $(date +%s) - t0 )) -lt $limit ]; do
    pending=0
    for j in $W/jobs/*.job; do [ -e "${j%.job}.done" ] || pending=1; done
    [ $pending = 0 ] && break
    sleep 15
  done
  nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
  for d in $W/*/; do
    case $(basename $d) in pack|results|jobs|src|exports) continue;; esac  # a run's arms only
    for f in $d*.log; do
      [ -e "$f" ] && echo "$(basename $d)/$(basename $f): $(grep -o '^[0-9]* ([0-9.]*%)' $f | tail -1)"
    done
  done
  for j in $W/jobs/*.job; do n=$(basename ${j%.job}); echo "$n: $(cat ${j%.job}.done 2>/dev/null || echo running)"; done
  # Pack what has landed (finished results, each trained variant's rows as they are measured, logs) in every
  # call: a machine goes back 30 s after a call returns, so a separate collect call that comes late finds nothing.
  exec bash "$0" collect ;;
collect)
  mkdir -p $W/pack && cp -r $W/results $W/pack/ && cp $W/*.log $W/pack/ 2>/dev/null
  for d in $W/*/; do
    n=$(basename $d); case $n in pack|results|jobs|src) continue;; esac
    mkdir -p $W/pack/$n; cp $d*.log $d*.json $W/pack/$n/ 2>/dev/null
  done
  tar -czf $OUT/results.tar.gz -C $W pack
  ls -la $OUT; echo "exports ready: $(cd $W/exports 2>/dev/null && find . -name model.ckpt | sed 's#^\./##; s#/model.ckpt##' | tr '\n' ' ')"
  cat $W/results/*.md 2>/dev/null ;;
exports)
  # Finished exports whose path under $W/exports matches PATTERN (e.g. 'pillow/*'), as [SCENE_]NAME.tar.part-aa...
  # (15 MiB parts). A call brings back at most 8 files and 64 MiB: one or two exports a call, never with `collect`.
  for e in $(find $W/exports -name record.json 2>/dev/null); do
    e=$(dirname $e); [ -e $e/model.ckpt ] || continue
    rel=${e#$W/exports/}
    case $rel in $1) tar -cf - -C $W/exports $rel | split -b 15m - $OUT/${rel//\//_}.tar.part- ;; esac
  done
  ls -la $OUT ;;
esac
