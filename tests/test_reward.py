"""The reward's components are named and written once (:mod:`memrl.envs.reward`): the config's
weights, the reference env, the batched engine and its gymnasium face all use those names, and
the engines agree on every component."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from memrl.envs import ENV_ID
from memrl.envs.batched import BatchedLaneChange
from memrl.envs.config import LaneChangeConfig, RewardConfig
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.reward import REWARD_NAMES, AgentState, components, weighted_sum
from memrl.envs.vehicles import ACTIONS
from tests.batched_helpers import compare

ROOT = Path(__file__).resolve().parents[1] / "memrl"
WEIGHTS = {"collision": -7.5, "lane_centre": 0.25, "stopped": -3.0, "target_lane": 1.5,
           "non_target_lane": -0.5}
"""Weights other than Table II's: each component weighs differently in the sum."""
BRAKE = ACTIONS.index((-1, 0))


def test_the_config_and_every_engine_name_the_components_as_the_module_does():
    assert tuple(f.name for f in dataclasses.fields(RewardConfig)) == REWARD_NAMES  # the weights' keys
    env = LaneChangeEnv()
    env.reset(seed=0)
    assert tuple(env.step(4)[4]["rewards"]) == REWARD_NAMES
    engine = BatchedLaneChange({}, 3)
    engine.reset(seeds=[0, 1, 2])
    assert tuple(engine.step(torch.full((3,), 4)).components) == REWARD_NAMES
    assert tuple(engine.info()["rewards"]) == REWARD_NAMES
    vec = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point")
    vec.reset(seed=0)
    rewards = vec.step(np.full(2, 4))[4]["rewards"]
    assert tuple(rewards) == REWARD_NAMES + tuple(f"_{name}" for name in REWARD_NAMES)


def _name_collections(tree: ast.AST) -> list[int]:
    """Lines of the tuples, lists, sets and dicts of ``tree`` holding two or more component
    names as string literals (a second list of the names, or of formulas by name)."""
    lines = []
    for node in ast.walk(tree):
        items = node.keys if isinstance(node, ast.Dict) else getattr(node, "elts", None) \
            if isinstance(node, ast.Tuple | ast.List | ast.Set) else None
        if items is None:
            continue
        names = [k.value for k in items if isinstance(k, ast.Constant) and k.value in REWARD_NAMES]
        if len(names) >= 2:
            lines.append(node.lineno)
    return lines


def test_no_other_module_lists_the_component_names():
    """A component added to or dropped from one place would drift from the other engine: only
    :mod:`memrl.envs.reward` lists the names (the config's fields are checked above)."""
    written = {str(path.relative_to(ROOT)): lines for path in sorted(ROOT.rglob("*.py"))
               if (lines := _name_collections(ast.parse(path.read_text())))}
    assert written == {"envs/reward.py": written.get("envs/reward.py")} and written["envs/reward.py"]


def test_a_reward_of_missing_extra_or_reordered_components_is_refused():
    values = dict.fromkeys(REWARD_NAMES, 1.0)
    assert weighted_sum(values, RewardConfig()) == sum(getattr(RewardConfig(), n) for n in REWARD_NAMES)
    missing = {k: v for k, v in values.items() if k != "stopped"}
    for bad in (missing, {**values, "speeding": 1.0}, dict(reversed(values.items()))):
        with pytest.raises(KeyError, match="reward components"):
            weighted_sum(bad, RewardConfig())


def test_one_formula_gives_the_same_bits_on_scalars_numpy_arrays_and_torch_tensors():
    cfg = LaneChangeConfig(reward=RewardConfig(**WEIGHTS))
    rng, n, w = np.random.default_rng(0), 400, cfg.lane_width
    lane = rng.integers(0, cfg.lanes_count, n)
    tol = cfg.lane_centre_tolerance  # offsets at the tolerance's edges, and anywhere in the lane
    offset = np.where(rng.random(n) < 0.5, rng.choice([0.0, tol, -tol], n), rng.uniform(-0.5, 0.5, n) * w)
    y = lane * w + offset
    speed = rng.choice([0.0, cfg.stopped_speed, 0.06, 7.0], n)
    arrays = {"crashed": rng.random(n) < 0.3, "y": y, "speed": speed, "lane": lane.astype(np.float64),
              "target_lane": rng.integers(0, cfg.lanes_count, n)}
    on_numpy = components(AgentState(**arrays), cfg)
    on_torch = components(AgentState(**{k: torch.as_tensor(v) for k, v in arrays.items()}), cfg)
    as_float = {name: v.astype(np.float64) for name, v in on_numpy.items()}
    numpy_sum = weighted_sum(as_float, cfg.reward)
    torch_sum = weighted_sum({name: v.to(torch.float64) for name, v in on_torch.items()}, cfg.reward)
    assert numpy_sum.dtype == np.float64 and torch_sum.dtype == torch.float64
    assert np.array_equal(torch_sum.numpy(), numpy_sum)
    for name in REWARD_NAMES:
        assert on_numpy[name].dtype == np.bool_ and on_torch[name].dtype == torch.bool, name
        assert np.array_equal(on_torch[name].numpy(), on_numpy[name]), name
        assert 0 < on_numpy[name].sum() < n, name  # both values of every component drawn
    for i in range(n):  # the reference env's scalars: Python numbers
        one = AgentState(bool(arrays["crashed"][i]), float(y[i]), float(speed[i]), int(lane[i]),
                         int(arrays["target_lane"][i]))
        values = {name: float(v) for name, v in components(one, cfg).items()}
        assert values == {name: as_float[name][i] for name in REWARD_NAMES}
        assert weighted_sum(values, cfg.reward) == numpy_sum[i]  # the same bits


def _random_or_braking(envs: list[LaneChangeEnv], rng: np.random.Generator) -> np.ndarray:
    """Uniform random actions, half the envs braking one step in two (to a stop, at times)."""
    brake = (np.arange(len(envs)) % 2 == 0) & (rng.random(len(envs)) < 0.5)
    return np.where(brake, BRAKE, rng.integers(9, size=len(envs)))


def test_the_engines_agree_on_every_named_component_over_a_random_rollout_with_collisions():
    """16 seeds x 200 steps of random driving and braking, with weights other than Table II's:
    every component takes both values, every step's components and reward are the reference's
    (``tests.batched_helpers.compare`` asserts them, by the module's names)."""
    tally = compare({"initial_lane": "non_goal", "vehicles_count": [0, 5], "reward": WEIGHTS},
                    list(range(700, 716)), 200, _random_or_braking)
    assert tally.collisions > 0 and tally.resets > 16
    assert tuple(tally.components) == REWARD_NAMES
    for name, steps in tally.components.items():
        assert 0 < steps < tally.steps, name
