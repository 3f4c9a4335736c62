"""Noisy sensors on the vehicle model: GNSS position, wheel speed and a yaw-rate gyro.

Each reading is truth + constant bias + Gaussian white noise. Wheel speed and gyro are read
every control period (IMU-like rate); the GNSS gives a fix every ``1 / gnss_rate`` seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from memrl.control.config import SensorConfig
from memrl.control.vehicle import VehicleState


@dataclass
class Readings:
    """What the sensors report at one control period."""

    time: float
    """[s] since the start of the episode."""
    wheel_speed: float
    """[m/s]."""
    yaw_rate: float
    """[rad/s]."""
    gnss: np.ndarray | None
    """Position fix (x, y) [m], or None when no fix falls in this period."""


class Sensors:
    """Samples :class:`Readings` from the true state with its own seeded generator."""

    def __init__(self, cfg: SensorConfig, seed: int | Sequence[int] | None = None) -> None:
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self._gnss_period = 1.0 / cfg.gnss_rate
        self._next_fix = 0.0

    def reset(self, seed: int | Sequence[int] | None = None) -> None:
        """Restart the GNSS schedule (a fix at time 0); reseed when ``seed`` is given."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self._next_fix = 0.0

    def read(self, state: VehicleState, time: float) -> Readings:
        """Readings of ``state`` at ``time`` [s]."""
        c = self.cfg
        noise = self.rng.standard_normal(4)
        gnss = None
        if time >= self._next_fix - 1e-9:
            gnss = np.array([state.x, state.y]) + np.asarray(c.gnss_bias) + c.gnss_noise * noise[2:]
            self._next_fix += self._gnss_period
        return Readings(
            time=time,
            wheel_speed=state.speed + c.wheel_speed_bias + c.wheel_speed_noise * noise[0],
            yaw_rate=state.yaw_rate + c.gyro_bias + c.gyro_noise * noise[1],
            gnss=gnss,
        )
