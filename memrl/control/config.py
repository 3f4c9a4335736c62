"""Typed parameters of the deploy step (the schema of the ``deploy`` Hydra group), with units.

Registered with Hydra's ConfigStore as ``deploy/deploy_schema`` (see :mod:`memrl.configs`), so a
misspelt key fails when the config is composed; :func:`check_deploy_config` checks the values
and names the bad key.

PID units (the paper's P=2000, I=100, D=0, Sec. IV-D, used for both loops):

* speed loop: error in m/s, output the accelerator force demand in N (negative: brake).
  P=2000 N per m/s; I=100 N per (m/s x s), i.e. N/m; D in N per m/s^2. On the default
  1500 kg car, P alone closes the loop with a time constant of m/P = 0.75 s; with the 0.25 s
  accelerator lag the loop is well damped (damping ratio ~0.87). I removes the offset that
  drag and rolling resistance (~260 N at 10 m/s) leave under P alone (0.13 m/s).
* curvature loop: error in rad/m, output the steering-rate demand in percent of the steering
  actuator's maximum rate (``vehicle.steer_rate_max``). P=2000 %/(rad/m): a curvature error of
  0.01 rad/m (one action step) asks 20 % of the maximum rate. The steering angle integrates
  the rate, so the loop has an integrator and needs no I to reach zero static error; its
  crossover is P x steer_rate_max / 100 / wheelbase = 2000 x 0.006 / 2.8 ~ 4.3 rad/s (time
  constant ~0.23 s). I=100 %/(rad/m x s) makes the loop type 2, so a ramp of curvature
  commands (repeated curvature actions) is tracked without steady lag. Why a rate and not an
  angle: curvature follows the steering angle statically (kappa ~ angle / wheelbase), so an
  angle command would make P alone leave a static error of 1 / (1 + loop gain) that I=100,
  20x slower than P, removes only over tens of seconds; a loop gain high enough to hide that
  (>~20) oscillates with the actuator and yaw lags. Commanding the rate puts the integrator in
  the actuator, where P=2000 gives a well-damped loop (below) and I only helps ramps.

Step responses with these defaults on the default car, loops closed on the true state
(``memrl.control.response.step_response``; checked by tests/test_pid.py):

* speed, steps of 0.5-2 m/s at 8-10 m/s: 90 % of the step in < 1.5 s (measured 1.34-1.37 s),
  overshoot < 4 % (2.9-3.7 %), within 5 % of the step after < 1.6 s (1.51-1.55 s), error
  < 0.03 m/s after 20 s. 2 -> 14 m/s saturates the drive force for ~4 s: overshoot 0.2 %,
  within 2 % after 5.3 s; without anti-windup 12 % overshoot and still 0.76 m/s off after 20 s.
* curvature, steps of 0.02 and -0.05 rad/m at 4-12 m/s: 90 % in < 0.5 s (0.42-0.48 s),
  overshoot < 6 % (1.2-4.8 %), within 2 % after < 1.2 s (0.53-1.12 s).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from memrl.errors import UserError
from memrl.fields import SEED_MAX, spec


@dataclass
class VehicleModelConfig:
    """Car driven by the PID loops: longitudinal dynamics and a dynamic bicycle model."""

    mass: float = spec(1500.0, gt=0)
    """Vehicle mass [kg]."""
    yaw_inertia: float = spec(2250.0, gt=0)
    """Moment of inertia about the vertical axis [kg m^2]."""
    cg_to_front: float = spec(1.2, gt=0)
    """Centre of gravity to front axle [m]."""
    cg_to_rear: float = spec(1.6, gt=0)
    """Centre of gravity to rear axle [m]; wheelbase = cg_to_front + cg_to_rear."""
    front_cornering_stiffness: float = spec(80000.0, gt=0)
    """Cornering stiffness of the front axle (both tyres) [N/rad]."""
    rear_cornering_stiffness: float = spec(90000.0, gt=0)
    """Cornering stiffness of the rear axle [N/rad] (stiffer than front: the car understeers)."""
    friction: float = spec(0.9, gt=0)
    """Tyre-road friction coefficient; each axle's lateral force is limited to friction x load."""
    drag_area: float = spec(0.7, ge=0)
    """Drag coefficient x frontal area, Cd A [m^2]."""
    air_density: float = spec(1.2, ge=0)
    """[kg/m^3]."""
    rolling_resistance: float = spec(0.015, ge=0)
    """Rolling-resistance coefficient (force = coefficient x m g while moving) [-]."""
    drive_force_max: float = spec(4000.0, gt=0)
    """Largest traction force the powertrain delivers [N] (2.7 m/s^2 on 1500 kg)."""
    brake_force_max: float = spec(8000.0, gt=0)
    """Largest braking force [N] (5.3 m/s^2 on 1500 kg)."""
    accelerator_lag: float = spec(0.25, gt=0)
    """Time constant of the first-order lag from force demand to delivered force [s]."""
    steer_lock: float = spec(0.6, gt=0)
    """Largest road-wheel steering angle [rad] (34 deg)."""
    steer_rate_max: float = spec(0.6, gt=0)
    """Largest road-wheel steering rate [rad/s] (550 deg/s at a 16:1 steering wheel); the
    steering command is a percentage of this rate."""
    steer_lag: float = spec(0.05, gt=0)
    """Time constant of the first-order lag from rate demand to steering rate [s]."""
    kinematic_below: float = spec(2.0, ge=0)
    """Below this speed the lateral motion is kinematic (no tyre slip) [m/s] ..."""
    dynamic_above: float = spec(4.0, gt=0)
    """... above this speed it is the dynamic bicycle model; blended in between [m/s]."""
    integration_dt: float = spec(0.002, gt=0)
    """Internal integration step [s] (the control period is divided into steps of at most this)."""


