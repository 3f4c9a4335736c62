"""Kill-and-resume with n-step windows (and strided stacks) stays exact on 4 envs."""

from __future__ import annotations

import pytest

from memrl.checkpoint import resume as ckpt
from memrl.train import train
from tests.helpers import (
    TINY,
    assert_same_final_weights_and_agent_buffers,
    csv_rows,
    tiny_mode,
    train_killed_after,
)


def _kill_and_resume(compose_cfg, tmp_path, demos, monkeypatch, extra):
    cfg = compose_cfg("train", TINY + extra)
    full = train(cfg, tmp_path / "full", demos=demos)
    train_killed_after(monkeypatch, cfg, tmp_path / "cut", demos, episodes=8)  # mid-episode of the others
    state = ckpt.load_state(tmp_path / "cut" / "checkpoints" / "last")
    assert 3 <= state["counters"]["episodes"] < 8 and bool(state["collector"]["engine"]["steps"].any())
    resumed = train(compose_cfg("train", TINY + extra + [f"resume={tmp_path / 'cut'}"]), demos=demos)
    for key in ("frames", "episodes", "updates", "stage"):
        assert getattr(resumed, key) == getattr(full, key), key
    assert csv_rows(tmp_path / "cut" / "episodes.csv") == csv_rows(tmp_path / "full" / "episodes.csv")
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")


BASE = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3", "agent.n_step=3"]


@pytest.mark.parametrize("mode", [None, "A", "B"])
def test_n_step_run_killed_and_resumed_equals_an_uninterrupted_one(
        compose_cfg, tmp_path, demos, monkeypatch, mode):
    _kill_and_resume(compose_cfg, tmp_path, demos, monkeypatch,
                     BASE + tiny_mode(mode))


def test_strided_n_step_run_killed_and_resumed_equals_an_uninterrupted_one(
        compose_cfg, tmp_path, demos, monkeypatch):
    _kill_and_resume(compose_cfg, tmp_path, demos, monkeypatch, BASE + ["env.frame_stride=3"])
