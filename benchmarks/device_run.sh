#!/usr/bin/env bash
# GPU-machine driver for one hold of a multi-GPU machine (the `device` tool), in three phases:
#   bash benchmarks/device_run.sh start SCENE SPLIT MAIN_ITERS ABL_ITERS DEADLINE_S
#       compile gsplat, a quick GPU smoke run, then in the background: the main comparison
#       (deform-splatfacto and garo-deform, MAIN_ITERS steps, GPUs 0 and 1, stopped at DEADLINE_S
#       seconds if unfinished), the rasterizer parity check and the GARO step benchmark (GPUs 2
#       and 3), then the ablations (baseline, GARO, OAA only, GCA only at ABL_ITERS, GPUs 2 and 3).
#   bash benchmarks/device_run.sh wait SECONDS     poll until everything ended or SECONDS passed
#   bash benchmarks/device_run.sh collect          pack results and logs into $OUT/results.tar.gz
# Scenes come from .scenes/<name> (../shared/device/make-device-kit.sh), copied to /tmp first.
set -u
phase=$1
W=/tmp/garo-work
if [ -e .device/prelude.sh ]; then source .device/prelude.sh; else source /tmp/kit/prelude.sh; fi
export NERFSTUDIO_METHOD_CONFIGS="garo-deform=garo_ns.config:garo_deform,deform-splatfacto=garo_ns.config:deform_splatfacto"
export TORCHDYNAMO_DISABLE=1 GARO_GIT_COMMIT=$(cat .git-commit 2>/dev/null || echo unknown)
export PYTHONPATH=$PWD:${PYTHONPATH:-}

case $phase in
start)
  shift; scene=$1; split=$2; main_iters=$3; abl_iters=$4; deadline=$5
  mkdir -p $W/results && cp -r .scenes/$scene /tmp/$scene && cp -r . $W/src
  cd $W/src
  nvidia-smi --query-gpu=index,name,memory.total --format=csv
  python3 -c "import torch; print('torch', torch.__version__, 'gpus', torch.cuda.device_count())"
  t0=$(date +%s)
  python3 -c "from gsplat.cuda._backend import _C; assert _C is not None; print('gsplat CUDA ready')" || exit 1
  echo "gsplat compile: $(( $(date +%s) - t0 )) s"
  # Smoke: a few steps of both arms through the CUDA path, so a bug surfaces before the long runs.
  python3 -m garo_ns.benchmark --scene /tmp/$scene --split $split --iterations 200 --gpus 0 1 \
      --output $W/smoke/smoke.json --work-dir $W/smoke/runs > $W/smoke.log 2>&1 || { tail -40 $W/smoke.log; exit 1; }
  tail -6 $W/smoke.log
  setsid nohup bash -c "CUDA_VISIBLE_DEVICES=0,1 python3 -m garo_ns.benchmark --scene /tmp/$scene --split $split \
      --iterations $main_iters --gpus 0 1 --deadline-s $deadline --output $W/results/${scene}_main.json \
      --work-dir $W/main > $W/main.log 2>&1; echo done > $W/main.done" > /dev/null 2>&1 &
  setsid nohup bash -c "CUDA_VISIBLE_DEVICES=3 python3 benchmarks/rasterizer_parity.py --scene /tmp/$scene --split $split \
      --n 50000 --output $W/results/rasterizer_parity.json > $W/parity.log 2>&1; \
      CUDA_VISIBLE_DEVICES=2 python3 benchmarks/garo_step.py --n 500000 --output $W/results/garo_step.json \
      > $W/garo_step.log 2>&1; \
      CUDA_VISIBLE_DEVICES=2 python3 -m garo_ns.benchmark --scene /tmp/$scene --split $split --ablations \
      --iterations $abl_iters --gpus 2 3 --deadline-s $deadline --output $W/results/${scene}_ablations.json \
      --work-dir $W/abl > $W/abl.log 2>&1; echo done > $W/abl.done" > /dev/null 2>&1 &
  sleep 5; echo started ;;
wait)
  limit=$2; t0=$(date +%s)
  while [ $(( $(date +%s) - t0 )) -lt $limit ]; do
    [ -e $W/main.done ] && [ -e $W/abl.done ] && break
    sleep 20
  done
  nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
  for f in $W/main/*.log $W/abl/*.log; do
    [ -e "$f" ] && echo "$(basename $f): $(grep -o '^[0-9]* ([0-9.]*%)' $f | tail -1)"
  done
  ls $W/results; for f in $W/main.done $W/abl.done; do [ -e $f ] && echo "$f"; done ;;
collect)
  mkdir -p $W/pack && cp -r $W/results $W/pack/ && cp $W/*.log $W/pack/ 2>/dev/null
  for d in main abl smoke; do mkdir -p $W/pack/$d; cp $W/$d/*.log $W/$d/*.json $W/pack/$d/ 2>/dev/null; done
  tar -czf $OUT/results.tar.gz -C $W pack && ls -la $OUT
  cat $W/results/*.md 2>/dev/null; cat $W/results/rasterizer_parity.json $W/results/garo_step.json 2>/dev/null ;;
esac
