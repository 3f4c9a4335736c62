#!/bin/bash
# How several training processes share one GPU: B stage 2 (the screen's config), 1 process, then 4 at once,
# then 4 at once under CUDA MPS (if it starts); 65 s each; train logs tarred to $OUT.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 SDL_VIDEODRIVER=dummy PYTHONDONTWRITEBYTECODE=1
python3 -m pip install -q --no-index --no-deps .wheels/*.whl || exit 1
python3 -m pip install -q --no-deps --no-build-isolation --ignore-requires-python -e . || exit 1
mkdir -p /work/science && cp -r .gpu/stage1 /work/science/stage1_pt
phase() {  # $1 name, $2 processes
  echo "=== $(date +%T) $1: $2 process(es)"
  for i in $(seq 0 $(($2 - 1))); do
    timeout 65 python3 -m memrl.train +mode=B seed=$i total_frames=30000 total_episodes=null env.num_envs=16 agent.threads=1 \
      agent.n_step=3 progress=false mode.stage1.init=/work/science/stage1_pt/B_s$((i % 3)) hydra.run.dir=/tmp/share/$1_$i > /dev/null 2>&1 &
  done
  wait; nvidia-smi --query-gpu=utilization.gpu --format=csv,noheader
  for i in $(seq 0 $(($2 - 1))); do echo "$1_$i: $(grep 'stage B2' /tmp/share/$1_$i/train.log | tail -1 | cut -c 60-200)"; done
}
phase one 1
phase four 4
if nvidia-cuda-mps-control -d; then echo "MPS started"; phase four_mps 4; echo quit | nvidia-cuda-mps-control; else echo "MPS did not start"; fi
cd /tmp/share && tar czf "$OUT/logs.tgz" */train.log
echo "=== $(date +%T) done"
