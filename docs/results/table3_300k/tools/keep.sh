#!/bin/bash
# usage: ./keep.sh B_constant_s0   (copy a finished finals run and its stage-1 eval into the repo)
set -e
cd /work/science/studies/table3_300k_v3/runs
tar --exclude=checkpoints/last --exclude=train.lock -cf - "$1" | tar -xf - -C /work/main/docs/results/table3_300k/runs
if [ -d ../stage1/"$1" ]; then mkdir -p /work/main/docs/results/table3_300k/stage1 && cp -r ../stage1/"$1" /work/main/docs/results/table3_300k/stage1/; fi
du -sh /work/main/docs/results/table3_300k/runs/"$1"
