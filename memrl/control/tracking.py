"""The deployed car: two PID loops on the filter's estimate driving the vehicle model.

Every control period (``1 / control_rate`` s): speed PID (set point: the agent's commanded
speed) -> accelerator force; curvature PID (set point: the commanded curvature) -> steering
rate; the vehicle model moves; the sensors read the new state; the EKF predicts and fuses.
Everything is recorded in a :class:`Trace` for the metrics and the plot.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from memrl.control.config import DeployConfig
from memrl.control.estimator import Estimate, StateEstimator
from memrl.control.pid import PID
from memrl.control.sensors import Readings, Sensors
from memrl.control.vehicle import VehicleModel

TRACE_KEYS = (
    "time",                                               # [s]
    "x", "y", "heading", "speed", "yaw_rate", "curvature",  # truth
    "est_x", "est_y", "est_heading", "est_speed", "est_yaw_rate", "est_curvature",
    "raw_speed", "raw_yaw_rate", "raw_curvature",         # sensor readings
    "cmd_speed", "cmd_curvature",                         # PID set points (agent's commands)
    "force_demand", "steer_rate_demand", "force", "steer",  # actuators
)


@dataclass
class Trace:
    """Per-control-period records (``TRACE_KEYS``) plus the GNSS fixes and the truth at each."""

    rows: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in TRACE_KEYS})
    gnss: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    """(time [s], fix x, fix y, true x, true y [m]) per GNSS fix."""

    def arrays(self) -> dict[str, np.ndarray]:
        """Every record as a float array; ``gnss`` has shape ``[fixes, 5]``."""
        out = {k: np.asarray(v, dtype=np.float64) for k, v in self.rows.items()}
        out["gnss"] = np.asarray(self.gnss, dtype=np.float64).reshape(-1, 5)
        return out


class TrackedCar:
    """Vehicle model + sensors + EKF + the two PID loops of the paper."""

    def __init__(self, cfg: DeployConfig, seed: int | Sequence[int] | None = None) -> None:
        self.cfg = cfg
        self.period = 1.0 / cfg.control_rate
        self.vehicle = VehicleModel(cfg.vehicle)
        self.sensors = Sensors(cfg.sensors, seed)
        self.estimator = StateEstimator(cfg.estimator, cfg.sensors)
        self.speed_pid = PID.from_config(cfg.speed_pid)
        self.curvature_pid = PID.from_config(cfg.curvature_pid)
        self.time = 0.0
        self.trace = Trace()
        self.estimate: Estimate | None = None
        self._min_speed = cfg.estimator.min_speed

    def reset(self, x: float, y: float, heading: float, speed: float,
              seed: int | Sequence[int] | None = None) -> Estimate:
        """Put the car at a pose driving straight at ``speed``; fuse the first readings.

        The speed loop starts bumpless: its integral holds the force that keeps ``speed``, as
        when the controller takes over a car already cruising.
        """
        state = self.vehicle.reset(x, y, heading, speed)
        self.sensors.reset(seed)
        self.time = 0.0
        self.trace = Trace()
        readings = self.sensors.read(state, 0.0)
        self.estimate = self.estimator.reset(readings, heading)
        self.speed_pid.reset(integral=self.vehicle.resistance(speed))
        self.curvature_pid.reset()
        return self.estimate

    def drive(self, speed_cmd: float, curvature_cmd: float, duration: float) -> Estimate:
        """Track the set points for ``duration`` seconds (a whole number of control periods)."""
        assert self.estimate is not None, "call reset() first"
        for _ in range(max(1, round(duration / self.period))):
            est = self.estimate
            force = self.speed_pid.update(speed_cmd, est.speed, self.period)
            steer = self.curvature_pid.update(curvature_cmd, est.curvature, self.period)
            state = self.vehicle.step(force, steer, self.period)
            self.time += self.period
            readings = self.sensors.read(state, self.time)
            self.estimate = self.estimator.step(readings, self.period)
            self._record(readings, speed_cmd, curvature_cmd, force, steer)
        return self.estimate

    def _record(self, readings: Readings, speed_cmd: float, curvature_cmd: float,
                force: float, steer: float) -> None:
        s, e, rows = self.vehicle.state, self.estimate, self.trace.rows
        assert e is not None
        raw_curvature = readings.yaw_rate / max(readings.wheel_speed, self._min_speed)
        values = (
            self.time, s.x, s.y, s.heading, s.speed, s.yaw_rate, self.vehicle.curvature,
            e.x, e.y, e.heading, e.speed, e.yaw_rate, e.curvature,
            readings.wheel_speed, readings.yaw_rate, raw_curvature,
            speed_cmd, curvature_cmd, force, steer, s.force, s.steer,
        )
        for key, value in zip(TRACE_KEYS, values, strict=True):
            rows[key].append(float(value))
        if readings.gnss is not None:
            self.trace.gnss.append(
                (self.time, float(readings.gnss[0]), float(readings.gnss[1]), s.x, s.y))
