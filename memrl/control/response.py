"""Step responses of the two PID loops on the vehicle model (the figures quoted in the docs).

The loops are closed on the true state here (no sensor noise), so the figures describe the
controller and the car, not the estimator. Both loops run together, one holding its set point
while the other steps, at the control rate of the deploy config.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from memrl.control.config import DeployConfig
from memrl.control.pid import PID
from memrl.control.vehicle import VehicleModel


@dataclass
class StepResponse:
    """A step of a set point and what the car did."""

    time: np.ndarray
    """[s] after the step."""
    value: np.ndarray
    """The tracked quantity (speed [m/s] or curvature [rad/m]) at each control period."""
    start: float
    target: float
    output: np.ndarray
    """PID output at each control period."""

    def rise_time(self, fraction: float = 0.9) -> float:
        """First time [s] the value covers ``fraction`` of the step (inf if never)."""
        progress = (self.value - self.start) / (self.target - self.start)
        hit = np.flatnonzero(progress >= fraction)
        return float(self.time[hit[0]]) if hit.size else float("inf")

    @property
    def overshoot(self) -> float:
        """Largest excursion beyond the target, as a fraction of the step (0 if none)."""
        progress = (self.value - self.start) / (self.target - self.start)
        return max(0.0, float(progress.max()) - 1.0)

    def settling_time(self, band: float = 0.02) -> float:
        """Time [s] after which the value stays within ``band`` x step of the target."""
        outside = np.flatnonzero(np.abs(self.value - self.target) > band * abs(self.target - self.start))
        if not outside.size:
            return 0.0
        return float(self.time[outside[-1] + 1]) if outside[-1] + 1 < self.time.size else float("inf")

    @property
    def final_error(self) -> float:
        """Target minus the last value."""
        return float(self.target - self.value[-1])


def step_response(cfg: DeployConfig, loop: str, start: float, target: float,
                  duration: float, speed: float = 8.0) -> StepResponse:
    """Settle the car at ``start`` (speed loop) or straight at ``speed``, then step the set point.

    Args:
        cfg: vehicle, PID gains, control rate.
        loop: 'speed' (set point in m/s) or 'curvature' (rad/m, at constant ``speed``).
        start: set point before the step; the car starts in the steady state that holds it
            (for curvature: driving straight, so ``start`` must be 0).
        target: set point after the step.
        duration: how long to record [s].
        speed: speed held during a curvature step [m/s].
    """
    if loop not in ("speed", "curvature"):
        raise ValueError(f"loop: expected 'speed' or 'curvature', got {loop!r}")
    if loop == "curvature" and start != 0.0:
        raise ValueError("a curvature step starts from straight driving (start=0)")
    v0 = start if loop == "speed" else speed
    car = VehicleModel(cfg.vehicle)
    car.reset(0.0, 0.0, 0.0, v0)
    speed_pid, curvature_pid = PID.from_config(cfg.speed_pid), PID.from_config(cfg.curvature_pid)
    speed_pid.reset(integral=car.resistance(v0))  # bumpless: the force that holds v0
    dt = 1.0 / cfg.control_rate
    n = round(duration / dt)
    values, outputs = np.empty(n), np.empty(n)
    speed_sp, curvature_sp = (target, 0.0) if loop == "speed" else (speed, target)
    for k in range(n):
        force = speed_pid.update(speed_sp, car.state.speed, dt)
        steer = curvature_pid.update(curvature_sp, car.curvature, dt)
        car.step(force, steer, dt)
        values[k] = car.state.speed if loop == "speed" else car.curvature
        outputs[k] = force if loop == "speed" else steer
    return StepResponse(np.arange(1, n + 1) * dt, values, start, target, outputs)
