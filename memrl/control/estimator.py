"""State estimate from the noisy sensors: an extended Kalman filter (filterpy).

State ``[x, y, heading, speed, acceleration, yaw_rate, yaw_acceleration, speed_bias,
gyro_bias]``. Motion: the car moves at ``speed`` along ``heading + slip``, where the side-slip
angle is ``slip = slip_gain x curvature`` (the steady-state slip of a bicycle model),
``d heading/dt = yaw_rate``; longitudinal and yaw accelerations are constant between steps and
driven by white jerk (so the ramps of speed and yaw rate that the agent's repeated actions
produce are followed without lag); biases are random walks. Measurements: wheel speed
``speed + speed_bias`` and gyro ``yaw_rate + gyro_bias`` every control period, GNSS ``(x, y)``
at its own rate. Curvature is ``yaw_rate / max(speed, min_speed)``.

Why an EKF: the only nonlinearity is the rotation of the velocity by heading and slip in the
motion model; every measurement is linear. The motion over one 10 ms prediction step is nearly
linear, so the first-order (Jacobian) EKF is accurate, and an unscented filter would spend 19
sigma points per step (of 9 states) to buy nothing: the measurement updates are exact linear
Kalman updates either way. A linear KF cannot move a position along an unknown heading.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import ExtendedKalmanFilter

from memrl.control.config import EstimatorConfig, SensorConfig
from memrl.control.sensors import Readings

X, Y, HEADING, SPEED, ACCEL, YAW_RATE, YAW_ACCEL, SPEED_BIAS, GYRO_BIAS = range(9)
N = 9
_H_IMU = np.zeros((2, N))
_H_IMU[0, [SPEED, SPEED_BIAS]] = 1.0
_H_IMU[1, [YAW_RATE, GYRO_BIAS]] = 1.0
_H_GNSS = np.zeros((2, N))
_H_GNSS[0, X] = _H_GNSS[1, Y] = 1.0


@dataclass
class Estimate:
    """The filter's current belief (means only)."""

    x: float
    y: float
    heading: float
    speed: float
    yaw_rate: float
    curvature: float
    speed_bias: float
    gyro_bias: float


class _MotionEKF(ExtendedKalmanFilter):
    """filterpy's EKF with our nonlinear state propagation (filterpy's documented extension)."""

    dt = 0.01
    slip_gain = 0.0
    min_speed = 1.0

    def predict_x(self, u: object = 0) -> None:
        x = self.x
        v, heading = x[SPEED, 0], x[HEADING, 0]
        course = heading + self.slip_gain * x[YAW_RATE, 0] / max(v, self.min_speed)
        x[X, 0] += v * math.cos(course) * self.dt
        x[Y, 0] += v * math.sin(course) * self.dt
        x[HEADING, 0] += x[YAW_RATE, 0] * self.dt
        x[SPEED, 0] += x[ACCEL, 0] * self.dt
        x[YAW_RATE, 0] += x[YAW_ACCEL, 0] * self.dt


