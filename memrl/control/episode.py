"""One lane-change episode with the agent's commands tracked by the deployed car.

The env keeps doing what it does in training (other cars, collisions with cars and walls,
rewards, ``reached_target``, truncation), but its agent car is a :class:`TrackedAgent`: instead
of integrating its own kinematics it jumps to the vehicle model's true state at each env step.
The policy, on the other hand, sees its *belief*: the BEV is drawn around the EKF's estimated
pose (the ego car drawn there), and a policy that reads the world state (the scripted driver)
finds the agent at the estimated pose with the commanded speed and curvature, which are the
state its actions change.

Per env step (``env.cfg.dt``): policy acts on the belief -> the action changes the commanded
speed and curvature (clamped as in the env) -> :meth:`TrackedCar.drive` runs the PID loops,
vehicle model, sensors and EKF for ``dt`` -> ``env.step`` moves the other cars, puts the agent
at the true state and checks collisions.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from torchrl.envs.transforms.functional import rgb_to_grayscale

from memrl.control.estimator import Estimate
from memrl.control.tracking import TrackedCar
from memrl.control.vehicle import VehicleModel
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import CurvatureVehicle
from memrl.modules.policy import DrivingPolicy, FrameStack


class TrackedAgent(CurvatureVehicle):
    """The env's agent car, moved to the vehicle model's state instead of by its kinematics."""

    model: VehicleModel | None = None

    def apply_action(self, action: int) -> None:
        """No-op: in deploy, actions change the PID set points (see :func:`run_episode`)."""

    def step(self, dt: float) -> None:
        """Take the vehicle model's true pose, speed and curvature (it already moved ``dt``)."""
        assert self.model is not None, "TrackedAgent needs a vehicle model"
        s = self.model.state
        self.position = np.array([s.x, s.y], dtype=np.float64)
        self.heading, self.speed, self.curvature = s.heading, s.speed, self.model.curvature
        self.on_state_update()


def install_tracked_agent(env: LaneChangeEnv, model: VehicleModel) -> TrackedAgent:
    """Replace the env's freshly reset agent car by a :class:`TrackedAgent` at the same state."""
    old = env.vehicle
    cfg = env.cfg
    agent = TrackedAgent(
        env.road, old.position.copy(), old.heading, old.speed, curvature=old.curvature,
        length=cfg.vehicle_length, width=cfg.vehicle_width, kind="agent",
        target_lane=old.target_lane,
        limits={"speed_step": cfg.speed_step, "curvature_step": cfg.curvature_step,
                "speed_limits": cfg.speed_limits, "curvature_limit": cfg.curvature_limit},
    )
    agent.model = model
    env.road.vehicles[env.road.vehicles.index(old)] = agent
    env.vehicle = agent
    return agent


@contextmanager
def believed_state(env: LaneChangeEnv, estimate: Estimate, commands: CurvatureVehicle) -> Iterator[None]:
    """Temporarily put the env's agent at the estimated pose with the commanded speed/curvature."""
    car = env.vehicle
    saved = car.position, car.heading, car.speed, car.curvature
    car.position = np.array([estimate.x, estimate.y], dtype=np.float64)
    car.heading, car.speed, car.curvature = estimate.heading, commands.speed, commands.curvature
    car.on_state_update()
    try:
        yield
    finally:
        car.position, car.heading, car.speed, car.curvature = saved
        car.on_state_update()


@dataclass
class EpisodeRecord:
    """What one deploy episode did."""

    seed: int
    target_y: float
    """Centre line of the target lane [m]."""
    start_y: float
    """Agent's initial lateral position [m]."""
    steps: int
    """Env steps taken."""
    episode_return: float
    """Sum of the env's rewards (Table II), from the true state."""
    collided: bool
    """A collision (car or wall) ended the episode."""
    reached_target: bool
    """All four corners of the true car inside the target lane at some step."""
    trace: dict[str, np.ndarray]
    """Per-control-period records (see :data:`memrl.control.tracking.TRACE_KEYS`) and ``gnss``."""
    actions: np.ndarray
    """Action index per env step."""


def gray(img: np.ndarray) -> np.ndarray:
    """``[H, W]`` grayscale of a ``[C, H, W]`` view: as drawn (C=1) or TorchRL's GrayScale (C=3)."""
    if img.shape[0] == 1:
        return img[0]
    return rgb_to_grayscale(torch.from_numpy(np.ascontiguousarray(img)))[0].numpy()


def run_episode(env: LaneChangeEnv, policy: DrivingPolicy, car: TrackedCar, seed: int,
                sensor_seed: int | Sequence[int] | None = None, frame_stack: int = 4) -> EpisodeRecord:
    """Run one episode of ``policy`` through the deployed car; see the module docstring."""
    env.reset(seed=seed)
    start = env.vehicle
    estimate = car.reset(float(start.position[0]), float(start.position[1]), float(start.heading),
                         float(start.speed), seed=sensor_seed)
    agent = install_tracked_agent(env, car.vehicle)
    commands = CurvatureVehicle(None, np.zeros(2), 0.0, agent.speed, curvature=agent.curvature,
                                limits={"speed_step": env.cfg.speed_step,
                                        "curvature_step": env.cfg.curvature_step,
                                        "speed_limits": env.cfg.speed_limits,
                                        "curvature_limit": env.cfg.curvature_limit})
    stack = FrameStack(frame_stack, env.cfg.frame_stride)  # the TorchRL pipeline's stack
    actions: list[int] = []
    episode_return, collided, steps = 0.0, False, 0
    with believed_state(env, estimate, commands):
        policy.reset(env)
    while True:
        with believed_state(env, estimate, commands):
            frame = gray(env.observe_from(env.vehicle, env.target_lane))
            pixels = stack.reset(frame[None]) if stack.frames is None else stack.push(frame[None])
            action = int(policy.act(env, pixels))
        commands.apply_action(action)
        estimate = car.drive(commands.speed, commands.curvature, env.cfg.dt)
        _, reward, terminated, truncated, info = env.step(action)
        actions.append(action)
        episode_return += float(reward)
        steps += 1
        collided = collided or bool(info["collided"])
        if terminated or truncated:
            break
    return EpisodeRecord(
        seed=seed, target_y=env.target_lane * env.cfg.lane_width, start_y=float(start.position[1]),
        steps=steps, episode_return=episode_return, collided=collided,
        reached_target=bool(env.reached_target), trace=car.trace.arrays(),
        actions=np.asarray(actions, dtype=np.int64),
    )
