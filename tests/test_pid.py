"""PID controller: terms, limits, anti-windup; step responses of both loops on the vehicle model.

The bounds below are the ones documented in memrl/control/config.py (module docstring).
"""

from __future__ import annotations

import pytest

from memrl.control.config import DeployConfig
from memrl.control.pid import PID
from memrl.control.response import step_response


def test_proportional_integral_and_clamp():
    pid = PID(p=2.0, i=0.5, output_limits=(-10.0, 10.0))
    assert pid.update(1.0, 0.0, dt=0.1) == pytest.approx(2.0 + 0.05)
    assert pid.update(1.0, 0.0, dt=0.1) == pytest.approx(2.0 + 0.10)
    assert pid.update(100.0, 0.0, dt=0.1) == 10.0 and pid.saturated
    assert pid.update(-100.0, 0.0, dt=0.1) == -10.0


def test_derivative_acts_on_the_measurement_without_set_point_kick():
    pid = PID(p=0.0, d=1.0)
    assert pid.update(0.0, 0.0, dt=0.1) == 0.0
    assert pid.update(5.0, 0.0, dt=0.1) == 0.0  # set point jumps: no kick
    assert pid.update(5.0, 1.0, dt=0.1) == pytest.approx(-10.0)  # measurement rises 10/s


def test_integral_is_frozen_while_saturated_and_error_pushes_outward():
    pid = PID(p=1.0, i=10.0, output_limits=(-1.0, 1.0))
    for _ in range(100):
        pid.update(5.0, 0.0, dt=0.1)
    assert pid.integral <= 1.0
    # with the windup-prone integral the same history leaves a huge integral
    plain = PID(p=1.0, i=10.0, output_limits=(-1.0, 1.0), anti_windup=False)
    for _ in range(100):
        plain.update(5.0, 0.0, dt=0.1)
    assert plain.integral == pytest.approx(500.0)
    # integration resumes as soon as the error would pull the output back inside
    before = pid.integral
    pid.update(-0.5, 0.0, dt=0.1)
    assert pid.integral < before


def _overshoot_on_saturating_integrator(anti_windup: bool) -> float:
    """x' = u with |u| <= 1, PI loop stepping x from 0 to 10: the classic windup test."""
    pid = PID(p=1.0, i=1.0, output_limits=(-1.0, 1.0), anti_windup=anti_windup)
    x, peak, dt = 0.0, 0.0, 0.01
    for _ in range(3000):
        x += pid.update(10.0, x, dt) * dt
        peak = max(peak, x)
    return peak - 10.0


def test_anti_windup_removes_the_overshoot_after_saturation():
    with_aw, without = _overshoot_on_saturating_integrator(True), _overshoot_on_saturating_integrator(False)
    assert without > 5.0  # wound-up integral: x overshoots by more than half the step
    assert with_aw < 0.5


def test_rejects_empty_output_range():
    with pytest.raises(ValueError, match="output_limits"):
        PID(1.0, output_limits=(1.0, 1.0))


@pytest.mark.parametrize("start, target", [(8.0, 10.0), (10.0, 8.0), (8.0, 8.5)])
def test_speed_step_settles_within_documented_bounds(start, target):
    r = step_response(DeployConfig(), "speed", start, target, duration=20.0)
    assert r.rise_time(0.9) < 1.5  # s
    assert r.overshoot < 0.04
    assert r.settling_time(0.05) < 1.6  # s, within 5 % of the step
    assert abs(r.final_error) < 0.03  # m/s after 20 s: the integral removed drag and rolling


def test_large_speed_step_saturates_the_accelerator_and_still_settles():
    cfg = DeployConfig()
    r = step_response(cfg, "speed", 2.0, 14.0, duration=10.0)
    assert r.output.max() == cfg.speed_pid.output_limits[1]  # drive force saturated
    assert r.overshoot < 0.01 and r.settling_time(0.02) < 6.0


def test_speed_loop_anti_windup_on_the_vehicle():
    """Without anti-windup, 4 s at the force limit wind the integral up: 12 % overshoot and an
    error that the slow integral (P/I = 20 s) has not removed after 20 s."""
    cfg = DeployConfig()
    cfg.speed_pid.anti_windup = False
    wound = step_response(cfg, "speed", 2.0, 14.0, duration=20.0)
    clean = step_response(DeployConfig(), "speed", 2.0, 14.0, duration=20.0)
    assert wound.overshoot > 0.08 and abs(wound.final_error) > 0.5
    assert clean.overshoot < 0.01 and abs(clean.final_error) < 0.02


@pytest.mark.parametrize("speed", [4.0, 8.0, 12.0])
@pytest.mark.parametrize("target", [0.02, -0.05])
def test_curvature_step_settles_within_documented_bounds(speed, target):
    r = step_response(DeployConfig(), "curvature", 0.0, target, duration=4.0, speed=speed)
    assert r.rise_time(0.9) < 0.5  # s
    assert r.overshoot < 0.06
    assert r.settling_time(0.02) < 1.2  # s, within 2 % of the step
    assert abs(r.final_error) < 0.02 * abs(target)
