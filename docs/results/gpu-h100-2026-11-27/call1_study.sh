#!/bin/bash
# issue 30 screen on the GPU machine: B's stage 2 (30k env steps, n = 3) from the drawn-path stage 1s
# of pt_B (section 21), four variants x 3 seeds. $@: extra study args. FRAMES / VARIANTS / SEEDS for dry runs.
PY=${PY:-python3}
F=${FRAMES:-30000}
V=${VARIANTS:-"{base:[],lr4:['agent.lr=6.25e-5'],rr2:['agent.updates_per_round=2'],tgt2k:['agent.target_update_interval=2000']}"}
$PY -m memrl.study study.name=gpu_B2 study.dir=${SDIR:-/work/science/studies/gpu_B2} study.progress=false 'study.modes=[B]' "study.seeds=${SEEDS:-[0,1,2]}" 'study.baselines=[]' "study.train_overrides=[\"total_frames=$F\",\"total_episodes=null\",\"env.num_envs=16\",\"agent.threads=1\",\"agent.n_step=3\",\"mode.stage1.init='/work/science/stage1_pt/B_s\\\${seed}'\"]" "study.variants=$V" "$@"
