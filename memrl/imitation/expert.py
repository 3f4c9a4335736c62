"""The scripted driver as an expert on call for the batched engine's states.

:class:`~memrl.modules.scripted.ScriptedDriver` reads a :class:`LaneChangeEnv` (the world
state, privileged). :class:`ExpertLabeler` copies each env's cars from a
:class:`~memrl.envs.batched.BatchedLaneChange` into one reference env (the engine's slot
order is the reference's ``road.vehicles`` order), and asks that env's own driver (it keeps
state across an episode: its home lane, whether a lane change is under way) what it would do.
Nothing is rendered: the labels cost a fraction of a step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from memrl.envs.batched import BatchedLaneChange
from memrl.envs.config import env_config_dict
from memrl.envs.lane_change import LaneChangeEnv
from memrl.modules.policy import DrivingPolicy


def sync(mirror: LaneChangeEnv, engine: BatchedLaneChange, i: int, state: np.ndarray, present: np.ndarray,
         target: int) -> None:
    """Make ``mirror``'s road env ``i``'s cars of ``state [C, 5]`` (slots ``present``)."""
    mirror.remove_others()
    mirror.target_lane = target
    x, y, heading, speed, curvature = (float(v) for v in state[0])
    mirror.place_agent(x, y, speed, heading=heading, curvature=curvature)
    for row in state[1:][present[1:]]:
        car = mirror.add_car(float(row[0]), float(row[1]), float(row[3]), heading=float(row[2]))
        car.curvature = float(row[4])
    mirror.steps = int(engine.steps[i])


class ExpertLabeler:
    """The expert's action in every env of an engine, one driver per env.

    Args:
        engine: the batched engine whose states are labelled.
        make_driver: a fresh expert (e.g. the scripted driver of ``demos.policy``).
    """

    def __init__(self, engine: BatchedLaneChange, make_driver: Callable[[], DrivingPolicy]) -> None:
        env_values: dict[str, Any] = {**env_config_dict(engine.cfg), "vehicles_count": 0}
        env_values.pop("opponent")  # the expert reads states; who drives the others is moot here
        self.mirror = LaneChangeEnv(config=env_values)
        self.mirror.reset(seed=0)
        self.engine = engine
        self.drivers = [make_driver() for _ in range(engine.num_envs)]
        self.fresh = np.ones(engine.num_envs, dtype=bool)
        """Envs whose episode starts at the next labelling (the driver is reset there)."""

    def new_episodes(self, ids: list[int]) -> None:
        """Envs ``ids`` start new episodes: their drivers are reset at the next :meth:`labels`."""
        self.fresh[ids] = True

    def labels(self) -> np.ndarray:
        """The expert's action ``[N]`` (int64) in every env's current state."""
        e = self.engine
        state, present = e.state.cpu().numpy(), e.present.cpu().numpy()
        target = e.target_lane.cpu().numpy()
        out = np.empty(e.num_envs, dtype=np.int64)
        for i, driver in enumerate(self.drivers):
            sync(self.mirror, e, i, state[i], present[i], int(target[i]))
            if self.fresh[i]:
                driver.reset(self.mirror)
                self.fresh[i] = False
            out[i] = int(driver.act(self.mirror, None))  # type: ignore[arg-type]
        return out
