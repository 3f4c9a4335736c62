"""Training on a CUDA device (skipped where CUDA is absent)."""

from __future__ import annotations

import pytest
import torch

from memrl.dqn.loop import Trainer
from memrl.train import train
from tests.helpers import TINY

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
