"""Controllers of the other cars.

A controller drives a group of cars with the same 9 actions as the agent, deciding for all of
its cars at once (one batched call per step), so that a controller backed by a neural network
(a later issue: cars driven by earlier checkpoints) runs one forward pass per step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

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


CONTROLLERS: dict[str, Callable[[], CarController]] = {"constant": ConstantSpeedController}
"""Registry of controllers the env can build by name (``opponent`` key of the env config)."""


def register_controller(name: str, factory: Callable[[], CarController]) -> None:
    """Make ``factory`` available as ``opponent=<name>`` (idempotent for the same factory)."""
    if CONTROLLERS.get(name, factory) is not factory:
        raise ValueError(f"controller name {name!r} is already registered")
    CONTROLLERS[name] = factory


def make_controller(name: str) -> CarController:
    """Build a registered controller, with a clear error for an unknown name."""
    try:
        return CONTROLLERS[name]()
    except KeyError:
        raise ValueError(
            f"env config 'opponent': unknown controller {name!r}; known: {sorted(CONTROLLERS)}"
        ) from None
