#!/bin/bash
# One device call: install, the CUDA tests (foreground) beside the stage-2 screen (12 runs, background),
# stop the study once every run has trained (evaluation happens on the CPU machine), pack the runs.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 SDL_VIDEODRIVER=dummy PYTHONDONTWRITEBYTECODE=1
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
step() { echo "=== $(date +%T) +$(el)s $*"; }
step install
python3 -m pip install -q --no-index --no-deps .wheels/*.whl || exit 1
python3 -m pip install -q --no-deps --no-build-isolation --ignore-requires-python -e . || exit 1
python3 -c "import sys, torch, torchrl, tensordict, memrl.envs; print(sys.version.split()[0], torch.__version__, torchrl.__version__, tensordict.__version__, torch.cuda.get_device_name())"
nproc; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
mkdir -p /work/science && cp -r .gpu/stage1 /work/science/stage1_pt
D=/work/science/studies/gpu_B2
step screen start
setsid .gpu/study.sh study.jobs=12 study.workers=16 > "$OUT/study.log" 2>&1 < /dev/null &
SPID=$!
step cuda tests
timeout "${T_CUDA:-200}" python3 -m pytest -q -p no:cacheprovider tests/test_train_cuda.py tests/test_batched_cuda.py \
  tests/test_frame_store_cuda.py "tests/test_batched_state.py::test_a_state_saved_on_cuda_loads_on_cpu" \
  "tests/test_engine_runner.py::test_engine_on_cuda_gives_the_gym_runner_records" \
  "tests/test_frame_ring_stride.py::test_strided_n_step_buffer_on_cuda_equals_the_cpu_one" 2>&1 | tail -25
step waiting for the screen
while [ "$(ls $D/runs/*/summary.json 2>/dev/null | wc -l)" -lt 12 ] && [ "$(el)" -lt "${DEADLINE:-470}" ]; do
  sleep 10; echo "+$(el)s: $(ls $D/runs/*/summary.json 2>/dev/null | wc -l) runs done; $(grep -h 'stage B2' $D/runs/*/train.log 2>/dev/null | tail -1 | cut -c1-160)"
done
sleep 3; kill -TERM -- -"$SPID" 2>/dev/null; sleep 5; kill -KILL -- -"$SPID" 2>/dev/null
step pack
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
cd "$D" && ls runs
runs=(runs/*)
tar czf "$OUT/runs_a.tgz" --exclude='checkpoints/last' --exclude='checkpoints/stage1.pt' study.json "${runs[@]:0:6}"
tar czf "$OUT/runs_b.tgz" --exclude='checkpoints/last' --exclude='checkpoints/stage1.pt' "${runs[@]:6}"
ls -la "$OUT"; step done
