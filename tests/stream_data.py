"""Transitions of S envs stepped together, as the batched trainer writes them: one TensorDict of
``[S]`` rows per env step, row i = env i, stacks as ``CatFrames(padding="same")`` makes them."""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict

STACK = 4


def frame(k: int, size: int) -> np.ndarray:
    """A small frame that tells its number ``k`` apart from every other (3 bytes of it)."""
    f = np.full((size, size), (7 * k) % 256, dtype=np.uint8)
    f.reshape(-1)[:3] = [k % 256, (k // 256) % 256, (k // 65536) % 256]
    return f


def stream_steps(streams: int, steps: int, seed: int = 0, max_len: int = 12, size: int = 4,
                 lengths: list[list[int]] | None = None) -> list[TensorDict]:
    """``steps`` writes of ``streams`` rows; each env runs episodes of random lengths.

    Args:
        streams: envs ``S``.
        steps: env steps (writes).
        seed: draws episode lengths (1 to ``max_len``) and rewards.
        max_len: longest random episode.
        size: frame height and width.
        lengths: per env, the episode lengths to run first (then random ones).
    """
    rng = np.random.default_rng(seed)
    queue = [list(x) for x in lengths] if lengths is not None else [[] for _ in range(streams)]
    left = [0] * streams  # steps left in each env's episode
    stack = [[0] * STACK for _ in range(streams)]
    next_id, row_id, out = 1, 0, []
    for _ in range(steps):
        p, q, done = [], [], []
        for s in range(streams):
            if left[s] == 0:  # reset: the reset frame repeated
                left[s] = queue[s].pop(0) if queue[s] else int(rng.integers(1, max_len + 1))
                stack[s] = [next_id] * STACK
                next_id += 1
            nxt = stack[s][1:] + [next_id]
            next_id += 1
            p.append(stack[s])
            q.append(nxt)
            left[s] -= 1
            done.append(left[s] == 0)
            stack[s] = nxt
        frames = lambda ids: torch.from_numpy(  # noqa: E731
            np.stack([np.stack([frame(k, size) for k in row]) for row in ids]))
        d = torch.tensor(done)[:, None]
        term = d & torch.from_numpy(rng.random((streams, 1)) < 0.5)
        out.append(TensorDict({
            "pixels": frames(p), "action": torch.arange(row_id, row_id + streams),
            "is_demo": torch.zeros(streams, dtype=torch.bool),
            "next": {"pixels": frames(q),
                     "reward": torch.from_numpy(rng.normal(size=(streams, 1)).astype(np.float32)),
                     "done": d, "terminated": term, "truncated": d & ~term},
        }, [streams]))
        row_id += streams
    return out
