"""Env-shaped transitions without an env: random 84x84 frames stacked as ``CatFrames`` does.

The learner and memory benchmarks need many transitions fast; their cost does not depend on
what the frames show, only on the layout, which this reproduces exactly: 4-frame stacks,
the reset frame repeated at an episode start (``padding="same"``), ``("next", "pixels")``
the stack shifted by one frame, episodes of 1 to ``max_len`` steps.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch
from tensordict import TensorDict


def episodes(total: int, seed: int = 0, max_len: int = 300, size: int = 84,
             stack: int = 4) -> Iterator[TensorDict]:
    """Episodes of transitions (``TRANSITION_KEYS`` layout), ``total`` transitions in all."""
    rng = np.random.default_rng(seed)
    made = 0
    while made < total:
        n = min(int(rng.integers(1, max_len + 1)), total - made)
        frames = rng.integers(0, 256, (n + 1, size, size), dtype=np.uint8)  # frame 0: reset
        t = np.arange(n)[:, None] + np.arange(stack)[None, :] - (stack - 1)
        pixels = torch.from_numpy(frames[np.clip(t, 0, None)])
        next_pixels = torch.from_numpy(frames[np.clip(t + 1, 0, None)])
        terminated = torch.zeros(n, 1, dtype=torch.bool)
        terminated[-1] = bool(rng.random() < 0.5)  # a crash, else a truncation
        truncated = torch.zeros(n, 1, dtype=torch.bool)
        truncated[-1] = not bool(terminated[-1])
        yield TensorDict({
            "pixels": pixels, "action": torch.from_numpy(rng.integers(0, 9, n)),
            "is_demo": torch.zeros(n, dtype=torch.bool),
            "next": {"pixels": next_pixels,
                     "reward": torch.from_numpy(rng.normal(size=(n, 1)).astype(np.float32)),
                     "done": terminated | truncated, "terminated": terminated,
                     "truncated": truncated},
        }, [n])
        made += n
