"""Drive reference envs and the batched engine side by side and compare every output."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from memrl.envs.batched import BatchedLaneChange, StepOut
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.reward import REWARD_NAMES

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
    components: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REWARD_NAMES, 0))
    """Per reward component: the env steps at which it was 1 (in both engines)."""


def car_states(env: LaneChangeEnv) -> np.ndarray:
    return np.array([[c.position[0], c.position[1], c.heading, c.speed, c.curvature]
                     for c in env.road.vehicles])


def compare(config: dict, seeds: list[int], steps: int,
            act: Callable[[list[LaneChangeEnv], np.random.Generator], np.ndarray],
            device: str = "cpu", state_atol: float = STATE_ATOL, auto_reset: bool = False,
            reward_atol: float = 0.0) -> Tally:
    """Run ``len(seeds)`` reference envs and one batched engine with the same seeds and
    actions for ``steps`` steps (finished episodes reset in both), asserting identical
    frames, rewards, components, flags and states within ``state_atol``. ``auto_reset``: the
    engine resets finished envs inside its step (``step(auto_reset=True)``). A config with
    ``frame_stack`` S > 1 compares the reference's gym stacks with the engine's S-frame stacks
    (at the config's ``frame_stride``) too. ``reward_atol``: rewards equal within it (0:
    exactly; shaped rewards on CUDA read states that may differ in the last bit)."""
    stacked = int(config.get("frame_stack", 1)) > 1
    refs = [LaneChangeEnv(config=config) for _ in seeds]
    for env, seed in zip(refs, seeds, strict=True):
        env.reset(seed=seed)
    engine = BatchedLaneChange(config, len(seeds), device, int(config.get("frame_stack", 4)),
                               opponents=refs[0]._opponents if len(refs) == 1 else None)
    engine.reset(seeds=seeds)
    rng = np.random.default_rng(seeds[0])
    tally = Tally()
    for env_i, env in enumerate(refs):
        first = env.observe_from(env.vehicle, env.target_lane)[0]
        assert np.array_equal(engine.newest_frame()[env_i].cpu().numpy(), first)
        assert (engine.observation()[env_i].cpu().numpy() == first).all()  # padded with the first
    for _ in range(steps):
        actions = act(refs, rng)
        tally.actions.append(actions)
        out = engine.step(torch.as_tensor(actions, device=engine.device), auto_reset=auto_reset)
        frames = engine.newest_frame().cpu().numpy()
        state = engine.state.cpu().numpy()
        present = engine.present.cpu().numpy()
        final = _final_stacks(out)
        stacks = engine.observation().cpu().numpy() if stacked else None
        assert auto_reset or not final
        done = []
        for i, env in enumerate(refs):
            obs, reward, terminated, truncated, info = env.step(int(actions[i]))
            newest = final[i][-1] if i in final else frames[i]
            assert np.array_equal(newest, obs[-1]), f"env {i} step {env.steps}: frames differ"
            if stacks is not None:
                stack = final.get(i, stacks[i])
                assert np.array_equal(stack, obs), f"env {i} step {env.steps}: stacks differ"
            _assert_outcome(out, i, reward, terminated, truncated, info, reward_atol)
            if i not in final:  # (a reset env's state is checked against the new scene below)
                expected = car_states(env)
                got = state[i][present[i]]
                assert got.shape == expected.shape
                diff = float(np.abs(got - expected).max())
                assert diff <= state_atol, f"env {i}: states differ by {diff}"
                tally.max_state_diff = max(tally.max_state_diff, diff)
            tally.steps += 1
            for name, value in info["rewards"].items():
                tally.components[name] += int(value)
            if terminated:
                lo, hi = env._lateral_extent(env.vehicle)
                tally.wall_hits += int(env._hits_wall(lo, hi))
                tally.collisions += 1
            tally.truncations += int(truncated)
            if terminated or truncated:
                tally.reached += int(info["reached_target"])
                env.reset()
                done.append(i)
        assert sorted(final) == (done if auto_reset else [])
        if done:
            if not auto_reset:
                engine.reset(done)
            tally.resets += len(done)
            _assert_new_episodes(engine, refs, done)
    return tally


def _final_stacks(out: StepOut) -> dict[int, np.ndarray]:
    """The last stacks of the episodes that ``step(auto_reset=True)`` finished, by env."""
    if out.reset_ids is None:
        return {}
    assert out.final_observation is not None
    return {i: out.final_observation[row].cpu().numpy() for row, i in enumerate(out.reset_ids.tolist())}


def _assert_new_episodes(engine: BatchedLaneChange, refs: list[LaneChangeEnv], done: list[int]) -> None:
    """The reset envs start where the reset reference envs start: frames, stacks, cars."""
    frames = engine.newest_frame().cpu().numpy()
    obs = engine.observation().cpu().numpy()
    state = engine.state.cpu().numpy()
    for i in done:
        first = refs[i].observe_from(refs[i].vehicle, refs[i].target_lane)[0]
        assert np.array_equal(frames[i], first)
        assert (obs[i] == first).all()  # the first frame repeated through the stack
        assert np.array_equal(state[i][engine.present[i].cpu().numpy()], car_states(refs[i]))


def _assert_outcome(out: StepOut, i: int, reward: float, terminated: bool, truncated: bool,
                    info: dict, reward_atol: float = 0.0) -> None:
    """Env ``i``'s reward, components and flags of the engine's step are the reference's; both
    engines name the components as :data:`memrl.envs.reward.REWARD_NAMES` does, in its order."""
    assert abs(out.reward[i].item() - reward) <= reward_atol
    assert tuple(info["rewards"]) == REWARD_NAMES and tuple(out.components) == REWARD_NAMES
    got = {name: value[i].item() for name, value in out.components.items()}
    assert got == info["rewards"], f"env {i}: reward components {got} != the reference's {info['rewards']}"
    assert bool(out.terminated[i]) == terminated and bool(out.truncated[i]) == truncated
    assert bool(out.collided[i]) == bool(info["collided"])
    assert bool(out.on_target_lane[i]) == bool(info["on_target_lane"])
    assert bool(out.reached_target[i]) == bool(info["reached_target"])


def random_actions(p_random: float) -> Callable[[list[LaneChangeEnv], np.random.Generator], np.ndarray]:
    """Uniform random actions with probability ``p_random``, else 'keep' (4)."""

    def act(envs: list[LaneChangeEnv], rng: np.random.Generator) -> np.ndarray:
        return np.where(rng.random(len(envs)) < p_random, rng.integers(9, size=len(envs)), 4)

    return act
