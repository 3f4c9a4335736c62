"""The task's reward (Table II of the paper): its components, each named and written once.

Both engines reward through this module: the reference env
(:class:`memrl.envs.lane_change.LaneChangeEnv`, on Python scalars: highway-env's ``_rewards``
dict) and the batched engine (:class:`memrl.envs.batched.BatchedLaneChange`, on ``[N]`` numpy
arrays or torch tensors). A component is a formula of named quantities of the agent's state
after a step (:class:`AgentState`); it gives a truth value (a bool, or a bool array / tensor,
elementwise), counted as 0 or 1. The reward is the components weighted by
``config['reward'][name]`` (:class:`memrl.envs.config.RewardConfig`, whose fields are
:data:`REWARD_NAMES`) and summed in that order.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from memrl.envs.config import LaneChangeConfig, RewardConfig


@dataclass(slots=True)
class AgentState:
    """What the components read of the agent, each a scalar or ``[N]`` (numpy or torch)."""

    crashed: Any
    """Whether it has hit another car or a road edge (bool)."""
    y: Any
    """Lateral position of its centre [m] (lane i is centred at y = i * lane_width)."""
    speed: Any
    """Speed [m/s]."""
    lane: Any
    """Lane holding its centre (a number)."""
    target_lane: Any
    """The episode's target lane (a number)."""


_FORMULAS: dict[str, Callable[[AgentState, LaneChangeConfig], Any]] = {
    "collision": lambda s, cfg: s.crashed,
    "lane_centre": lambda s, cfg: abs(s.y - s.lane * cfg.lane_width) <= cfg.lane_centre_tolerance,
    "stopped": lambda s, cfg: s.speed <= cfg.stopped_speed,
    "target_lane": lambda s, cfg: s.lane == s.target_lane,
    "non_target_lane": lambda s, cfg: s.lane != s.target_lane,
}
# (each formula works elementwise on Python scalars, numpy arrays and torch tensors alike; the
# config's docstrings of RewardConfig say in words what each one rewards)

REWARD_NAMES: tuple[str, ...] = tuple(_FORMULAS)
"""The components' names, in the order the reward sums them (``info['rewards']``'s keys)."""


def components(state: AgentState, cfg: LaneChangeConfig) -> dict[str, Any]:
    """Every component of ``state`` by name (truth values, shaped as ``state``'s quantities)."""
    return {name: formula(state, cfg) for name, formula in _FORMULAS.items()}


def weighted_sum(values: Mapping[str, Any], weights: RewardConfig) -> Any:
    """The reward: ``values`` (every component as a number, 0.0 or 1.0: floats or float64
    arrays / tensors) times its weight, summed in the order of :data:`REWARD_NAMES` from 0.0,
    so a scalar and an array element add up the same bits."""
    if tuple(values) != REWARD_NAMES:
        raise KeyError(f"reward components {tuple(values)}, expected {REWARD_NAMES}")
    reward: Any = 0.0
    for name in REWARD_NAMES:
        reward = reward + float(getattr(weights, name)) * values[name]
    return reward
