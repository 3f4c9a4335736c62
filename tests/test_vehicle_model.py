"""Vehicle model: longitudinal dynamics, actuators (limits, lags, rate limit), bicycle model."""

from __future__ import annotations

import math

import pytest

from memrl.control.config import VehicleModelConfig
from memrl.control.vehicle import GRAVITY, VehicleModel

CFG = VehicleModelConfig()
WHEELBASE = CFG.cg_to_front + CFG.cg_to_rear


def hold(model: VehicleModel, force: float, steer_rate: float, seconds: float) -> None:
    for _ in range(round(seconds / 0.01)):
        model.step(force, steer_rate, 0.01)


def test_resistance_is_drag_plus_rolling():
    car = VehicleModel(CFG)
    v = 10.0
    drag = 0.5 * CFG.air_density * CFG.drag_area * v * v
    assert car.resistance(v) == pytest.approx(drag + CFG.rolling_resistance * CFG.mass * GRAVITY)
    assert car.resistance(0.0) == 0.0


def test_cruise_holds_speed_and_drives_straight():
    car = VehicleModel(CFG)
    car.reset(100.0, 4.0, 0.0, 10.0)
    hold(car, car.resistance(10.0), 0.0, 5.0)
    assert car.state.speed == pytest.approx(10.0, abs=1e-6)
    assert car.state.x == pytest.approx(150.0, abs=1e-3) and car.state.y == pytest.approx(4.0)


def test_accelerator_first_order_lag_and_force_limits():
    car = VehicleModel(CFG)
    car.reset(0.0, 0.0, 0.0, 10.0)
    base = car.state.force
    hold(car, base + 1000.0, 0.0, CFG.accelerator_lag)
    assert car.state.force - base == pytest.approx(1000.0 * (1 - math.exp(-1)), rel=1e-3)
    hold(car, 1e6, 0.0, 3.0)
    assert car.state.force == pytest.approx(CFG.drive_force_max, rel=1e-3)
    hold(car, -1e6, 0.0, 3.0)
    assert car.state.force == pytest.approx(-CFG.brake_force_max, rel=1e-3)


def test_braking_stops_the_car_without_reversing():
    car = VehicleModel(CFG)
    car.reset(0.0, 0.0, 0.0, 3.0)
    hold(car, -CFG.brake_force_max, 0.0, 3.0)
    x_stop = car.state.x
    assert car.state.speed == 0.0
    hold(car, -CFG.brake_force_max, 0.0, 1.0)
    assert car.state.speed == 0.0 and car.state.x == pytest.approx(x_stop)


def test_steering_rate_lag_rate_limit_and_lock():
    car = VehicleModel(CFG)
    car.reset(0.0, 0.0, 0.0, 8.0)
    hold(car, car.resistance(8.0), 50.0, CFG.steer_lag)
    assert car.state.steer_rate == pytest.approx(0.5 * CFG.steer_rate_max * (1 - math.exp(-1)), rel=1e-2)
    car.reset(0.0, 0.0, 0.0, 2.0)
    hold(car, car.resistance(2.0), 300.0, 0.5)  # demand clamped to 100 %
    assert car.state.steer_rate == pytest.approx(CFG.steer_rate_max, rel=1e-3)
    assert car.state.steer < CFG.steer_rate_max * 0.5
    hold(car, car.resistance(2.0), 100.0, 2.0)
    assert car.state.steer == CFG.steer_lock


def _steady_turn(speed: float, steer: float) -> VehicleModel:
    car = VehicleModel(CFG)
    car.reset(0.0, 0.0, 0.0, speed)
    car.state.steer = steer
    hold(car, car.resistance(speed), 0.0, 5.0)
    return car


def test_low_speed_turn_is_kinematic():
    car = _steady_turn(1.0, 0.2)
    assert car.curvature == pytest.approx(math.tan(0.2) / WHEELBASE, rel=1e-6)
    assert car.state.lateral_speed == pytest.approx(1.0 * CFG.cg_to_rear * math.tan(0.2) / WHEELBASE,
                                                    rel=1e-3)


@pytest.mark.parametrize("speed", [8.0, 12.0])
def test_steady_turn_matches_linear_bicycle_theory(speed):
    """Curvature = steer / (L + K v^2) with the understeer gradient K = m/L (l_r/C_f - l_f/C_r);
    side slip / curvature = l_r - m l_f v^2 / (L C_r) (the estimator's slip_gain)."""
    steer = 0.02
    car = _steady_turn(speed, steer)
    c = CFG
    understeer = c.mass / WHEELBASE * (c.cg_to_rear / c.front_cornering_stiffness
                                       - c.cg_to_front / c.rear_cornering_stiffness)
    kappa = math.cos(steer) * steer / (WHEELBASE + understeer * speed ** 2)
    assert car.curvature == pytest.approx(kappa, rel=2e-2)
    slip_per_curvature = c.cg_to_rear - c.mass * c.cg_to_front * speed ** 2 / (
        WHEELBASE * c.rear_cornering_stiffness)
    assert car.state.lateral_speed / speed / car.curvature == pytest.approx(slip_per_curvature, rel=3e-2)
    assert car.state.speed == pytest.approx(speed, rel=2e-2)  # held by the resistance force


def test_tyre_forces_saturate_at_the_friction_limit():
    car = _steady_turn(14.0, 0.3)  # asks ~10x the lateral grip
    lateral_accel = car.state.speed * car.state.yaw_rate
    assert lateral_accel < CFG.friction * GRAVITY * 1.05