@dataclass
class SensorConfig:
    """Noisy sensors. Wheel speed and gyro are sampled every control period; GNSS slower."""

    gnss_rate: float = spec(10.0, gt=0)
    """GNSS position fixes per second [Hz]."""
    gnss_noise: float = spec(0.3, gt=0)
    """Standard deviation of each GNSS coordinate [m]."""
    gnss_bias: list[float] = spec([0.0, 0.0], finite=True)
    """Constant offset of the GNSS position (x, y) [m] (not modelled by the filter)."""
    wheel_speed_noise: float = spec(0.1, gt=0)
    """Standard deviation of the wheel-speed reading [m/s]."""
    wheel_speed_bias: float = spec(0.05, finite=True)
    """Constant offset of the wheel-speed reading [m/s] (estimated by the filter)."""
    gyro_noise: float = spec(0.01, gt=0)
    """Standard deviation of the yaw-rate reading [rad/s] (0.57 deg/s)."""
    gyro_bias: float = spec(0.005, finite=True)
    """Constant offset of the yaw-rate reading [rad/s] (estimated by the filter)."""


@dataclass
class EstimatorConfig:
    """Extended Kalman filter over [x, y, heading, speed, acceleration, yaw rate, yaw
    acceleration, speed bias, gyro bias].

    Process noises are square roots of white-noise spectral densities: over a prediction step
    of ``dt`` seconds a random walk driven by noise ``q`` gains variance q^2 x dt.
    Measurement noises are the sensors' (``sensors.*_noise``).
    """

    jerk_noise: float = spec(2.0, gt=0)
    """White longitudinal jerk driving the acceleration [m/s^3 per sqrt(Hz)]."""
    yaw_jerk_noise: float = spec(0.5, gt=0)
    """White yaw jerk driving the yaw acceleration [rad/s^3 per sqrt(Hz)]."""
    slip_gain: float = spec(1.2, ge=0)
    """Side-slip angle per unit curvature [m]: the filter moves the car along heading + this x
    curvature. The bicycle model's steady-state value is l_r - m l_f v^2 / (L C_r): 1.6 m at
    standstill, 1.14 m at 8 m/s on the default car; 0 ignores side slip."""
    position_noise: float = spec(0.03, gt=0)
    """Unmodelled motion (slip transients, road) [m per sqrt(s)]."""
    heading_noise: float = spec(0.003, gt=0)
    """Unmodelled heading change [rad per sqrt(s)]."""
    speed_bias_noise: float = spec(0.001, gt=0)
    """Drift of the wheel-speed bias [m/s per sqrt(s)]."""
    gyro_bias_noise: float = spec(0.0001, gt=0)
    """Drift of the gyro bias [rad/s per sqrt(s)]."""
    initial_heading_std: float = spec(0.05, gt=0)
    """Uncertainty of the initial heading (the road direction) [rad]."""
    initial_speed_bias_std: float = spec(0.2, gt=0)
    """Uncertainty of the initial wheel-speed bias [m/s]."""
    initial_gyro_bias_std: float = spec(0.01, gt=0)
    """Uncertainty of the initial gyro bias [rad/s]."""
    min_speed: float = spec(1.0, gt=0)
    """Curvature is yaw rate / max(speed, min_speed) [m/s]: bounded near standstill."""


@dataclass
class PIDConfig:
    """One PID loop; gains in output units per error unit (see the module docstring)."""

    p: float = spec(2000.0, ge=0)
    """Proportional gain [output per error]."""
    i: float = spec(100.0, ge=0)
    """Integral gain [output per (error x s)]."""
    d: float = spec(0.0, ge=0)
    """Derivative gain [output per (error / s)], on the measurement (no set-point kick)."""
    output_limits: list[float] = spec([-100.0, 100.0], finite=True)
    """Output clamp (low, high) [output units]."""
    anti_windup: bool = True
    """Stop integrating while the output is clamped and the error would push it further."""


