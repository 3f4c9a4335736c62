"""``memrl.deploy``: episodes through PID, vehicle model and EKF on the real composed config."""

from __future__ import annotations

import importlib.util
import json

import cv2
import numpy as np
import pytest

from memrl.control.config import DeployConfigError
from memrl.control.episode import TrackedAgent, run_episode
from memrl.control.tracking import TrackedCar
from memrl.deploy import deploy, deploy_config
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import IDLE
from memrl.modules.policy import DrivingPolicy


def test_scripted_driver_changes_lanes_without_collision_and_bounded_overshoot(compose_cfg, tmp_path):
    cfg = compose_cfg("deploy", ["deploy.episodes=2"])
    assert cfg.deploy.policy == "scripted" and cfg.env.initial_lane == "non_goal"
    summary = deploy(cfg, tmp_path)
    m = summary.metrics
    assert m["lane_change_episodes"] == 2 and m["collisions"] == 0
    assert m["lane_change_success_rate"] == 1.0
    assert m["overshoot_max"] < 0.5  # m past the target lane centre
    assert m["final_offset_abs_mean"] < 0.3  # m: it settles on the target lane centre
    assert m["speed_tracking_rms"] < 0.5 and m["curvature_tracking_rms"] < 0.015
    assert m["sim_collisions"] == 0 and m["sim_success_rate"] == 1.0  # the plain simulator
    for q in ("position", "lateral", "speed", "yaw_rate", "curvature"):
        assert m[f"{q}_est_rms"] < 0.7 * m[f"{q}_raw_rms"], q
    data = json.loads(summary.json.read_text())
    assert data["metrics"]["collisions"] == 0 and len(data["episodes"]) == 2
    png = cv2.imread(str(summary.png))
    assert png is not None and png.std() > 10


class _Spy(DrivingPolicy):
    """Keeps the lane (IDLE) and records what it sees of the agent at each step."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, float, float]] = []

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        assert pixels.shape == (4, 84, 84) and pixels.dtype == np.uint8
        car = env.vehicle
        self.seen.append((float(car.position[0]), float(car.position[1]), float(car.speed)))
        return IDLE


def test_policy_sees_the_estimate_while_the_env_holds_the_true_state(compose_cfg):
    dcfg = deploy_config(compose_cfg("deploy").deploy)
    env = LaneChangeEnv(config={"vehicles_count": 0, "initial_lane": "non_goal", "duration": 30})
    car, spy = TrackedCar(dcfg), _Spy()
    rec = run_episode(env, spy, car, seed=0, sensor_seed=[0, 0])
    assert isinstance(env.vehicle, TrackedAgent) and rec.steps == 30
    # the env's agent ends at the vehicle model's true pose ...
    s = car.vehicle.state
    assert tuple(env.vehicle.position) == (s.x, s.y) and env.vehicle.speed == s.speed
    # ... while the policy was shown the estimate (every 10th control period ends a step)
    est_x, est_y = rec.trace["est_x"][9::10], rec.trace["est_y"][9::10]
    seen = np.array(spy.seen[1:])
    np.testing.assert_allclose(seen[:, 0], est_x[:-1])
    np.testing.assert_allclose(seen[:, 1], est_y[:-1])
    assert np.abs(seen[:, 1] - rec.trace["y"][9::10][:-1]).max() > 1e-3  # not the truth
    assert np.all(seen[:, 2] == rec.trace["cmd_speed"][0])  # commanded speed, IDLE keeps it


class _IntoParkedCar(DrivingPolicy):
    """Parks a car 20 m ahead in the agent's lane, then keeps driving straight."""

    def reset(self, env: LaneChangeEnv) -> None:
        env.add_car(env.vehicle.position[0] + 20.0, env.vehicle.position[1], speed=0.0)

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        return IDLE


def test_collisions_are_detected_by_the_env_on_the_true_pose(compose_cfg):
    dcfg = deploy_config(compose_cfg("deploy").deploy)
    env = LaneChangeEnv(config={"vehicles_count": 0, "initial_lane": "non_goal"})
    rec = run_episode(env, _IntoParkedCar(), TrackedCar(dcfg), seed=1)
    assert rec.collided and not rec.reached_target
    assert rec.steps < 40  # ~15 m of free road at 6-9 m/s, then terminated


def test_bad_values_name_their_key(compose_cfg):
    with pytest.raises(DeployConfigError, match="vehicle.mass"):
        deploy_config(compose_cfg("deploy", ["deploy.vehicle.mass=-1"]).deploy)
    with pytest.raises(DeployConfigError, match="policy"):
        deploy_config(compose_cfg("deploy", ["deploy.policy=human"]).deploy)
    with pytest.raises(DeployConfigError, match="checkpoint"):
        deploy_config(compose_cfg("deploy", ["deploy.policy=checkpoint"]).deploy)
    with pytest.raises(Exception, match="mas"):
        compose_cfg("deploy", ["deploy.vehicle.mas=1"])  # misspelt key: the schema rejects it


@pytest.mark.skipif(importlib.util.find_spec("memrl.checkpoint") is not None,
                    reason="memrl.checkpoint exists: the training module is installed")
def test_checkpoint_policy_without_training_module_fails_clearly(compose_cfg, tmp_path):
    cfg = compose_cfg("deploy", ["deploy.policy=checkpoint", "deploy.checkpoint=nowhere.pt"])
    with pytest.raises(RuntimeError, match="training module"):
        deploy(cfg, tmp_path)


@pytest.mark.slow
def test_scripted_driver_default_deploy_run(compose_cfg, tmp_path):
    """The default 20 episodes (0-5 other cars): every lane change succeeds, as in the simulator."""
    m = deploy(compose_cfg("deploy"), tmp_path).metrics
    assert m["episodes"] == 20 and m["collisions"] == 0 and m["lane_change_success_rate"] == 1.0
    assert m["overshoot_max"] < 0.5 and m["sim_success_rate"] == 1.0
