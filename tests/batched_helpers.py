"""Drive reference envs and the batched engine side by side and compare every output."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from memrl.envs.batched import REWARD_NAMES, BatchedLaneChange
from memrl.envs.lane_change import LaneChangeEnv

STATE_ATOL = 1e-9
"""[m, rad, m/s, rad/m]: both integrate the same float64 formulas; sin/cos of numpy and torch
may differ in the last bit, which 300 steps of 0.1 s cannot grow anywhere near this."""


@dataclass
class Tally:
    """What a side-by-side run saw (the equality checks assert inside :func:`compare`)."""

    steps: int = 0
    collisions: int = 0
    wall_hits: int = 0
    reached: int = 0
    truncations: int = 0
    resets: int = 0
    max_state_diff: float = 0.0
    actions: list[np.ndarray] = field(default_factory=list)


def car_states(env: LaneChangeEnv) -> np.ndarray:
    return np.array([[c.position[0], c.position[1], c.heading, c.speed, c.curvature]
                     for c in env.road.vehicles])


def compare(config: dict, seeds: list[int], steps: int,
            act: Callable[[list[LaneChangeEnv], np.random.Generator], np.ndarray],
            device: str = "cpu", state_atol: float = STATE_ATOL) -> Tally:
    """Run ``len(seeds)`` reference envs and one batched engine with the same seeds and
    actions for ``steps`` steps (finished episodes reset in both), asserting identical
    frames, rewards, components, flags and states within ``state_atol``."""
    refs = [LaneChangeEnv(config=config) for _ in seeds]
    for env, seed in zip(refs, seeds, strict=True):
        env.reset(seed=seed)
    engine = BatchedLaneChange(config, len(seeds), device,
                               opponents=refs[0]._opponents if len(refs) == 1 else None)
    engine.reset(seeds=seeds)
    rng = np.random.default_rng(seeds[0])
    tally = Tally()
    for env_i, env in enumerate(refs):
        first = env.observe_from(env.vehicle, env.target_lane)[0]
        assert np.array_equal(engine.newest_frame()[env_i].cpu().numpy(), first)
    for _ in range(steps):
        actions = act(refs, rng)
        tally.actions.append(actions)
        out = engine.step(torch.as_tensor(actions, device=engine.device))
        frames = engine.newest_frame().cpu().numpy()
        state = engine.state.cpu().numpy()
        present = engine.present.cpu().numpy()
        done = []
        for i, env in enumerate(refs):
            obs, reward, terminated, truncated, info = env.step(int(actions[i]))
            assert np.array_equal(frames[i], obs[0]), f"env {i} step {env.steps}: frames differ"
            assert out.reward[i].item() == reward
            assert out.components[i].tolist() == [bool(info["rewards"][k]) for k in REWARD_NAMES]
            assert bool(out.terminated[i]) == terminated and bool(out.truncated[i]) == truncated
            assert bool(out.collided[i]) == bool(info["collided"])
            assert bool(out.on_target_lane[i]) == bool(info["on_target_lane"])
            assert bool(out.reached_target[i]) == bool(info["reached_target"])
            expected = car_states(env)
            got = state[i][present[i]]
            assert got.shape == expected.shape
            diff = float(np.abs(got - expected).max())
            assert diff <= state_atol, f"env {i}: states differ by {diff}"
            tally.max_state_diff = max(tally.max_state_diff, diff)
            tally.steps += 1
            if terminated:
                lo, hi = env._lateral_extent(env.vehicle)
                tally.wall_hits += int(env._hits_wall(lo, hi))
                tally.collisions += 1
            tally.truncations += int(truncated)
            if terminated or truncated:
                tally.reached += int(info["reached_target"])
                env.reset()
                done.append(i)
        if done:
            engine.reset(done)
            tally.resets += len(done)
            frames = engine.newest_frame().cpu().numpy()
            for i in done:
                first = refs[i].observe_from(refs[i].vehicle, refs[i].target_lane)[0]
                assert np.array_equal(frames[i], first)
    return tally


def random_actions(p_random: float) -> Callable[[list[LaneChangeEnv], np.random.Generator], np.ndarray]:
    """Uniform random actions with probability ``p_random``, else 'keep' (4)."""

    def act(envs: list[LaneChangeEnv], rng: np.random.Generator) -> np.ndarray:
        return np.where(rng.random(len(envs)) < p_random, rng.integers(9, size=len(envs)), 4)

    return act
