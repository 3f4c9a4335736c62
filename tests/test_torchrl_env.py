"""The TorchRL pipeline built by ``make_env``."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from memrl.envs.config import EnvConfigError
from memrl.envs.torchrl_env import make_env


def test_check_env_specs_and_keys():
    env = make_env(seed=0)
    check_env_specs(env)
    td = env.rollout(5)
    assert td["pixels"].shape == (5, 4, 84, 84) and td["pixels"].dtype == torch.uint8
    assert td["action"].dtype == torch.int64 and td["action"].shape == (5,)
    for key in ("collided", "on_target_lane", "reached_target", "step_count", "episode_reward"):
        assert ("next", key) in td.keys(True)


def test_frames_stack_oldest_first_and_pad_with_the_first_frame():
    env = make_env(seed=3)
    td = env.rollout(40, break_when_any_done=False)
    first = td["pixels"][0]
    assert all(torch.equal(first[i], first[0]) for i in range(4))  # reset: 4 copies
    px, nxt = td["pixels"], td["next", "pixels"]
    live = ~td["next", "done"].squeeze(-1)
    # after a step, the stack shifts by one: next[:3] == current[1:]
    assert torch.equal(nxt[live][:, :3], px[live][:, 1:])
    # frames change over time (the scene moves)
    assert not torch.equal(px[0, -1], px[-1, -1])


def test_counters_and_flags():
    env = make_env(seed=0)
    td = env.rollout(30, break_when_any_done=True)
    steps = td["next", "step_count"].squeeze(-1)
    assert torch.equal(steps, torch.arange(1, len(steps) + 1))
    assert torch.allclose(td["next", "episode_reward"].squeeze(-1),
                          td["next", "reward"].squeeze(-1).cumsum(0))
    # collisions are exactly the terminations
    assert torch.equal(td["next", "collided"], td["next", "terminated"].squeeze(-1))


def test_rgb_env_through_torchrl_grayscale_gives_the_same_pixels():
    gray = make_env({"bev": {"grayscale": True}}, seed=5).rollout(25, break_when_any_done=False)
    rgb = make_env({"bev": {"grayscale": False}}, seed=5)
    torch.manual_seed(0)
    actions = gray["action"]
    td = rgb.reset()
    for t in range(25):
        assert torch.equal(td["pixels"], gray["pixels"][t])
        td["action"] = actions[t]
        td = rgb.step_and_maybe_reset(td)[1]


def test_bad_env_config_fails_before_building():
    with pytest.raises(EnvConfigError, match="initial_lane"):
        make_env({"initial_lane": "left"})


def test_hydra_env_group_rejects_a_misspelt_key(compose_cfg):
    cfg = compose_cfg("preview", ["env.lanes_count=3"])
    assert cfg.env.lanes_count == 3
    env = make_env(cfg.env, seed=0)
    assert env.reset()["pixels"].shape == (4, 84, 84)
    with pytest.raises(Exception, match="lane_cont"):
        compose_cfg("preview", ["env.lane_cont=3"])


def test_a_dict_holding_hydra_nodes_is_accepted(compose_cfg):
    cfg = compose_cfg("preview")
    env = make_env({**dict(cfg.env), "vehicles_count": [0, 5]}, seed=0)
    assert env.reset()["pixels"].shape == (4, 84, 84)
