"""The scene sampler: one episode's start drawn from a seeded generator.

Shared by the highway-env reference env (:class:`memrl.envs.lane_change.LaneChangeEnv`) and
the batched engine (:mod:`memrl.envs.batched`): env ``i`` of the engine reset with seed ``s``
starts from exactly the scene that ``gym.make("memrl/LaneChange-v0").reset(seed=s)`` starts
from, because both call :func:`sample_scene` with the same generator state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from memrl.envs.config import AGENT_X, LaneChangeConfig, OpponentConfig  # noqa: F401 (AGENT_X re-exported)

STATE = ("x", "y", "heading", "speed", "curvature")
"""Columns of a car's state row: position [m], heading [rad], speed [m/s], curvature [rad/m]."""


@dataclass
class Scene:
    """The start of one episode.

    Attributes:
        target_lane: the agent's target lane.
        agent: ``[5]`` state row of the agent (see :data:`STATE`).
        others: ``[K, 5]`` state rows of the other cars (lane by lane, rear to front).
        learned: ``[K]`` bool, car driven by a past agent (else constant speed).
        car_target: ``[K]`` target lane of each learned car (-1 for constant cars).
        policy: ``[K]`` index into the opponent pool of each learned car (0 for constant cars).
    """

    target_lane: int
    agent: np.ndarray
    others: np.ndarray
    learned: np.ndarray
    car_target: np.ndarray
    policy: np.ndarray


def controller_mix(opponent: OpponentConfig) -> tuple[list[str], list[float]]:
    """The kinds of car controllers of an episode and the chance of each car to get each."""
    if opponent.type == "constant":
        return ["constant"], [1.0]
    if opponent.type == "learned":
        return ["learned"], [1.0]
    p = float(opponent.learned_fraction)
    return ["constant", "learned"], [1.0 - p, p]


def sample_scene(cfg: LaneChangeConfig, rng: np.random.Generator, pool_size: int = 1) -> Scene:
    """Draw a scene: target lane, agent start, other cars, and who drives each car.

    Args:
        cfg: the env config.
        rng: the episode's generator (the env's ``np_random``); the order of the draws is
            part of the contract (seeds reproduce episodes across versions).
        pool_size: networks in the learned cars' pool (each learned car draws one).
    """
    n = cfg.lanes_count
    target = int(rng.integers(n)) if cfg.target_lane == "random" else int(cfg.target_lane)
    others = [lane for lane in range(n) if lane != target]
    start_on_target = cfg.initial_lane == "random" and rng.random() < 0.5
    # others[integers(len)] is exactly Generator.choice(others) (the same draw), without its overhead
    lane = target if start_on_target else others[int(rng.integers(len(others)))]
    low, high = cfg.initial_speed
    agent = np.array([AGENT_X, lane * cfg.lane_width, 0.0, float(rng.uniform(low, high)), 0.0])
    # Drawn only when enabled, so the episodes of a seed stay the same without them.
    if cfg.initial_offset > 0:
        agent[1] += float(rng.uniform(-cfg.initial_offset, cfg.initial_offset))
    if cfg.initial_heading > 0:
        agent[2] = float(rng.uniform(-cfg.initial_heading, cfg.initial_heading))
    if cfg.initial_curvature > 0:
        agent[4] = float(rng.uniform(-cfg.initial_curvature, cfg.initial_curvature))
    cars = _spawn_others(cfg, rng, lane)
    kinds, weights = controller_mix(cfg.opponent)
    if len(kinds) == 1:
        learned = np.full(len(cars), kinds[0] == "learned")
    else:
        learned = np.array([kinds[i] == "learned" for i in rng.choice(len(kinds), size=len(cars), p=weights)],
                           dtype=bool)
    car_target = np.full(len(cars), -1, dtype=np.int64)
    policy = np.zeros(len(cars), dtype=np.int64)
    for i in np.flatnonzero(learned):
        car_target[i] = int(rng.integers(n))
        policy[i] = int(rng.integers(pool_size))
    return Scene(target, agent, cars.reshape(-1, len(STATE)), learned.reshape(-1), car_target, policy)


def _spawn_others(cfg: LaneChangeConfig, rng: np.random.Generator, agent_lane: int) -> np.ndarray:
    """Straight cars in all lanes, ahead and behind the agent, with no initial overlap.

    Within a lane, speeds are sorted so that no car is faster than the one ahead of it:
    straight constant-speed cars then never run into each other.
    """
    count = cfg.vehicles_count
    if isinstance(count, list | tuple):
        count = int(rng.integers(count[0], count[1] + 1))
    integers, uniform = rng.integers, rng.uniform  # called per attempt: looked up once
    lanes, x0 = cfg.lanes_count, AGENT_X
    low, high = x0 - cfg.spawn_behind, x0 + cfg.spawn_ahead
    min_gap = cfg.vehicle_length + cfg.spawn_gap
    agent_gap = cfg.vehicle_length + 2 * cfg.spawn_gap
    by_lane: list[list[float]] = [[] for _ in range(lanes)]
    placed = 0
    for _ in range(count):
        for _ in range(cfg.spawn_attempts):
            lane = int(integers(lanes))
            x = float(uniform(low, high))
            if lane == agent_lane and abs(x - x0) < agent_gap:
                continue
            taken = by_lane[lane]
            for px in taken:  # a plain loop: cheaper than any() over a generator
                if abs(x - px) < min_gap:
                    break
            else:
                taken.append(x)
                placed += 1
                break
    low, high = cfg.other_speed
    speeds = rng.uniform(low, high, size=placed).tolist()
    rows = np.zeros((placed, len(STATE)))
    row = 0
    for lane, xs in enumerate(by_lane):
        xs.sort()
        rows[row: row + len(xs), 0] = xs
        rows[row: row + len(xs), 1] = lane * cfg.lane_width
        rows[row: row + len(xs), 3] = sorted(speeds[row: row + len(xs)])
        row += len(xs)
    return rows


def max_cars(cfg: LaneChangeConfig) -> int:
    """The most other cars a scene of this config can hold."""
    count = cfg.vehicles_count
    return int(count[1]) if isinstance(count, list | tuple) else int(count)
