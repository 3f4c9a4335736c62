"""Cars driven by speed and curvature commands (Sec. IV-A of the paper).

Each of the 9 discrete actions adds a speed change and a curvature change to the car's current
speed and curvature; the heading rate is speed x curvature.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from memrl.envs.config import LaneChangeConfig
from memrl.errors import UserError

SPEED_CHANGES = (-1, 0, +1)
"""Multiples of ``speed_step`` [m/s]: slower, keep, faster."""
CURVATURE_CHANGES = (-1, 0, +1)
"""Multiples of ``curvature_step`` [rad/m]: left (negative y), keep, right (positive y)."""
ACTIONS: tuple[tuple[int, int], ...] = tuple(
    (ds, dk) for ds in SPEED_CHANGES for dk in CURVATURE_CHANGES
)
"""Action index -> (speed sign, curvature sign); index = 3 * speed_index + curvature_index."""
N_ACTIONS = len(ACTIONS)
IDLE = ACTIONS.index((0, 0))
"""The action that keeps speed and curvature (index 4)."""
_ENV = LaneChangeConfig()
ACTION_LIMITS: dict[str, Any] = {"speed_step": _ENV.speed_step, "curvature_step": _ENV.curvature_step,
                                 "speed_limits": tuple(_ENV.speed_limits),
                                 "curvature_limit": _ENV.curvature_limit}
"""A car's action steps and limits when none are given: the env config's defaults."""


class InvalidActionError(UserError, ValueError):
    """An action that is not one of the 9 action indices."""


def validate_action(action: Any) -> int:
    """The action as a Python int, if it is an integer index in 0..8.

    Accepts Python and numpy integers, and one-element integer numpy arrays and torch tensors;
    refuses bools, floats, strings and out-of-range values (no silent cast or wrap-around).

    Raises:
        InvalidActionError: naming the action and the valid range.
    """
    value: int | None = None
    if isinstance(action, bool | np.bool_):
        value = None
    elif isinstance(action, numbers.Integral):  # int, numpy integer scalars
        value = int(action)
    elif hasattr(action, "dtype") and hasattr(action, "shape"):  # numpy arrays, torch tensors
        kind = str(action.dtype).removeprefix("torch.")
        if kind.startswith(("int", "uint")) and math.prod(action.shape) == 1:
            value = int(action.item())
    if value is None or not 0 <= value < N_ACTIONS:
        raise InvalidActionError(f"action {action!r} is not valid: expected an integer in "
                                 f"0..{N_ACTIONS - 1}")
    return value


def action_index(speed_sign: int, curvature_sign: int) -> int:
    """Index of the action with the given signs, each in {-1, 0, +1}."""
    return ACTIONS.index((speed_sign, curvature_sign))


class CurvatureVehicle(Vehicle):
    """A highway-env vehicle integrated with unicycle kinematics driven by curvature.

    State: position [m], heading [rad], speed [m/s], curvature [rad/m]. One :meth:`step` of ``dt``
    moves the car along its heading and turns it by ``speed * curvature * dt``.
    """

    position: np.ndarray
    heading: float
    speed: float

    def __init__(
        self,
        road: Road,
        position: np.ndarray,
        heading: float = 0.0,
        speed: float = 0.0,
        *,
        curvature: float = 0.0,
        length: float = 5.0,
        width: float = 2.0,
        kind: str = "constant",
        target_lane: int | None = None,
        limits: dict[str, Any] | None = None,
    ) -> None:
        self.LENGTH, self.WIDTH = float(length), float(width)  # per-instance, read by polygon()
        super().__init__(road, position, heading, speed)
        self.curvature = float(curvature)
        self.kind = kind
        """Who drives the car ('agent', 'constant', 'learned', ...): picks its shade in the BEV."""
        self.target_lane = target_lane
        self.controller: Any = None
        """The :class:`~memrl.envs.controllers.CarController` driving this car (None: the agent)."""
        self.policy_index = 0
        """Learned cars: which network of the opponent pool drives this car this episode."""
        self.frames: np.ndarray | None = None
        """Learned cars: the car's own stack of BEV frames."""
        lim = {**ACTION_LIMITS, **(limits or {})}
        self.speed_step = float(lim["speed_step"])
        self.curvature_step = float(lim["curvature_step"])
        self.speed_limits = tuple(lim["speed_limits"])
        self.curvature_limit = float(lim["curvature_limit"])

    def apply_action(self, action: int) -> None:
        """Add the speed and curvature changes of one of the 9 actions, then clamp both."""
        ds, dk = ACTIONS[int(action)]
        low, high = self.speed_limits
        self.speed = min(max(self.speed + ds * self.speed_step, low), high)
        # Round away float drift so that e.g. 0.3 - 3 * 0.1 stops exactly at 0.
        self.speed = round(self.speed, 9)
        self.curvature = round(
            min(max(self.curvature + dk * self.curvature_step, -self.curvature_limit),
                self.curvature_limit),
            9,
        )

    def act(self, action: Any = None) -> None:
        """Actions are applied by :meth:`apply_action`; highway-env's per-frame ``act`` is a no-op."""

    def step(self, dt: float) -> None:
        """Integrate one step: exact arc for constant speed and curvature."""
        distance = self.speed * dt
        turn = self.curvature * distance
        if abs(turn) < 1e-9:
            self.position = self.position + distance * np.array(
                [np.cos(self.heading), np.sin(self.heading)]
            )
        else:
            radius = 1.0 / self.curvature
            new_heading = self.heading + turn
            self.position = self.position + radius * np.array(
                [np.sin(new_heading) - np.sin(self.heading), np.cos(self.heading) - np.cos(new_heading)]
            )
            self.heading = new_heading
        self.on_state_update()

    def on_state_update(self) -> None:
        """Lanes are straight and parallel: the lane index follows from the lateral position."""
        # Hand-written: highway-env's nearest-lane search loops over all lanes every frame.
        if self.road is not None:
            net = self.road.network
            lanes = net.graph["0"]["1"]
            width = lanes[0].width
            idx = int(np.clip(np.floor(self.position[1] / width + 0.5), 0, len(lanes) - 1))
            self.lane_index = ("0", "1", idx)
            self.lane = lanes[idx]
