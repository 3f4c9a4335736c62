"""The env config is checked for meaning in one place (``memrl.envs.config``), for every face:
the gym env, the batched engine, the vector env, ``make_env`` and the train entry point."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from memrl.envs.config import (
    EnvConfigError,
    LaneChangeConfig,
    max_cars_room,
    min_road_length,
    validate_env_config,
)
from memrl.errors import one_line

BAD = [
    ({"lane_width": math.inf}, "lane_width"),
    ({"lane_width": math.nan}, "lane_width"),
    ({"reward": {"collision": math.nan}}, "reward.collision"),
    ({"reward": {"target_lane": -math.inf}}, "reward.target_lane"),
    ({"dt": math.inf}, "dt"),
    ({"other_speed": [5.0, math.inf]}, "other_speed"),
    ({"opponent": {"epsilon": math.nan}}, "opponent.epsilon"),
    ({"bev": {"lateral_scale": math.nan}}, "bev.lateral_scale"),
    ({"initial_speed": [20.0, 30.0]}, "initial_speed"),
    ({"initial_speed": [6.0, 16.0]}, "initial_speed"),
    ({"spawn_gap": -1.0}, "spawn_gap"),
    ({"spawn_gap": -4.5}, "spawn_gap"),
    ({"vehicles_count": [0, 1000]}, "vehicles_count"),
    ({"vehicles_count": 7}, "vehicles_count"),
    ({"road_length": 10.0}, "road_length"),
]


@pytest.mark.parametrize(("values", "key"), BAD, ids=[repr(v) for v, _ in BAD])
def test_meaningless_values_are_refused_naming_the_key(values, key):
    with pytest.raises(EnvConfigError) as info:
        validate_env_config(values)
    message = one_line(info.value)
    assert f"env config '{key}'" in message and "\n" not in message


def test_the_same_check_guards_every_face():
    from memrl.envs.batched import BatchedLaneChange
    from memrl.envs.lane_change import LaneChangeEnv
    from memrl.envs.torchrl_env import make_env

    bad = {"lane_width": math.inf}
    for build in (lambda: LaneChangeEnv(config=bad), lambda: BatchedLaneChange(bad, 2, "cpu"),
                  lambda: make_env(bad, num_envs=2), lambda: make_env(bad),
                  lambda: gym.make("memrl/LaneChange-v0", config=bad),
                  lambda: gym.make_vec("memrl/LaneChange-v0", num_envs=2,
                                       vectorization_mode="vector_entry_point", config=bad)):
        with pytest.raises(EnvConfigError, match="'lane_width'"):
            build()


def test_vehicles_count_refusal_says_the_most_the_road_holds():
    room = max_cars_room(LaneChangeConfig())
    assert room == 6  # 90 m window, 13 m spacing: 4 per free lane, 2 beside the agent
    with pytest.raises(EnvConfigError, match=f"at most {room} other cars"):
        validate_env_config({"vehicles_count": [0, 1000]})
    validate_env_config({"vehicles_count": [0, room]})
    validate_env_config({"vehicles_count": 12, "spawn_ahead": 200.0})  # a longer window holds more


def test_as_many_cars_as_allowed_are_always_placed_without_overlap():
    from memrl.envs.scene import sample_scene

    room = max_cars_room(LaneChangeConfig())
    cfg = validate_env_config({"vehicles_count": room})
    for seed in range(200):
        scene = sample_scene(cfg, np.random.default_rng(seed))
        cars = scene.others
        assert len(cars) == room, seed
        xs = np.concatenate([cars[:, 0], [scene.agent[0]]])
        ys = np.concatenate([cars[:, 1], [scene.agent[1]]])
        for i in range(len(xs)):
            for j in range(i + 1, len(xs)):
                assert not (ys[i] == ys[j] and abs(xs[i] - xs[j]) < cfg.vehicle_length), seed


def test_the_road_must_hold_the_episode():
    cfg = LaneChangeConfig()
    need = min_road_length(cfg)
    assert need == 500 + 15 * 0.1 * 300 + 5  # the agent at its speed limit for 300 steps
    with pytest.raises(EnvConfigError, match=f"need >= {need:.0f} m"):
        validate_env_config({"road_length": need - 1})
    validate_env_config({"road_length": need})


def test_the_defaults_pass():
    assert validate_env_config({}) == LaneChangeConfig()


def test_vector_env_refuses_step_before_reset_as_gymnasium_does():
    from gymnasium.error import ResetNeeded

    vec = gym.make_vec("memrl/LaneChange-v0", num_envs=2, vectorization_mode="vector_entry_point")
    with pytest.raises(ResetNeeded):
        vec.step(np.zeros(2, dtype=np.int64))
    vec.reset(seed=0)
    vec.step(np.zeros(2, dtype=np.int64))
