"""Training on a CUDA device (skipped where CUDA is absent)."""

from __future__ import annotations

import json

import pytest
import torch

from memrl.dqn.loop import Trainer
from memrl.train import train
from tests.helpers import TINY

DEVICE = "cuda"  # tests of this file run only where CUDA is
pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


@pytest.mark.parametrize("num_envs", [1, 16])
def test_a_few_hundred_updates_on_cuda_then_evaluation_and_resume_on_the_cpu(
        compose_cfg, tmp_path, num_envs):
    extra = ["device=cuda", f"env.num_envs={num_envs}", "total_episodes=null",
             "total_frames=1300", "agent.warmup_frames=100", "buffer.capacity=2000",
             "checkpoint_every=5"]
    cfg = compose_cfg("train", TINY + extra)
    summary = train(cfg, tmp_path / "run")
    assert summary.device.startswith("cuda") and summary.updates >= 300
    trainer = Trainer(cfg, tmp_path / "again")
    assert next(trainer.learner.qnet.parameters()).is_cuda
    trainer.resume(tmp_path / "run")
    batch = trainer.stage.buffer.sample()
    assert batch["pixels"].is_cuda and batch["pixels"].dtype == torch.uint8
    from memrl.checkpoint import load_qnet

    net, _ = load_qnet(tmp_path / "run")  # saved on CUDA, loads on the CPU
    assert not next(net.parameters()).is_cuda
    cpu_cfg = compose_cfg("train", TINY + extra + ["device=cpu", "total_frames=1400",
                                                   f"resume={tmp_path / 'run'}"])
    resumed = train(cpu_cfg)
    assert resumed.frames >= 1400 and resumed.device == "cpu"


def test_sigterm_stops_training_on_cuda_and_the_printed_command_finishes_it(tmp_path):
    """A second GPU call (2026-11-27) saw a CUDA training process outlive its `timeout 65` by
    minutes; on the CPU the same run stops within seconds. A stop that never comes fails here."""
    import shlex
    import signal
    import subprocess
    import sys

    from tests.test_signals import ROOT, environ, run_folder, start, wait_for_episodes

    args = ["+experiment=smoke", "total_frames=1500", "progress=false", f"device={DEVICE}",
            "env.num_envs=16"]
    proc = start(["memrl.train", *args], tmp_path)
    try:
        wait_for_episodes(tmp_path, proc, 5)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    last = [ln for ln in err.splitlines() if ln.strip()][-1]
    assert last.startswith("interrupted by SIGTERM: ") and "resume with: " in last, err
    run = run_folder(tmp_path)
    assert (run / "checkpoints" / "last" / "COMPLETE").is_file()
    command = shlex.split(last.split("resume with: ", 1)[1])
    again = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, env=environ(tmp_path),
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert (run / "checkpoints" / "final.pt").is_file()
    assert json.loads((run / "summary.json").read_text())["frames"] >= 1500
