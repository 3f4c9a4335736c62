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
                 lengths: list[list[int]] | None = None, stride: int = 1) -> list[TensorDict]:
    """``steps`` writes of ``streams`` rows; each env runs episodes of random lengths.

    Args:
        streams: envs ``S``.
        steps: env steps (writes).
        seed: draws episode lengths (1 to ``max_len``) and rewards.
        max_len: longest random episode.
        size: frame height and width.
        lengths: per env, the episode lengths to run first (then random ones).
        stride: k, stacks ``[f(t-3k), f(t-2k), f(t-k), f(t)]`` (``f(s) = f(0)`` for s < 0).
    """
    rng = np.random.default_rng(seed)
    queue = [list(x) for x in lengths] if lengths is not None else [[] for _ in range(streams)]
    left = [0] * streams  # steps left in each env's episode
    seen = [[0] for _ in range(streams)]  # each env's frame ids this episode, oldest first
    span = (STACK - 1) * stride + 1

    def strided(ids: list[int]) -> list[int]:
        ids = [ids[0]] * max(0, span - len(ids)) + ids[-span:]
        return ids[::stride]

    next_id, row_id, out = 1, 0, []
    for _ in range(steps):
        p, q, done = [], [], []
        for s in range(streams):
            if left[s] == 0:  # reset: the reset frame repeated
                left[s] = queue[s].pop(0) if queue[s] else int(rng.integers(1, max_len + 1))
                seen[s] = [next_id]
                next_id += 1
            p.append(strided(seen[s]))
            seen[s].append(next_id)
            next_id += 1
            q.append(strided(seen[s]))
            left[s] -= 1
            done.append(left[s] == 0)
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
