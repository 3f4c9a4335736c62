"""Controllers of the other cars (``opponent`` key of the env config).

A controller drives a group of cars with the same 9 actions as the agent, deciding for all of
its cars at once (one batched call per step), so that a controller backed by a neural network
(a later issue: cars driven by earlier checkpoints) runs one forward pass per step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from memrl.envs.config import OpponentConfig
from memrl.envs.vehicles import IDLE, CurvatureVehicle

if TYPE_CHECKING:
    from memrl.envs.lane_change import LaneChangeEnv


class CarController(ABC):
    """Drives the cars given to it; ``kind`` names their shade in the bird's-eye view."""

    kind: str = "constant"

    def reset(self, env: LaneChangeEnv, cars: Sequence[CurvatureVehicle]) -> None:  # noqa: B027
        """Called once per episode after the scene is built (default: nothing to prepare)."""

    @abstractmethod
    def act(self, env: LaneChangeEnv, cars: Sequence[CurvatureVehicle]) -> np.ndarray:
        """Return one action index (int64) per car, in the order of ``cars``."""


class ConstantSpeedController(CarController):
    """Straight ahead at constant speed: always the 'keep speed, keep curvature' action."""

    kind = "constant"

    def act(self, env: LaneChangeEnv, cars: Sequence[CurvatureVehicle]) -> np.ndarray:
        return np.full(len(cars), IDLE, dtype=np.int64)


@dataclass
class Opponents:
    """The controllers of an episode's other cars and the chance of each car to get each."""

    controllers: list[CarController]
    weights: list[float]

    def assign(self, rng: np.random.Generator, n: int) -> list[CarController]:
        """A controller for each of ``n`` cars (drawn with the env's generator)."""
        if len(self.controllers) == 1:
            return [self.controllers[0]] * n
        picks = rng.choice(len(self.controllers), size=n, p=self.weights)
        return [self.controllers[i] for i in picks]


def make_opponents(cfg: OpponentConfig) -> Opponents:
    """Controllers for ``constant``, ``learned`` or ``mixed`` traffic (loads the pool once)."""
    if cfg.type == "constant":
        return Opponents([ConstantSpeedController()], [1.0])
    from memrl.modules.opponents import LearnedCarController  # torch networks: load lazily

    learned = LearnedCarController(cfg.pool, epsilon=cfg.epsilon)
    if cfg.type == "learned":
        return Opponents([learned], [1.0])
    p = float(cfg.learned_fraction)
    return Opponents([ConstantSpeedController(), learned], [1.0 - p, p])
