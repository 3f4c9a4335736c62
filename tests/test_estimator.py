"""The EKF on a synthetic trajectory: error well below the raw sensors', biases found."""

from __future__ import annotations

import math

import numpy as np
import pytest

from memrl.control.config import DeployConfig
from memrl.control.estimator import GYRO_BIAS, SPEED, YAW_RATE, N, StateEstimator
from memrl.control.sensors import Readings, Sensors
from memrl.control.vehicle import VehicleModel

DT = 0.01  # s, control period


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def synthetic_run(seed: int, seconds: float = 30.0) -> tuple[dict[str, np.ndarray], object]:
    """Open-loop weave: steering angle oscillating (+-0.04 rad/m of curvature, 4 s period) while
    the force swings the speed between ~6.7 and ~10.9 m/s (10 s period)."""
    cfg = DeployConfig()
    car = VehicleModel(cfg.vehicle)
    car.reset(0.0, 0.0, 0.0, 8.0)
    sensors = Sensors(cfg.sensors, seed)
    est = StateEstimator(cfg.estimator, cfg.sensors)
    est.reset(sensors.read(car.state, 0.0))
    rows, fixes = [], []
    for k in range(1, round(seconds / DT) + 1):
        t = k * DT
        steer_rate = 30.0 * math.cos(2 * math.pi * t / 4.0)  # % of the maximum rate
        force = car.resistance(car.state.speed) + 1500.0 * math.sin(2 * math.pi * t / 10.0)
        s = car.step(force, steer_rate, DT)
        r = sensors.read(s, t)
        e = est.step(r, DT)
        rows.append((t, s.x, s.y, s.speed, s.yaw_rate, car.curvature,
                     e.x, e.y, e.speed, e.yaw_rate, e.curvature,
                     r.wheel_speed, r.yaw_rate, r.yaw_rate / max(r.wheel_speed, cfg.estimator.min_speed)))
        if r.gnss is not None:
            fixes.append((t, r.gnss[0] - s.x, r.gnss[1] - s.y))
    names = ("t x y v r k est_x est_y est_v est_r est_k raw_v raw_r raw_k").split()
    a = np.array(rows)
    out = {n: a[:, i] for i, n in enumerate(names)}
    out["gnss"] = np.array(fixes)
    return out, est


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_filter_error_is_well_below_raw_sensor_error(seed):
    d, _ = synthetic_run(seed)
    assert np.ptp(d["k"]) > 0.06 and np.ptp(d["v"]) > 3.0  # the run really manoeuvres
    keep = d["t"] > 5.0  # after the biases converged
    g = d["gnss"][d["gnss"][:, 0] > 5.0]
    pos_est = rms(np.hypot(d["est_x"] - d["x"], d["est_y"] - d["y"])[keep])
    pos_raw = rms(np.hypot(g[:, 1], g[:, 2]))
    assert pos_est < 0.4 * pos_raw
    for q, bound in (("v", 0.5), ("r", 0.55), ("k", 0.55)):
        est, raw = rms((d[f"est_{q}"] - d[q])[keep]), rms((d[f"raw_{q}"] - d[q])[keep])
        assert est < bound * raw, (q, est, raw)


def test_biases_are_estimated():
    cfg = DeployConfig()
    _, est = synthetic_run(0)
    e = est.estimate
    assert e.gyro_bias == pytest.approx(cfg.sensors.gyro_bias, abs=1e-3)
    assert e.speed_bias == pytest.approx(cfg.sensors.wheel_speed_bias, abs=0.015)
    assert est.std[GYRO_BIAS] < 1e-3


def test_jacobian_matches_finite_differences_of_the_motion_model():
    cfg = DeployConfig()
    est = StateEstimator(cfg.estimator, cfg.sensors)
    est.reset(Readings(0.0, 8.0, 0.1, np.array([3.0, 1.0])))
    rng = np.random.default_rng(0)
    x0 = np.array([3.0, 1.0, 0.2, 8.0, 0.5, 0.25, -0.3, 0.05, 0.004]).reshape(N, 1)
    x0 += 0.01 * rng.standard_normal((N, 1))
    ekf = est.ekf
    ekf.dt = 0.01
    ekf.x = x0.copy()
    jac = est._jacobian(0.01)

    def propagate(x: np.ndarray) -> np.ndarray:
        ekf.x = x.copy()
        ekf.predict_x()
        return ekf.x.copy()

    numeric = np.zeros((N, N))
    for j in range(N):
        h = np.zeros((N, 1))
        h[j] = 1e-6
        numeric[:, j] = ((propagate(x0 + h) - propagate(x0 - h)) / 2e-6)[:, 0]
    np.testing.assert_allclose(jac, numeric, atol=1e-7)
    assert jac[SPEED, SPEED] == 1.0 and jac[YAW_RATE, YAW_RATE] == 1.0


def test_reset_needs_a_gnss_fix():
    cfg = DeployConfig()
    est = StateEstimator(cfg.estimator, cfg.sensors)
    with pytest.raises(ValueError, match="GNSS"):
        est.reset(Readings(0.0, 8.0, 0.0, None))


def test_sensors_have_configured_bias_noise_and_gnss_rate():
    cfg = DeployConfig()
    car = VehicleModel(cfg.vehicle)
    state = car.reset(0.0, 0.0, 0.0, 8.0)
    sensors = Sensors(cfg.sensors, seed=0)
    readings = [sensors.read(state, k * DT) for k in range(2000)]
    wheel = np.array([r.wheel_speed for r in readings]) - 8.0
    gyro = np.array([r.yaw_rate for r in readings])
    fixes = [r for r in readings if r.gnss is not None]
    assert len(fixes) == 200  # 10 Hz over 20 s
    assert wheel.mean() == pytest.approx(cfg.sensors.wheel_speed_bias, abs=0.01)
    assert wheel.std() == pytest.approx(cfg.sensors.wheel_speed_noise, rel=0.1)
    assert gyro.mean() == pytest.approx(cfg.sensors.gyro_bias, abs=1e-3)
    assert gyro.std() == pytest.approx(cfg.sensors.gyro_noise, rel=0.1)
    assert np.std([f.gnss for f in fixes]) == pytest.approx(cfg.sensors.gnss_noise, rel=0.15)
