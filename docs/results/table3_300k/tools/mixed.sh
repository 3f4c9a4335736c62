#!/bin/bash
# usage: SEEDS='[1,2]' ./mixed.sh '[B]' [more overrides]   (mixed_100k_v3; WT default /work/wt/mixed)
. /work/main/.venv/bin/activate
WT=${WT:-/work/wt/mixed}
export PYTHONPATH=$WT
cd $WT
F=/work/science/studies/table3_300k_v3/runs
exec python -m memrl.study study.name=mixed_100k study.dir=/work/science/studies/mixed_100k_v3 study.jobs=1 study.progress=false study.workers=1 "study.modes=$1" "study.seeds=${SEEDS:-[0,1,2]}" 'study.opponents=[mixed]' "study.train_overrides=[\"total_frames=100000\",\"total_episodes=null\",\"env.num_envs=16\",\"agent.threads=1\",\"env.opponent.pool=[$F/Default_constant_s0,$F/Default_constant_s1,$F/Default_constant_s2]\"]" "${@:2}"
