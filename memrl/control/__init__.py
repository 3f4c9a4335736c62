"""Deployment of the agent's commands on a simulated car (issue 7).

The agent's speed and curvature commands become set points of two PID loops (speed ->
accelerator force, curvature -> steering rate) that drive a dynamic vehicle model; noisy
sensors feed an extended Kalman filter (filterpy) whose estimate closes the loops and places
the car in the scene the agent sees. One idea per module:

* :mod:`memrl.control.config`: typed parameters (the ``deploy`` Hydra group's schema), units.
* :mod:`memrl.control.pid`: a PID controller with output limits and anti-windup.
* :mod:`memrl.control.vehicle`: longitudinal dynamics + dynamic bicycle model with actuators.
* :mod:`memrl.control.sensors`: GNSS position, wheel speed and yaw-rate gyro with noise and bias.
* :mod:`memrl.control.estimator`: the EKF.
* :mod:`memrl.control.tracking`: one control period of PID + vehicle + sensors + EKF.
* :mod:`memrl.control.episode`: one lane-change episode through the env (true state in the
  env, estimated state shown to the policy).
* :mod:`memrl.control.metrics`: success, overshoot, tracking and estimate-vs-raw errors.
* :mod:`memrl.control.baseline`: the same seeds in the plain simulator, for reference.
* :mod:`memrl.control.response`: step responses of the PID loops (the documented figures).
* :mod:`memrl.control.plot`: the PNG of trajectory, commands and tracked values.
"""
