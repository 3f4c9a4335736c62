#!/bin/bash
set -e
cd /work/science/studies/mixed_100k_v3/runs
tar --exclude=checkpoints/last --exclude=train.lock -cf - "$1" | tar -xf - -C /work/main/docs/results/mixed_100k/runs
if [ -d ../stage1/"$1" ]; then cp -r ../stage1/"$1" /work/main/docs/results/mixed_100k/stage1/; fi
du -sh /work/main/docs/results/mixed_100k/runs/"$1"
