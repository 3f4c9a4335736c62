"""What a collision was, from the world state at the crash: one classifier for both engines.

The reference env (:class:`memrl.envs.lane_change.LaneChangeEnv`, its ``info``) and the
batched engine (:class:`memrl.envs.batched.BatchedLaneChange`) both call :func:`classify` on
the car rows ``(x, y, heading, speed, curvature)`` of the step that ended in a crash, so an
evaluation through either runner records the same kind and closing speed.

Kinds (:data:`CRASH_KINDS`):

* ``ahead``: the agent's body overlaps a car whose centre lies ahead of it along the road,
  the contact being front-to-back (see below); the agent ran into it.
* ``behind``: the same with the other car's centre behind the agent: hit from behind.
* ``side``: side contact (the other car's centre mostly beside the agent), e.g. during a
  lane change.
* ``road_edge``: no car touches the agent; its body crossed a road edge.

Front-to-back or side: the other car's centre offset (dx, dy) in road coordinates, scaled by
the body (|dx| / length against |dy| / width): which face of the agent's box the contact lies
beyond. This holds when a step of 0.1 s at a large speed difference pushes the bodies deep
into each other (a rear-end contact stays front-to-back). With several cars touching, the
one whose centre is nearest (in those scaled units) is the contact; car contact goes before
the road edge.

Closing speed [m/s]: for a car contact, the relative longitudinal speed toward the other car,
``sign(dx) * (vx_agent - vx_other)`` with ``vx = speed * cos(heading)`` (positive when the
gap was closing; for ``side`` it is the longitudinal part of the relative motion, often near
0); for ``road_edge``, the agent's lateral speed toward the edge it crossed.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.utils import are_polygons_intersecting

from memrl.envs.render import body_corners

CRASH_KINDS = ("ahead", "behind", "side", "road_edge")
"""Kinds of collision; code ``k + 1`` in the engines' integer arrays (0: no crash)."""
NO_CRASH = 0


def kind_name(code: int) -> str:
    """The kind of an integer code (``""`` for :data:`NO_CRASH`)."""
    return "" if int(code) == NO_CRASH else CRASH_KINDS[int(code) - 1]


def _polygon(row: np.ndarray, length: float, width: float) -> np.ndarray:
    """The closed body polygon ``[5, 2]`` (first corner repeated), as highway-env's ``polygon()``."""
    corners = body_corners(np.float64(row[0]), np.float64(row[1]), np.float64(row[2]), length, width)
    return np.vstack([corners, corners[:1]])


def classify(agent: np.ndarray, others: np.ndarray, lane_width: float, lanes_count: int,
             length: float, width: float) -> tuple[int, float]:
    """Kind code (index in :data:`CRASH_KINDS` + 1) and closing speed [m/s] of the agent's crash.

    Args:
        agent: the agent's row ``(x, y, heading, speed, curvature)`` at the crash.
        others: the other cars' rows ``[K, 5]`` (K may be 0).
        lane_width, lanes_count: the road.
        length, width: the car body [m].

    Returns ``(NO_CRASH, 0.0)`` when nothing touches (not a crash state).
    """
    agent = np.asarray(agent, dtype=np.float64)
    others = np.asarray(others, dtype=np.float64).reshape(-1, 5)
    vx_a = agent[3] * np.cos(agent[2])
    own = _polygon(agent, length, width)
    best: tuple[float, int, float] | None = None  # (scaled distance, code, closing speed)
    zero = np.zeros(2)
    for row in others:
        if not are_polygons_intersecting(own, _polygon(row, length, width), zero, zero)[0]:
            continue
        dx, dy = row[0] - agent[0], row[1] - agent[1]
        sx, sy = abs(dx) / length, abs(dy) / width
        if sx >= sy:
            code = CRASH_KINDS.index("ahead" if dx >= 0 else "behind") + 1
        else:
            code = CRASH_KINDS.index("side") + 1
        closing = float(np.sign(dx) * (vx_a - row[3] * np.cos(row[2])))
        if best is None or max(sx, sy) < best[0]:
            best = (max(sx, sy), code, closing)
    if best is not None:
        return best[1], best[2]
    y = own[:4, 1]
    vy = float(agent[3] * np.sin(agent[2]))
    if y.min() < -0.5 * lane_width:  # the edge on the low-y side
        return CRASH_KINDS.index("road_edge") + 1, -vy
    if y.max() > (lanes_count - 0.5) * lane_width:
        return CRASH_KINDS.index("road_edge") + 1, vy
    return NO_CRASH, 0.0


def classify_rows(state: Any, present: Any, lane_width: float, lanes_count: int, length: float,
                  width: float) -> tuple[int, float]:
    """:func:`classify` of one env's car slots ``[C, 5]`` (slot 0 the agent) and presence ``[C]``."""
    state, present = np.asarray(state), np.asarray(present, dtype=bool)
    return classify(state[0], state[1:][present[1:]], lane_width, lanes_count, length, width)
