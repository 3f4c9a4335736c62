"""Collision risk of a state and the potential-based shaping built on it (``env.shaping``).

Why: the Table II reward says nothing until the crash, and a crash is decided seconds before it
happens (issue 30's second suspect, credit assignment). Potential-based shaping (Ng, Harada and
Russell, 1999) adds ``F = gamma * Phi(s') - Phi(s)`` to every reward with
``Phi(s) = -weight * risk(s)``: the return of every trajectory from ``s`` changes by ``-Phi(s)``
alone, so the optimal policy of the task is unchanged, while every step that raises the risk
is paid for at once. ``Phi`` is 0 in a terminal state (a crash), as the theory needs for
episodic tasks; a time-limit truncation is not terminal.

Risk (one formula for both engines, numpy arrays or torch tensors on any device): the time to
collision ``ttc`` [s] is the smallest of

* **along the road**, each other car whose body overlaps the agent's across the road
  (``|dy| < W``): gap ``|dx| - L`` over the closing speed ``sign(dx) (vx_agent - vx_car)``;
* **across the road**, each other car beside the agent (``|dx| < L``): gap ``|dy| - W`` over
  ``sign(dy) (vy_agent - vy_car)``;
* **the road edges**: the agent body's distance to each edge over its lateral speed toward it;

with ``vx = speed cos(heading)``, ``vy = speed sin(heading)``, (dx, dy) the car's centre
offset from the agent's, ``L`` and ``W`` the car length and width; a gap that is not closing
counts as no threat. ``risk = clip(1 - ttc / horizon, 0, 1)``: 0 when nothing is reached
within ``horizon`` seconds at today's speeds, 1 at contact.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from memrl.envs.batched_physics import lateral_extent

__all__ = ["risk", "shaping_reward"]

X, Y, HEADING, SPEED = range(4)


def _xp(x: Any) -> Any:
    return torch if isinstance(x, torch.Tensor) else np


def _ttc(gap: Any, closing: Any, threat: Any) -> Any:
    """Seconds until ``gap`` closes at ``closing`` (inf where not closing or not a threat)."""
    xp = _xp(gap)
    closes = threat & (closing > 0)
    safe = xp.where(closes, closing, xp.ones_like(closing))
    return xp.where(closes, xp.clip(gap, 0.0, None) / safe, xp.full_like(gap, np.inf))


def risk(state: Any, present: Any, lane_width: float, lanes_count: int, length: float,
         width: float, horizon: float) -> Any:
    """Collision risk in [0, 1] of each env (module doc).

    Args:
        state: ``[..., C, 5]`` car rows ``(x, y, heading, speed, curvature)``, the agent in
            slot 0, float64 (numpy array or torch tensor).
        present: ``[..., C]`` bool, the slots that hold a car (slot 0 is not read).
        lane_width: lane width [m]; the road edges lie half a lane outside the outer centres.
        lanes_count: number of lanes.
        length: car length [m].
        width: car width [m].
        horizon: seconds at which the risk reaches 0.

    Returns:
        ``[...]`` float64.
    """
    xp = _xp(state)
    agent, others = state[..., :1, :], state[..., 1:, :]
    vx = state[..., SPEED] * xp.cos(state[..., HEADING])
    vy = state[..., SPEED] * xp.sin(state[..., HEADING])
    dx = others[..., X] - agent[..., X]
    dy = others[..., Y] - agent[..., Y]
    there = present[..., 1:]
    along = _ttc(xp.abs(dx) - length, xp.sign(dx) * (vx[..., :1] - vx[..., 1:]),
                 there & (xp.abs(dy) < width))
    across = _ttc(xp.abs(dy) - width, xp.sign(dy) * (vy[..., :1] - vy[..., 1:]),
                  there & (xp.abs(dx) < length))
    lo, hi = lateral_extent(state[..., 0, :], length, width)  # the wall test's body extent
    vy0 = vy[..., 0]
    low_edge, high_edge = -0.5 * lane_width, (lanes_count - 0.5) * lane_width
    ttc = xp.minimum(_ttc(lo - low_edge, -vy0, True), _ttc(high_edge - hi, vy0, True))
    if others.shape[-2]:
        ttc = xp.minimum(ttc, xp.amin(xp.minimum(along, across), -1))
    return xp.clip(1.0 - ttc / horizon, 0.0, 1.0)


def shaping_reward(risk_before: Any, risk_after: Any, terminated: Any, weight: float,
                   gamma: float) -> Any:
    """``F = gamma Phi(s') - Phi(s)`` with ``Phi = -weight risk`` and ``Phi = 0`` at a terminal
    ``s'``: ``weight (risk(s) - gamma risk(s') (1 - terminated))``."""
    xp = _xp(risk_after)
    after = xp.where(terminated, xp.zeros_like(risk_after), risk_after)
    return weight * (risk_before - gamma * after)
