"""Monte-Carlo returns of stored transitions (prior knowledge, recorded episodes), for
calibration checks of Q-values against what the recorded policy actually got (Cal-QL's
diagnosis, Nakamoto et al. 2023: an offline stage's Q(s, a_demo) against the demos' returns).

Row ``t + 1`` continues row ``t`` when ``t`` is not done and its ``("next", "pixels")`` are row
``t + 1``'s ``pixels`` (datasets store episodes in order, but recipes may cut an episode's tail
or noise steps: content, not position, tells). Along each such chain, ``G_t = r_t + gamma
G_(t+1)``; at a chain's end the sum stops. A return is *known* where the chain ends in a
termination (a crash: nothing follows) or at least ``horizon`` steps later (what the cut
misses weighs at most ``gamma^horizon`` of a return). Hand-written: TorchRL's value estimators
bootstrap from a value network, and its ``MultiStepTransform`` sums a fixed number of steps.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

CHUNK = 1024
"""Rows compared at once (two uint8 stacks of 28 KB each per row)."""


def continues(td: TensorDictBase) -> torch.Tensor:
    """``[N]`` bool: row ``t + 1`` continues row ``t`` (the last row: False)."""
    n = td.shape[0]
    out = torch.zeros(n, dtype=torch.bool)
    done = td.get(("next", "done")).reshape(n)
    for lo in range(0, n - 1, CHUNK):
        hi = min(lo + CHUNK, n - 1)
        nxt = td.get(("next", "pixels"))[lo:hi]
        following = td.get("pixels")[lo + 1:hi + 1]
        out[lo:hi] = (nxt == following).flatten(1).all(1) & ~done[lo:hi]
    return out


def mc_returns(td: TensorDictBase, gamma: float, horizon: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
    """``(G [N] float64, known [N] bool)`` of the rows of ``td`` (module docstring)."""
    n = td.shape[0]
    reward = td.get(("next", "reward")).reshape(n).to(torch.float64).tolist()
    terminated = td.get(("next", "terminated")).reshape(n).tolist()
    link = continues(td).tolist()
    g, known = [0.0] * n, [False] * n
    ahead, ends_in_crash, after = 0.0, False, 0  # the next row's return, its chain's end, steps to it
    for t in range(n - 1, -1, -1):
        if link[t]:
            ahead, after = gamma * ahead, after + 1
        else:
            ahead, ends_in_crash, after = 0.0, bool(terminated[t]), 0
        ahead += reward[t]
        g[t], known[t] = ahead, ends_in_crash or after >= horizon
    return torch.tensor(g, dtype=torch.float64), torch.tensor(known)
