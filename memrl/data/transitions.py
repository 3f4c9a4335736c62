"""The transition layout shared by agent data, prior knowledge and the replay buffers."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from memrl.modules.risk import TASK_ACTION_KEY

TRANSITION_KEYS: tuple = (
    "pixels", "action", "is_demo",
    ("next", "pixels"), ("next", "reward"), ("next", "done"), ("next", "terminated"),
    ("next", "truncated"),
)
"""Keys a stored transition has: stacked uint8 pixels ``[4, 84, 84]`` before and after, the
action index, reward ``[1]``, done flags ``[1]`` and the ``is_demo`` flag."""



def to_transitions(td: TensorDictBase, is_demo: bool = False) -> TensorDictBase:
    """Keep only :data:`TRANSITION_KEYS` (and :data:`TASK_ACTION_KEY` where ``td`` has it) of
    env-step data (a ``[T]`` rollout) and set ``is_demo``."""
    optional = (TASK_ACTION_KEY,) if TASK_ACTION_KEY in td.keys() else ()
    out = td.select(*(k for k in TRANSITION_KEYS if k != "is_demo"), *optional, strict=True)
    out.set("is_demo", torch.full(td.batch_size, is_demo, dtype=torch.bool))
    return out
