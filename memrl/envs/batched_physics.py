"""The batched engine's kinematics, wall test and lane, on numpy arrays (the engine's CPU
path: many small operations, where numpy's calls cost a fraction of torch's) or torch tensors
(any device), with the same formulas either way (the reward's: :mod:`memrl.envs.reward`).

Cars are rows ``[..., (x, y, heading, speed, curvature)]``, float64.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from memrl.envs.render import NUMPY, TORCH, _Ops, body_corners

X, Y, HEADING, SPEED, CURVATURE = range(5)


def ops(x: Any) -> _Ops:
    """The array operations of ``x``'s kind (numpy or torch)."""
    return TORCH if isinstance(x, torch.Tensor) else NUMPY


def round9(x: Any) -> Any:
    """Round to 9 decimals (scale, round half to even, unscale: the same steps in both)."""
    return torch.round(x, decimals=9) if isinstance(x, torch.Tensor) else np.round(x, 9)


def apply_actions(state: Any, ds: Any, dk: Any, speed_limits: tuple[float, float], curvature_limit: float
                  ) -> None:
    """Add the speed and curvature changes ``ds``, ``dk`` (per car) to every car, clamp, round."""
    x_ = ops(state)
    speed = x_.clip(state[..., SPEED] + ds, float(speed_limits[0]), float(speed_limits[1]))
    curv = x_.clip(state[..., CURVATURE] + dk, -curvature_limit, curvature_limit)
    # round away float drift, as the reference does with round(x, 9)
    state[..., SPEED] = round9(speed)
    state[..., CURVATURE] = round9(curv)


def move(state: Any, dt: float) -> None:
    """Every car drives ``dt`` along its exact arc (straight below a 1e-9 rad turn), in place."""
    x_ = ops(state)
    h, k = state[..., HEADING], state[..., CURVATURE]
    distance = state[..., SPEED] * dt
    turn = k * distance
    straight = abs(turn) < 1e-9
    radius = 1.0 / x_.where(straight, 1.0, k)
    new_h = h + turn
    sin_h, cos_h = x_.sin(h), x_.cos(h)
    dx = x_.where(straight, distance * cos_h, radius * (x_.sin(new_h) - sin_h))
    dy = x_.where(straight, distance * sin_h, radius * (cos_h - x_.cos(new_h)))
    state[..., X] += dx
    state[..., Y] += dy
    state[..., HEADING] = x_.where(straight, h, new_h)


def lateral_extent(cars: Any, length: float, width: float) -> tuple[Any, Any]:
    """Lowest and highest y [m] of the body corners of cars ``[..., 5]``."""
    y = body_corners(cars[..., X], cars[..., Y], cars[..., HEADING], length, width)[..., 1]
    if isinstance(y, torch.Tensor):
        return y.amin(-1), y.amax(-1)
    return y.min(-1), y.max(-1)


def inside_target(lo: Any, hi: Any, target: Any, lane_width: float) -> Any:
    """Whether a body spanning [lo, hi] across the road lies wholly in lane ``target``."""
    y = ops(lo).f64(target) * lane_width
    return (y - 0.5 * lane_width <= lo) & (hi <= y + 0.5 * lane_width)


def lane(agent: Any, lane_width: float, lanes_count: int) -> Any:
    """Lane holding each agent's centre (clipped to the road), as float64."""
    x_ = ops(agent)
    return x_.clip(x_.floor(agent[..., Y] / lane_width + 0.5), 0, lanes_count - 1)


def overlap(first: Any, second: Any, length: float, width: float) -> Any:
    """Whether car bodies ``[..., 5]`` (numpy arrays or tensors, broadcast alike) overlap:
    highway-env's ``utils.are_polygons_intersecting`` at zero velocity (the 4 edge normals of
    each body; touching counts), for many pairs at once."""
    # Hand-written: highway-env's test takes one pair of polygons per call.
    xp: Any = np if isinstance(first, np.ndarray) else torch
    x, y, heading = (xp.stack([first[..., i], second[..., i]]) for i in (X, Y, HEADING))
    both = body_corners(x, y, heading, length, width)
    nxt = [1, 2, 3, 0]  # each corner's next, around the body
    a, b = both[0], both[1]  # [..., 4, 2]
    edges = xp.concatenate([a[..., nxt, :] - a, b[..., nxt, :] - b], -2)  # [..., 8, 2]
    nx, ny = -edges[..., 1], edges[..., 0]  # [..., 8 edges]
    norm = xp.sqrt(nx * nx + ny * ny)
    nx, ny = (nx / norm)[..., None], (ny / norm)[..., None]  # [..., 8 axes, 1]
    proj = both[..., None, :, 0] * nx + both[..., None, :, 1] * ny  # [2, ..., 8 axes, 4 corners]
    low, high = xp.amin(proj, -1), xp.amax(proj, -1)
    (min_a, min_b), (max_a, max_b) = low, high
    gap = xp.where(min_a < min_b, min_b - max_a, min_a - max_b)
    return (gap <= 0).all(-1)
