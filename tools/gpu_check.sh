#!/usr/bin/env bash
# One GPU-machine check (run by the device tool from the repo root, .wheels carried; see
# docs/performance.md): install the wheels the image lacks, the CUDA tests, the batched-engine
# and end-to-end benchmarks on CUDA, then the engine's own tests on a CUDA-default machine.
# Everything it prints goes to $OUT/log.txt; benchmark JSON to $OUT/{batched,e2e,seeds,group}/bench.json.
set -u
OUT=${OUT:-/tmp/gpu_check}; mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 SDL_VIDEODRIVER=dummy PYTHONDONTWRITEBYTECODE=1
step() { echo "=== $(date +%T) $*"; }
want() { [[ " ${STEPS:-cuda batched e2e seeds group suite} " == *" $1 "* ]]; }  # STEPS="cuda e2e": a subset
step install
python3 -m pip install -q --no-index --no-deps .wheels/*.whl || exit 1
python3 -m pip install -q --no-deps --no-build-isolation --ignore-requires-python -e . || exit 1
python3 -c "import sys, torch, torchrl, tensordict, memrl.envs; print(sys.version.split()[0], torch.__version__, torchrl.__version__, tensordict.__version__, torch.cuda.get_device_name()); import torchrl._torchrl as t; print('torchrl C++ extension loaded')" 2>&1 | tail -3
nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
want cuda && { step cuda tests
# every test with cuda in its name (the CUDA-only ones, and the no-CUDA message checks, skipped there)
timeout "${T_CUDA:-300}" python3 -m pytest -q -p no:cacheprovider -rs -k cuda tests; }
want batched && { step bench batched on cuda
timeout "${T_BATCHED:-90}" python3 -m memrl.bench batched batched.device=cuda batched.seconds=2 batched.path_time=0 batched.reference_steps=500 \
  batched.threads=4 hydra.run.dir="$OUT/batched"; }
want e2e && { step bench e2e on cuda, eager and captured update
# (e2e.gpu_update_modes: the eager step and the CUDA-graph one, agent.update_mode=captured)
timeout "${T_E2E:-240}" python3 -m memrl.bench e2e e2e.device=cuda "e2e.gpu_num_envs=[16,256]" \
  "e2e.gpu_batch_sizes=[32,256]" e2e.gpu_total_frames="${E2E_FRAMES:-6000}" e2e.learner_seconds=3 \
  "e2e.num_envs=[16]" "e2e.overlap=[true]" hydra.run.dir="$OUT/e2e"; }
want seeds && { step bench seeds on cuda: K separate updates vs K networks stacked with vmap
timeout "${T_SEEDS:-90}" python3 -m memrl.bench seeds seeds.device=cuda "seeds.seeds=[1,5,16]" seeds.seconds=2 \
  hydra.run.dir="$OUT/seeds"; }
want group && { step bench group on cuda: 5 seeds in one process, an engine each and one shared, vs 5 processes
timeout "${T_GROUP:-150}" python3 -m memrl.bench group group.seeds=5 group.frames="${GROUP_FRAMES:-1500}" group.rounds=1 \
  "group.overrides=['env.num_envs=16','eval.every=0','logger=none','progress=false','checkpoint_every=1000','device=cuda']" \
  hydra.run.dir="$OUT/group"; }
rm -rf "$OUT/batched/.hydra" "$OUT/e2e/.hydra" "$OUT/seeds/.hydra" "$OUT/group/.hydra"
want suite && { step engine tests, device auto = cuda
timeout "${T_SUITE:-80}" python3 -m pytest -q -p no:cacheprovider -n 8 tests/test_batched.py \
  tests/test_batched_state.py tests/test_engine_runner.py tests/test_frame_store.py tests/test_train_batched.py; }
step done
