"""What the recorder's keys mean: held arrows -> one of the 9 actions per step.

Two mappings (``KeyboardDriver(controls=...)``):

* ``assisted`` (default): a held Left/Right means "curve that way": the wanted heading is
  ``turn_heading`` to that side; with neither held it is straight along the road (the lane
  heading). Each step the action is the one of the 9 whose curvature change brings the car
  toward that heading fastest without overshoot (:func:`assisted_action`).
  Speed: Up/Down held change it by one step per step; released, the speed is kept.
* ``literal``: each step a held Left/Right adds one curvature step (which stays when the key
  is released), Up/Down one speed step: the raw 9 actions.

Either way the returned action is what the env executes and what the recorder stores.
"""

from __future__ import annotations

import math

from memrl.envs.vehicles import action_index

ARROWS = ("up", "down", "left", "right")
CONTROLS = ("assisted", "literal")


def speed_sign(held: set[str]) -> int:
    return int("up" in held) - int("down" in held)


def steer_sign(held: set[str]) -> int:
    """+1: toward the right of the picture (positive y), -1: left, 0: neither or both."""
    return int("right" in held) - int("left" in held)


def action_from_keys(held: set[str]) -> int:
    """The literal action for a set of held arrow names (``up``, ``down``, ``left``, ``right``)."""
    return action_index(speed_sign(held), steer_sign(held))


def settled_heading(heading: float, curvature: float, speed: float, dt: float, step: float) -> float:
    """The heading [rad] the car ends at if its curvature is now ``curvature`` and then goes back
    to 0 by one ``step`` per action step of ``dt`` [s] at ``speed`` [m/s]."""
    n = round(abs(curvature) / step)
    return heading + speed * dt * curvature * (n + 1) / 2


def assisted_action(held: set[str], heading: float, curvature: float, speed: float, *,
                    curvature_step: float, dt: float = 0.1, turn_heading: float = 0.12,
                    turn_curvature: float = 0.02) -> int:
    """The assisted mode's action for the held keys and the car's state (see the module doc).

    Of the three curvature changes (one step left, none, one step right), the one whose
    :func:`settled_heading` lies nearest the heading wanted, without going past
    ``turn_curvature`` (ties: no change). So the car turns in as fast as the actions allow and
    straightens without overshoot; the heading left over is under half of what one step of
    curvature turns in one action step.

    Args:
        held: held arrow names.
        heading: the car's heading relative to the road [rad] (0: along it).
        curvature: its curvature [rad/m].
        speed: its speed [m/s].
        curvature_step: curvature change of one action [rad/m].
        dt: action step [s].
        turn_heading: heading wanted while Left/Right is held [rad].
        turn_curvature: largest curvature it steers to [rad/m].
    """
    heading = math.remainder(heading, 2 * math.pi)
    target = steer_sign(held) * turn_heading
    best, best_err = 0, math.inf
    for dk in (0, -1, 1):
        k = curvature + dk * curvature_step
        if dk and abs(k) > abs(curvature) and abs(k) > turn_curvature + 1e-9:
            continue
        err = abs(settled_heading(heading, k, speed, dt, curvature_step) - target)
        if err < best_err - 1e-9:
            best, best_err = dk, err
    return action_index(speed_sign(held), best)
