#!/bin/bash
# usage: SEEDS='[0]' ./finals.sh '[B]' [more overrides]   (the finals of table3_300k_v3, worktree at 97f898f)
. /work/main/.venv/bin/activate
export PYTHONPATH=/work/wt/finals
cd /work/wt/finals
exec python -m memrl.study study.name=table3_300k study.dir=/work/science/studies/table3_300k_v3 study.jobs=1 study.progress=false study.workers=1 "study.modes=$1" "study.seeds=${SEEDS:-[0,1,2,3,4]}" 'study.baselines=[]' 'study.train_overrides=["total_frames=300000","total_episodes=null","env.num_envs=16","agent.threads=1"]' "${@:2}"
