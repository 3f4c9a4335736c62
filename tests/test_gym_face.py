"""What gym users get: the paper's stacked observation, a trained policy in three lines, and an
env that changes no global state."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from memrl.checkpoint import load_policy, save_qnet
from memrl.data.demos import env_config_hash
from memrl.envs import ENV_ID
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.torchrl_env import make_env
from memrl.modules.qnet import QNetwork


def test_frame_stack_4_gives_the_stack_of_the_single_frames_step_by_step():
    """The stacked observation is the last 4 single-frame observations, first frame repeated
    after a reset: what the evaluation runner's FrameStack builds, which tests/test_evaluate.py
    checks against the TorchRL pipeline's CatFrames."""
    from memrl.evaluation.runner import FrameStack

    config = {"vehicles_count": [0, 5]}
    stacked = gym.make(ENV_ID, config={**config, "frame_stack": 4})
    single = gym.make(ENV_ID, config=config)
    assert stacked.observation_space.shape == (4, 84, 84) and stacked.observation_space.dtype == np.uint8
    rng = np.random.default_rng(0)
    for seed in (3, 4):
        obs, _ = stacked.reset(seed=seed)
        stack = FrameStack(4)
        expected = stack.reset(single.reset(seed=seed)[0])
        assert np.array_equal(obs, expected) and (obs == obs[:1]).all()
        for _ in range(60):
            action = int(rng.integers(9)) if rng.random() < 0.3 else 4
            obs, _, terminated, truncated, _ = stacked.step(action)
            frame, *_ = single.step(action)
            assert np.array_equal(obs, stack.push(frame))
            if terminated or truncated:
                break
    check_env(gym.make(ENV_ID, config={"frame_stack": 4}).unwrapped, skip_render_check=True)


def test_the_torchrl_pipeline_stacks_single_frames_whatever_the_env_config_says():
    td = make_env({"frame_stack": 4}, seed=0).reset()
    assert td["pixels"].shape == (4, 84, 84)  # CatFrames over single frames, not 16 channels
    td = make_env({"frame_stack": 4}, num_envs=2, seed=0).reset()
    assert td["pixels"].shape == (2, 4, 84, 84)


def test_default_observation_is_still_one_frame_and_the_stack_is_checked():
    assert gym.make(ENV_ID).observation_space.shape == (1, 84, 84)
    from memrl.envs.config import EnvConfigError

    with pytest.raises(EnvConfigError, match="frame_stack"):
        LaneChangeEnv(config={"frame_stack": 0})


def test_frame_stack_leaves_the_demo_hash_alone_at_one():
    assert env_config_hash({"frame_stack": 1}) == env_config_hash({})
    assert env_config_hash({"frame_stack": 4}) != env_config_hash({})


def test_a_trained_policy_drives_the_gym_env_in_three_lines(tmp_path):
    torch.manual_seed(0)
    net = QNetwork()
    save_qnet(tmp_path / "checkpoints" / "final.pt", net, {})
    # the README's three lines
    env = gym.make(ENV_ID, config={"frame_stack": 4})
    policy = load_policy(str(tmp_path))
    obs, _ = env.reset(seed=0)
    for _ in range(20):
        action = policy.act(obs)
        with torch.no_grad():
            assert action == int(net(torch.as_tensor(obs)).argmax(-1))
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    with pytest.raises(ValueError, match=r"shape \(4, 84, 84\).*frame_stack"):
        policy.act(gym.make(ENV_ID).reset(seed=0)[0])  # a single frame


def test_vector_env_with_frame_stack_equals_sync_vector_env():
    config = {"frame_stack": 4, "vehicles_count": 3}
    ref = gym.vector.SyncVectorEnv([lambda: LaneChangeEnv(config=config) for _ in range(3)])
    vec = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", config=config)
    assert vec.single_observation_space == ref.single_observation_space
    a, _ = ref.reset(seed=5)
    b, _ = vec.reset(seed=5)
    assert np.array_equal(a, b)
    rng = np.random.default_rng(1)
    for _ in range(60):
        actions = rng.integers(9, size=3)
        x, y = ref.step(actions), vec.step(actions)
        for u, w in zip(x[:4], y[:4], strict=True):
            assert np.array_equal(u, w)


def test_importing_and_creating_the_env_changes_no_global_state():
    """No multiprocessing start method set, no torchrl imported (it sets one on import)."""
    code = (
        "import multiprocessing as mp, sys, gymnasium as gym\n"
        "import memrl.envs\n"
        "env = gym.make('memrl/LaneChange-v0', config={'frame_stack': 4}); env.reset(seed=0); env.step(4)\n"
        "vec = gym.make_vec('memrl/LaneChange-v0', num_envs=2, vectorization_mode='vector_entry_point')\n"
        "vec.reset(seed=0); vec.step([4, 4])\n"
        "print(mp.get_start_method(allow_none=True), 'torchrl' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["None", "False"]