class StateEstimator:
    """Wraps the EKF: :meth:`reset` on the first readings, then :meth:`step` every period."""

    def __init__(self, cfg: EstimatorConfig, sensors: SensorConfig) -> None:
        self.cfg = cfg
        self.ekf = _MotionEKF(dim_x=N, dim_z=2)
        self.ekf.slip_gain, self.ekf.min_speed = cfg.slip_gain, cfg.min_speed
        self._r_imu = np.diag([sensors.wheel_speed_noise ** 2, sensors.gyro_noise ** 2])
        self._r_gnss = np.eye(2) * sensors.gnss_noise ** 2
        self._q_dt = -1.0
        self._q = np.zeros((N, N))

    def reset(self, readings: Readings, heading: float = 0.0) -> Estimate:
        """Start from a weak prior (heading along the road) and fuse the first readings.

        Args:
            readings: the sensors at time 0; must hold a GNSS fix.
            heading: prior heading [rad] (the road direction), std ``initial_heading_std``.
        """
        if readings.gnss is None:
            raise ValueError("the estimator starts from a GNSS fix; the first readings have none")
        c = self.cfg
        ekf = self.ekf
        ekf.x = np.zeros((N, 1))
        ekf.x[HEADING, 0] = heading
        ekf.P = np.diag([1e4, 1e4, c.initial_heading_std ** 2, 1e2, 1.0, 1.0, 1.0,
                         c.initial_speed_bias_std ** 2, c.initial_gyro_bias_std ** 2])
        self._update(readings)
        return self.estimate

    def _process_noise(self, dt: float) -> np.ndarray:
        """Q for a step of ``dt``: white jerk on (speed, acceleration) and (yaw rate, yaw
        acceleration), white rates on pose and biases (cached per ``dt``)."""
        if dt != self._q_dt:
            c = self.cfg
            q = np.zeros((N, N))
            q[X, X] = q[Y, Y] = c.position_noise ** 2 * dt
            q[HEADING, HEADING] = c.heading_noise ** 2 * dt
            q[SPEED_BIAS, SPEED_BIAS] = c.speed_bias_noise ** 2 * dt
            q[GYRO_BIAS, GYRO_BIAS] = c.gyro_bias_noise ** 2 * dt
            for i, noise in ((SPEED, c.jerk_noise), (YAW_RATE, c.yaw_jerk_noise)):
                q[i:i + 2, i:i + 2] = Q_continuous_white_noise(2, dt, noise ** 2)
            self._q, self._q_dt = q, dt
        return self._q

    def _jacobian(self, dt: float) -> np.ndarray:
        """d(next state) / d(state) of :meth:`_MotionEKF.predict_x` at the current state."""
        x, c = self.ekf.x[:, 0], self.cfg
        v, r = x[SPEED], x[YAW_RATE]
        v_eff = max(v, c.min_speed)
        course = x[HEADING] + c.slip_gain * r / v_eff
        d_course_dv = -c.slip_gain * r / (v * v) if v > c.min_speed else 0.0
        cos, sin = math.cos(course) * dt, math.sin(course) * dt
        f = np.eye(N)
        f[X, HEADING], f[Y, HEADING] = -v * sin, v * cos
        f[X, SPEED], f[Y, SPEED] = cos - v * sin * d_course_dv, sin + v * cos * d_course_dv
        f[X, YAW_RATE], f[Y, YAW_RATE] = -v * sin * c.slip_gain / v_eff, v * cos * c.slip_gain / v_eff
        f[HEADING, YAW_RATE] = f[SPEED, ACCEL] = f[YAW_RATE, YAW_ACCEL] = dt
        return f

    def step(self, readings: Readings, dt: float) -> Estimate:
        """Predict ``dt`` seconds ahead, then fuse ``readings``."""
        ekf = self.ekf
        ekf.dt = dt
        ekf.F = self._jacobian(dt)
        ekf.Q = self._process_noise(dt)
        ekf.predict()
        self._update(readings)
        return self.estimate

    def _update(self, readings: Readings) -> None:
        ekf = self.ekf
        z = np.array([[readings.wheel_speed], [readings.yaw_rate]])
        ekf.update(z, lambda _: _H_IMU, lambda s: _H_IMU @ s, R=self._r_imu)
        if readings.gnss is not None:
            ekf.update(readings.gnss.reshape(2, 1), lambda _: _H_GNSS, lambda s: _H_GNSS @ s,
                       R=self._r_gnss)

    @property
    def estimate(self) -> Estimate:
        """The current belief."""
        x = self.ekf.x[:, 0]
        return Estimate(
            x=float(x[X]), y=float(x[Y]), heading=float(x[HEADING]), speed=float(x[SPEED]),
            yaw_rate=float(x[YAW_RATE]),
            curvature=float(x[YAW_RATE] / max(x[SPEED], self.cfg.min_speed)),
            speed_bias=float(x[SPEED_BIAS]), gyro_bias=float(x[GYRO_BIAS]),
        )

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the 9 state components (the filter's own uncertainty)."""
        return np.sqrt(np.diag(self.ekf.P))
