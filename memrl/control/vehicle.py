"""A car heavier than the agent's kinematics: force-driven speed and a dynamic bicycle model.

Coordinates as in the env: x along the road, y across it [m], heading 0 along +x [rad].

* **Longitudinal**: ``m dv/dt = F - 1/2 rho CdA v^2 - c_rr m g + m vy r - F_yf sin(steer)``
  (the last two terms only in the dynamic regime). ``F`` follows the
  accelerator force demand (clamped to [-brake_force_max, drive_force_max]) with a first-order
  lag; braking never drives the car backwards.
* **Lateral**: the linear-tyre dynamic single-track (bicycle) model in body axes (lateral
  speed ``vy``, yaw rate ``r``), each axle's force limited by friction x load. Its slip angles
  divide by the speed, so near standstill it turns into the kinematic bicycle model (no slip):
  kinematic below ``kinematic_below``, dynamic above ``dynamic_above``, blended in between
  (the usual remedy in vehicle-dynamics MPC).
* **Steering actuator**: commanded in percent of the maximum steering rate; the rate follows
  the command with a first-order lag, and the angle stops at the steering lock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from memrl.control.config import VehicleModelConfig

GRAVITY = 9.81  # m/s^2


@dataclass
class VehicleState:
    """Full state of the vehicle model."""

    x: float = 0.0
    """Position along the road [m] (centre of gravity)."""
    y: float = 0.0
    """Position across the road [m]."""
    heading: float = 0.0
    """Yaw angle [rad]."""
    speed: float = 0.0
    """Longitudinal speed in body axes [m/s] (what the wheel-speed sensor reads)."""
    lateral_speed: float = 0.0
    """Lateral speed of the centre of gravity in body axes [m/s] (side slip)."""
    yaw_rate: float = 0.0
    """[rad/s]."""
    force: float = 0.0
    """Delivered longitudinal force [N] (negative: braking)."""
    steer: float = 0.0
    """Road-wheel steering angle [rad]."""
    steer_rate: float = 0.0
    """Road-wheel steering rate [rad/s]."""


class VehicleModel:
    """Integrates :class:`VehicleState` under accelerator and steering-rate commands."""

    def __init__(self, cfg: VehicleModelConfig) -> None:
        self.cfg = cfg
        self.wheelbase = cfg.cg_to_front + cfg.cg_to_rear
        # static axle loads [N]: the friction limit of each axle's lateral force
        self._front_max = cfg.friction * cfg.mass * GRAVITY * cfg.cg_to_rear / self.wheelbase
        self._rear_max = cfg.friction * cfg.mass * GRAVITY * cfg.cg_to_front / self.wheelbase
        self.state = VehicleState()

    def reset(self, x: float, y: float, heading: float = 0.0, speed: float = 0.0) -> VehicleState:
        """Start driving straight at ``speed`` with the force that holds it (no start-up jerk)."""
        self.state = VehicleState(x=x, y=y, heading=heading, speed=speed,
                                  force=self.resistance(speed))
        return self.state

    def resistance(self, speed: float) -> float:
        """Drag plus rolling resistance at ``speed`` [N] (zero at standstill)."""
        c = self.cfg
        rolling = c.rolling_resistance * c.mass * GRAVITY if speed > 1e-3 else 0.0
        return 0.5 * c.air_density * c.drag_area * speed * speed + rolling

    @property
    def curvature(self) -> float:
        """Curvature of the motion, yaw rate / speed [rad/m]; the steering geometry at standstill."""
        s = self.state
        if s.speed > 0.1:
            return s.yaw_rate / s.speed
        return math.tan(s.steer) / self.wheelbase

    def step(self, force_demand: float, steer_rate_demand: float, dt: float) -> VehicleState:
        """Advance ``dt`` seconds holding the commands.

        Args:
            force_demand: accelerator force demand [N]; negative brakes.
            steer_rate_demand: steering-rate demand [% of ``steer_rate_max``], clamped to +-100.
            dt: duration [s], split into steps of at most ``integration_dt``.
        """
        n = max(1, math.ceil(dt / self.cfg.integration_dt - 1e-9))
        for _ in range(n):
            self._substep(force_demand, steer_rate_demand, dt / n)
        return self.state

    def _substep(self, force_demand: float, steer_rate_demand: float, h: float) -> None:
        c, s = self.cfg, self.state
        # actuators: clamp, then first-order lag (exact discretisation)
        force_target = min(max(force_demand, -c.brake_force_max), c.drive_force_max)
        s.force += (force_target - s.force) * (1.0 - math.exp(-h / c.accelerator_lag))
        rate_target = min(max(steer_rate_demand, -100.0), 100.0) * 0.01 * c.steer_rate_max
        s.steer_rate += (rate_target - s.steer_rate) * (1.0 - math.exp(-h / c.steer_lag))
        steer = s.steer + s.steer_rate * h
        if abs(steer) >= c.steer_lock:
            steer = math.copysign(c.steer_lock, steer)
            s.steer_rate = 0.0
        s.steer = steer
        # lateral: blend of the kinematic and dynamic bicycle models (weight w of the dynamic)
        v = s.speed
        w = min(max((v - c.kinematic_below) / (c.dynamic_above - c.kinematic_below), 0.0), 1.0)
        vy_dot = r_dot = coupling = 0.0
        if w > 0.0:
            vy_dot, r_dot, coupling = self._dynamic_rates(v, s.lateral_speed, s.yaw_rate, s.steer)
        # longitudinal: braking stops the car but never reverses it
        accel = (s.force - self.resistance(v)) / c.mass + w * coupling
        s.speed = max(v + accel * h, 0.0)
        vy_kin, r_kin = self._kinematic(s.speed, s.steer)
        s.lateral_speed = w * (s.lateral_speed + vy_dot * h) + (1.0 - w) * vy_kin
        s.yaw_rate = w * (s.yaw_rate + r_dot * h) + (1.0 - w) * r_kin
        # pose
        cos, sin = math.cos(s.heading), math.sin(s.heading)
        s.x += (v * cos - s.lateral_speed * sin) * h
        s.y += (v * sin + s.lateral_speed * cos) * h
        s.heading += s.yaw_rate * h

    def _kinematic(self, v: float, steer: float) -> tuple[float, float]:
        """Lateral speed and yaw rate of rolling without slip at speed ``v``."""
        tan = math.tan(steer)
        return v * self.cfg.cg_to_rear * tan / self.wheelbase, v * tan / self.wheelbase

    def _dynamic_rates(self, v: float, vy: float, r: float, steer: float) -> tuple[float, float, float]:
        """d(vy)/dt, d(r)/dt and the lateral forces' share of d(v)/dt (``vy r`` minus the front
        tyre force's component along the car) of the linear-tyre bicycle model, each axle's
        force limited by friction."""
        c = self.cfg
        v = max(v, c.kinematic_below, 0.1)
        alpha_f = steer - (vy + c.cg_to_front * r) / v
        alpha_r = -(vy - c.cg_to_rear * r) / v
        fy_f = min(max(c.front_cornering_stiffness * alpha_f, -self._front_max), self._front_max)
        fy_r = min(max(c.rear_cornering_stiffness * alpha_r, -self._rear_max), self._rear_max)
        coupling = vy * r - fy_f * math.sin(steer) / c.mass
        fy_f *= math.cos(steer)
        vy_dot = (fy_f + fy_r) / c.mass - v * r
        r_dot = (c.cg_to_front * fy_f - c.cg_to_rear * fy_r) / c.yaw_inertia
        return vy_dot, r_dot, coupling
