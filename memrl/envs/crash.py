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

from memrl.envs.batched_physics import overlap
from memrl.envs.render import body_corners

CRASH_KINDS = ("ahead", "behind", "side", "road_edge")
"""Kinds of collision; code ``k + 1`` in the engines' integer arrays (0: no crash)."""
NO_CRASH = 0
_CODE = {kind: i + 1 for i, kind in enumerate(CRASH_KINDS)}


def kind_name(code: int) -> str:
    """The kind of an integer code (``""`` for :data:`NO_CRASH`)."""
    return "" if int(code) == NO_CRASH else CRASH_KINDS[int(code) - 1]


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
    others = np.asarray(others, dtype=np.float64).reshape(1, -1, 5)
    present = np.ones(others.shape[:2], dtype=bool)
    agent = np.asarray(agent, dtype=np.float64).reshape(1, 5)
    kind, closing = classify_batch(agent, others, present, lane_width, lanes_count, length, width)
    return int(kind[0]), float(closing[0])


def classify_batch(agent: Any, others: Any, present: Any, lane_width: float, lanes_count: int, length: float,
                   width: float, touch: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`classify` of M crashes at once: kind codes ``[M]`` (int64) and closing speeds
    ``[M]`` (float64) of the agents' rows ``[M, 5]`` among the other cars' slots ``[M, K, 5]``,
    of which those ``present [M, K]`` count (numpy arrays; the reference env passes one row).
    ``touch [M, K]``: which of them touch the agent, when the caller has tested it already
    (the batched engine's collision test: :func:`memrl.envs.batched_physics.overlap`)."""
    agent = np.asarray(agent, dtype=np.float64).reshape(-1, 5)
    others = np.asarray(others, dtype=np.float64).reshape(len(agent), -1, 5)
    present = np.asarray(present, dtype=bool).reshape(others.shape[:2])
    if touch is not None:
        touch = present & np.asarray(touch, dtype=bool).reshape(present.shape)
    elif others.shape[1]:
        touch = present & overlap(np.broadcast_to(agent[:, None], others.shape), others, length, width)
    else:
        touch = present.copy()
    dx, dy = others[..., 0] - agent[:, None, 0], others[..., 1] - agent[:, None, 1]
    sx, sy = abs(dx) / length, abs(dy) / width
    code = np.where(sx >= sy, np.where(dx >= 0, _CODE["ahead"], _CODE["behind"]), _CODE["side"])
    vx_a = agent[:, 3] * np.cos(agent[:, 2])
    closing = np.sign(dx) * (vx_a[:, None] - others[..., 3] * np.cos(others[..., 2]))
    # the contact: the touching car whose centre is nearest in body-scaled units (the first of equals)
    nearest = np.argmin(np.where(touch, np.maximum(sx, sy), np.inf), -1) if others.shape[1] else 0
    rows = np.arange(len(agent))
    hit = touch.any(-1)
    # no car touches: a road edge crossed (the agent's lateral speed toward it), else no crash
    y = body_corners(agent[:, 0], agent[:, 1], agent[:, 2], length, width)[..., 1]
    vy = agent[:, 3] * np.sin(agent[:, 2])
    low, high = y.min(-1) < -0.5 * lane_width, y.max(-1) > (lanes_count - 0.5) * lane_width
    edge = np.where(low | high, _CODE["road_edge"], NO_CRASH)
    edge_closing = np.where(low, -vy, np.where(high, vy, 0.0))
    if not others.shape[1]:
        return edge.astype(np.int64), edge_closing
    return (np.where(hit, code[rows, nearest], edge).astype(np.int64),
            np.where(hit, closing[rows, nearest], edge_closing))
