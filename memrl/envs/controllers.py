"""Controllers of the other cars (``opponent`` key of the env config).

A controller drives a group of cars with the same 9 actions as the agent, deciding for all of
its cars at once (one batched call per step), so that a controller backed by a neural network
(cars driven by earlier checkpoints) runs one forward pass per step.

Each kind of controller is made by a factory in :data:`CONTROLLERS`. This package makes the
``constant`` cars; a kind that needs more than the simulator is registered by the package that
has it (:func:`register_controller`): ``learned`` cars drive with the networks of past runs and
come with :mod:`memrl.checkpoint` (registered when it is imported, as every memrl command
does), so that the env never imports upwards.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from memrl.envs.config import EnvConfigError, OpponentConfig
from memrl.envs.scene import controller_mix
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
    """The controllers of the other cars, one per kind (``constant``, ``learned``), in the
    order of :func:`memrl.envs.scene.controller_mix`; which car gets which is drawn by the
    scene sampler."""

    controllers: list[CarController]

    def of_kind(self, kind: str) -> CarController:
        return next(c for c in self.controllers if c.kind == kind)

    @property
    def pool_size(self) -> int:
        """Networks a learned car can draw from (1 when there are no learned cars)."""
        learned = [c for c in self.controllers if c.kind == "learned"]
        return len(learned[0].networks) if learned else 1  # type: ignore[attr-defined]


ControllerFactory = Callable[[OpponentConfig], CarController]
"""Makes the controller of one kind of car from the env's ``opponent`` config."""

CONTROLLERS: dict[str, ControllerFactory] = {"constant": lambda cfg: ConstantSpeedController()}
"""The factory of each kind of controller (:func:`memrl.envs.scene.controller_mix` names the
kinds of an episode); ``learned``: registered by :mod:`memrl.checkpoint.opponents`."""


def register_controller(kind: str, factory: ControllerFactory) -> None:
    """Make the cars of ``kind`` with ``factory`` (called by the package that has them)."""
    CONTROLLERS[kind] = factory


def make_opponents(cfg: OpponentConfig) -> Opponents:
    """Controllers for ``constant``, ``learned`` or ``mixed`` traffic (loads the pool once)."""
    kinds, _ = controller_mix(cfg)
    missing = [kind for kind in kinds if kind not in CONTROLLERS]
    if missing:
        raise EnvConfigError(f"env config 'opponent.type': {cfg.type} traffic needs the controller of "
                             f"{' and '.join(missing)} cars, which memrl.checkpoint registers: "
                             "import memrl.checkpoint first")
    return Opponents([CONTROLLERS[kind](cfg) for kind in kinds])
