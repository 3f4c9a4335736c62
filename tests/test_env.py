"""The lane-change env: registration, kinematics, reward terms, termination, seeding, spawning."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from memrl.envs import ENV_ID, register_envs
from memrl.envs.config import EnvConfigError
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import IDLE, action_index
from tests.helpers import empty_road

W = 4.0  # default lane width [m]


def test_gymnasium_check_env_and_idempotent_registration():
    register_envs()
    register_envs()
    env = gym.make(ENV_ID, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=1)
    assert obs.shape == (1, 84, 84) and obs.dtype == np.uint8
    assert env.action_space.n == 9


def test_actions_change_speed_and_curvature_by_paper_steps_and_clamp():
    env = empty_road()
    env.place_agent(500.0, W, speed=1.0)
    car = env.vehicle
    car.apply_action(action_index(+1, 0))
    assert car.speed == pytest.approx(1.1) and car.curvature == 0.0
    car.apply_action(action_index(-1, +1))
    assert car.speed == pytest.approx(1.0) and car.curvature == pytest.approx(0.01)
    for _ in range(20):
        car.apply_action(action_index(0, +1))
    assert car.curvature == pytest.approx(0.05)  # clamp curvature_limit
    for _ in range(20):
        car.apply_action(action_index(-1, 0))
    assert car.speed == 0.0  # clamp at the lower speed limit, exactly


def test_heading_rate_is_speed_times_curvature():
    env = empty_road(vehicles_count=0)
    env.place_agent(500.0, W, speed=5.0, curvature=0.01)
    for _ in range(10):
        env.vehicle.step(0.1)
    # 10 steps of 0.1 s at 5 m/s: 5 m of arc, heading 0.05 rad, on a circle of radius 100 m
    assert env.vehicle.heading == pytest.approx(0.05)
    assert env.vehicle.position[0] == pytest.approx(500.0 + 100.0 * np.sin(0.05))
    assert env.vehicle.position[1] == pytest.approx(W + 100.0 * (1 - np.cos(0.05)))


def step_components(env: LaneChangeEnv, action: int = IDLE):
    _, reward, terminated, truncated, info = env.step(action)
    return reward, terminated, info


@pytest.mark.parametrize(
    ("y", "speed", "expected", "components"),
    [
        (W, 5.0, 2.0, {"lane_centre": 1, "target_lane": 1}),            # centred, target lane
        (0.0, 5.0, -1.0, {"lane_centre": 1, "non_target_lane": 1}),     # centred, other lane
        (W + 1.0, 5.0, 1.0, {"target_lane": 1}),                        # 1 m off centre
        (0.5, 5.0, -2.0, {"non_target_lane": 1}),                       # beyond the 0.3 m tolerance
        (W, 0.0, 1.0, {"lane_centre": 1, "stopped": 1, "target_lane": 1}),  # stopped
    ],
)
def test_reward_terms_of_hand_made_situations(y, speed, expected, components):
    env = empty_road()
    env.place_agent(500.0, y, speed=speed)
    reward, terminated, info = step_components(env)
    full = {"collision": 0, "lane_centre": 0, "stopped": 0, "target_lane": 0, "non_target_lane": 0}
    full.update(components)
    assert info["rewards"] == full
    assert reward == pytest.approx(expected)
    assert not terminated and not info["collided"]


def test_reward_weights_come_from_config():
    env = empty_road(reward={"lane_centre": 0.5, "target_lane": 3.0})
    env.place_agent(500.0, W, speed=5.0)
    reward, _, _ = step_components(env)
    assert reward == pytest.approx(3.5)


def test_collision_with_a_car_terminates_with_minus_five():
    env = empty_road()
    env.place_agent(500.0, W, speed=5.0)
    env.add_car(505.5, W, speed=0.0)  # 0.5 m gap; the agent covers 0.5 m in one step... and more
    env.vehicle.speed = 8.0
    reward, terminated, info = step_components(env)
    assert terminated and info["collided"]
    assert info["rewards"]["collision"] == 1
    assert reward == pytest.approx(-5 + 1 + 1)  # collision + centred + target lane


def test_no_collision_one_step_before_contact():
    env = empty_road()
    env.place_agent(500.0, W, speed=5.0)
    env.add_car(506.0, W, speed=0.0)  # 1 m gap, agent moves 0.5 m
    _, terminated, info = step_components(env)
    assert not terminated and not info["collided"]


@pytest.mark.parametrize(("y", "hits"), [(-2.0 + 1.05, False), (-2.0 + 0.95, True),
                                         (6.0 - 1.05, False), (6.0 - 0.95, True)])
def test_road_edges_are_walls(y, hits):
    # car width 2 m: the body reaches 1 m either side of its centre; edges at -2 m and 6 m
    env = empty_road()
    env.place_agent(500.0, y, speed=1.0)
    reward, terminated, info = step_components(env)
    assert terminated == hits and info["collided"] == hits
    assert info["rewards"]["collision"] == float(hits)


def test_truncated_after_300_steps_on_an_empty_road():
    env = empty_road(vehicles_count=0)
    env.place_agent(500.0, W, speed=5.0)
    for step in range(1, 301):
        _, reward, terminated, truncated, _ = env.step(IDLE)
        assert not terminated
        assert truncated == (step == 300)
        assert reward == pytest.approx(2.0)


def test_reached_target_needs_the_whole_body_in_the_target_lane():
    env = empty_road()
    env.place_agent(500.0, 0.0, speed=5.0)
    assert not env.reached_target
    env.place_agent(500.0, W - 1.5, speed=5.0)  # centre in target lane, body over the line
    *_, info = env.step(IDLE)
    assert info["on_target_lane"] and not info["reached_target"]
    env.place_agent(500.0, W - 0.5, speed=5.0)
    *_, info = env.step(IDLE)
    assert info["reached_target"]
    env.place_agent(500.0, 0.0, speed=5.0)
    env.reached_target = True  # sticky within the episode
    *_, info = env.step(IDLE)
    assert info["reached_target"] and not info["on_target_lane"]


def scene_signature(env: LaneChangeEnv) -> list[tuple]:
    return [(round(c.position[0], 9), round(c.position[1], 9), round(c.speed, 9), c.kind)
            for c in env.road.vehicles] + [("target", env.target_lane)]


def test_reset_with_seed_reproduces_the_scene_exactly():
    env = LaneChangeEnv()
    obs_a, _ = env.reset(seed=123)
    sig_a = scene_signature(env)
    traj_a = [env.step(a)[0] for a in [0, 4, 8, 2, 6] * 6]
    env.reset(seed=7)
    assert scene_signature(env) != sig_a
    obs_b, _ = env.reset(seed=123)
    assert scene_signature(env) == sig_a and np.array_equal(obs_a, obs_b)
    traj_b = [env.step(a)[0] for a in [0, 4, 8, 2, 6] * 6]
    assert all(np.array_equal(a, b) for a, b in zip(traj_a, traj_b, strict=True))


def test_initial_lane_modes():
    lanes_non_goal = []
    on_target = []
    for seed in range(60):
        env = LaneChangeEnv(config={"initial_lane": "non_goal"})
        env.reset(seed=seed)
        lanes_non_goal.append(env.current_lane() != env.target_lane)
        env = LaneChangeEnv(config={"initial_lane": "random"})
        env.reset(seed=seed)
        on_target.append(env.current_lane() == env.target_lane)
    assert all(lanes_non_goal)
    assert 15 <= sum(on_target) <= 45  # about half of 60


def test_initial_pose_perturbation_stays_in_its_bounds_and_is_off_by_default():
    poses = []
    for seed in range(30):
        env = LaneChangeEnv()
        env.reset(seed=seed)
        car = env.vehicle
        assert car.heading == 0.0 and car.curvature == 0.0
        assert car.position[1] == env.current_lane() * 4.0
        env = LaneChangeEnv(config={"initial_offset": 0.8, "initial_heading": 0.2,
                                    "initial_curvature": 0.03})
        env.reset(seed=seed)
        car = env.vehicle
        offset = car.position[1] - env.current_lane() * 4.0
        poses.append((offset, car.heading, car.curvature))
    offsets, headings, curvatures = np.array(poses).T
    assert np.abs(offsets).max() <= 0.8 and np.abs(headings).max() <= 0.2
    assert np.abs(curvatures).max() <= 0.03
    # drawn, not fixed: both signs and a spread
    for values, bound in ((offsets, 0.8), (headings, 0.2), (curvatures, 0.03)):
        assert values.min() < -0.3 * bound and values.max() > 0.3 * bound


def test_spawned_cars_do_not_overlap_and_count_follows_range():
    counts = set()
    for seed in range(40):
        env = LaneChangeEnv(config={"vehicles_count": [0, 5]})
        env.reset(seed=seed)
        counts.add(len(env.others))
        cars = env.road.vehicles
        for i, a in enumerate(cars):
            for b in cars[i + 1:]:
                if a.lane_index == b.lane_index:
                    assert abs(a.position[0] - b.position[0]) >= 5.0 + 8.0 - 1e-9
        # constant cars in a lane: the one behind is never faster, so they never meet
        for lane in range(2):
            lane_cars = sorted((c for c in env.others if c.lane_index[2] == lane),
                               key=lambda c: c.position[0])
            speeds = [c.speed for c in lane_cars]
            assert speeds == sorted(speeds)
    assert counts == {0, 1, 2, 3, 4, 5}


def test_five_cars_by_default_in_both_lanes():
    lanes = set()
    for seed in range(10):
        env = LaneChangeEnv()
        env.reset(seed=seed)
        assert len(env.others) == 5
        lanes |= {c.lane_index[2] for c in env.others}
        assert all(c.kind == "constant" for c in env.others)
    assert lanes == {0, 1}


@pytest.mark.parametrize(
    ("config", "key"),
    [
        ({"initial_lane": "left"}, "initial_lane"),
        ({"target_lane": 2}, "target_lane"),
        ({"vehicles_count": [3, 1]}, "vehicles_count"),
        ({"lane_widht": 4.0}, "lane_widht"),
        ({"bev": {"width": 2}}, "bev.width"),
        ({"reward": {"colision": -5}}, "reward.colision"),
        ({"opponent": "nobody"}, "opponent"),
        ({"initial_heading": 0.6}, "initial_heading"),
        ({"initial_offset": 1.5}, "initial_offset"),
        ({"bev": {"path_time": -1.0}}, "bev.path_time"),
        ({"bev": {"path_length": 20.0, "path_time": 2.0}}, "bev.path_length,bev.path_time"),
    ],
)
def test_bad_config_names_the_key(config, key):
    with pytest.raises((EnvConfigError, ValueError), match=key.replace(".", r"\.")):
        env = LaneChangeEnv(config=config)
        env.reset(seed=0)


def test_info_flags_and_components_are_present():
    env = LaneChangeEnv()
    _, info = env.reset(seed=0)
    for key in ("collided", "on_target_lane", "reached_target", "rewards"):
        assert key in info
    assert set(info["rewards"]) == {"collision", "lane_centre", "stopped", "target_lane",
                                    "non_target_lane"}
