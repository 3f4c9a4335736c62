"""Controllers of the other cars (``opponent`` key of the env config).

A controller drives a group of cars with the same 9 actions as the agent, deciding for all of
its cars at once (one batched call per step), so that a controller backed by a neural network
(a later issue: cars driven by earlier checkpoints) runs one forward pass per step.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from memrl.envs.config import OpponentConfig
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


def make_opponents(cfg: OpponentConfig) -> Opponents:
    """Controllers for ``constant``, ``learned`` or ``mixed`` traffic (loads the pool once)."""
    kinds, _ = controller_mix(cfg)
    controllers: list[CarController] = []
    for kind in kinds:
        if kind == "constant":
            controllers.append(ConstantSpeedController())
        else:
            controllers.append(_entry_point(LEARNED_CONTROLLER)(cfg.pool, epsilon=cfg.epsilon))
    return Opponents(controllers)


LEARNED_CONTROLLER = "memrl.modules.opponents:LearnedCarController"
"""Entry point of the learned cars' controller (as gymnasium registers envs): it lives with the
networks in ``memrl.modules``, which build on this package, so it is found by name, not imported."""


def _entry_point(name: str) -> Any:
    module, attr = name.split(":")
    return getattr(importlib.import_module(module), attr)