@dataclass
class DeployConfig:
    """``python -m memrl.deploy``: lane-change episodes through PID, vehicle model and EKF."""

    policy: str = "scripted"
    """Who drives: 'scripted' (memrl.modules.scripted.ScriptedDriver), 'checkpoint' (a trained
    agent from ``checkpoint``) or 'random' (uniform actions, for plumbing checks)."""
    checkpoint: str | None = None
    """Path of a trained checkpoint, for policy=checkpoint."""
    episodes: int = spec(20, ge=1)
    """Number of episodes."""
    seed: int = spec(0, ge=0, le=SEED_MAX)
    """Seed of the first episode (episode k uses seed + k), of the sensors and of the policy."""
    control_rate: float = spec(100.0, gt=0)
    """PID, sensor and filter rate [Hz]; the agent decides every env ``dt`` (0.1 s)."""
    plot_episode: int = spec(0, ge=0)
    """Episode drawn in ``deploy.png``."""
    compare_simulator: bool = True
    """Also run the policy on the same seeds in the plain simulator (instant commands, true
    state) and report its success, collisions and overshoot as ``sim_*`` metrics."""
    vehicle: VehicleModelConfig = field(default_factory=VehicleModelConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    speed_pid: PIDConfig = field(
        default_factory=lambda: PIDConfig(output_limits=[-8000.0, 4000.0]))
    """Speed [m/s] -> accelerator force [N]."""
    curvature_pid: PIDConfig = field(default_factory=PIDConfig)
    """Curvature [rad/m] -> steering rate [% of steer_rate_max]."""


POLICIES = ("scripted", "checkpoint", "random")


class DeployConfigError(UserError, ValueError):
    """A deploy config value is out of range."""


def _positive(obj: object, prefix: str, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not value > 0:
            raise DeployConfigError(f"deploy config '{prefix}{name}': must be > 0, got {value!r}")


def check_deploy_config(cfg: DeployConfig) -> DeployConfig:
    """Check every value of a deploy config; raise :class:`DeployConfigError` naming the key
    (each key's range, :func:`memrl.fields.check_fields`: ``config 'deploy.<key>': ...``)."""
    import dataclasses

    from memrl.errors import ConfigError
    from memrl.fields import check_fields

    try:
        check_fields(DeployConfig, dataclasses.asdict(cfg), "deploy.")
    except ConfigError as err:
        raise DeployConfigError(str(err)) from None
    if cfg.policy not in POLICIES:
        raise DeployConfigError(
            f"deploy config 'policy': expected one of {POLICIES}, got {cfg.policy!r}")
    if cfg.policy == "checkpoint" and not cfg.checkpoint:
        raise DeployConfigError("deploy config 'checkpoint': policy=checkpoint needs a path")
    _positive(cfg, "", "episodes", "control_rate")
    if not 0 <= cfg.plot_episode < cfg.episodes:
        raise DeployConfigError(
            f"deploy config 'plot_episode': expected 0 <= value < episodes, got {cfg.plot_episode}")
    v = cfg.vehicle
    _positive(v, "vehicle.", "mass", "yaw_inertia", "cg_to_front", "cg_to_rear",
              "front_cornering_stiffness", "rear_cornering_stiffness", "friction",
              "drive_force_max", "brake_force_max", "accelerator_lag", "steer_lock",
              "steer_rate_max", "steer_lag", "integration_dt")
    if not 0 <= v.kinematic_below < v.dynamic_above:
        raise DeployConfigError("deploy config 'vehicle.dynamic_above': must exceed kinematic_below >= 0")
    _positive(cfg.sensors, "sensors.", "gnss_rate", "gnss_noise", "wheel_speed_noise", "gyro_noise")
    if len(cfg.sensors.gnss_bias) != 2:
        raise DeployConfigError("deploy config 'sensors.gnss_bias': expected [x, y]")
    if cfg.estimator.slip_gain < 0:
        raise DeployConfigError("deploy config 'estimator.slip_gain': must be >= 0")
    _positive(cfg.estimator, "estimator.", "jerk_noise", "yaw_jerk_noise",
              "position_noise", "heading_noise", "speed_bias_noise", "gyro_bias_noise",
              "initial_heading_std", "initial_speed_bias_std", "initial_gyro_bias_std", "min_speed")
    for name in ("speed_pid", "curvature_pid"):
        pid: PIDConfig = getattr(cfg, name)
        lo, hi = pid.output_limits
        if not lo < hi:
            raise DeployConfigError(f"deploy config '{name}.output_limits': need low < high")
        if min(pid.p, pid.i, pid.d) < 0:
            raise DeployConfigError(f"deploy config '{name}': gains must be >= 0")
    return cfg
